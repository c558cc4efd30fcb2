"""ChcrtPass: one trace() call of chcrt on one pair front (Algorithm 1, chcrt.py), and the steps its
three modes share (binding, clears, the records' draws, the tile bounds). The modes are mixins: a
front's first passes read their queries back within the pass (chcrt_pass_sync.py), later ones are
GPU-driven with the front on the host (chcrt_pass_gpu.py) or on the device (chcrt_pass_device.py)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.chcrt.chcrt_cache import MB
from viewer.backends.chcrt.chcrt_devfront import FRONT_SSBO
from viewer.backends.chcrt.chcrt_front import INNER, INVISIBLE, VISIBLE, PairFront, to_finest_tiles
from viewer.backends.chcrt.chcrt_layout import (
    BIND_CHC_COUNT,
    BIND_CHC_DRAWS,
    BIND_CHC_TILES,
    BIND_IMG_CHC_BATCH,
    BIND_IMG_CHC_BEST,
    BIND_IMG_CHC_OVERDRAW,
    COUNT_BYTES,
    DRAW_DTYPE,
    HINT_UNIT,
    ITEM_DTYPE,
    TILE_BOUND_BYTES,
)
from viewer.backends.chcrt.chcrt_pass_device import DeviceFrontSteps
from viewer.backends.chcrt.chcrt_pass_gpu import GpuDrivenSteps
from viewer.backends.chcrt.chcrt_pass_sync import SyncSteps
from viewer.effects import RayType
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_COUNTERS, BIND_NODES, BIND_TRIS
from viewer.gl.textures import clear_float_texture, clear_int_texture
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.screen_tiles import tile_rects

if TYPE_CHECKING:
    from viewer.backends.chcrt.chcrt import ChcrtBackend


class ChcrtPass(SyncSteps, GpuDrivenSteps, DeviceFrontSteps):
    """One trace() call: Algorithm 1 on one front."""

    def __init__(self, be: ChcrtBackend, front: PairFront, rays: RayBatch, ray_type: RayType,
                 hits: HitBuffer, pinfo: PassInfo | None = None):
        self.be = be
        self.hits = hits
        self.pinfo = pinfo or PassInfo(ray_type, 0, 0, 1.0)
        self.ctx = be.ctx
        self.p = be.p
        self.nt = be.nt
        self.front = front
        self.rays = rays
        self.ray_type = ray_type
        self.any_hit = ray_type.any_hit
        self.tg = be.targets
        self.hit_fbo = self.tg.hit_framebuffer(self.ctx, hits)
        self.size = rays.size
        self.stats = {k: 0 for k in ("queries", "multi_queries", "failed_multi_queries", "visible_pairs",
                                     "invisible_pairs", "subtrees_scheduled", "draws", "rays",
                                     "intersect_draws", "batch_tiles", "tile_batches_1", "tile_batches_2",
                                     "tile_batches_3plus", "query_waves", "pull_ups", "phase1_subtrees",
                                     "query_pixels", "requeries", "batches", "upload_bvh_mb", "upload_geom_mb",
                                     "lca_tiles", "gpu_driven", "newly_visible_queries", "query_records_drawn",
                                     "full_bvh_passes", "work_probe_passes", "wasted_front_passes",
                                     "shared_front_passes", "shared_plan_passes")}
        self.rep: tuple[np.ndarray, np.ndarray] | None = None  # representative rays per finest tile
        self.rays_read = False
        self.threshold = int(self.p.visible_threshold)
        # the split rule's t_q of this front (times t_q_primary for camera rays)
        self.t_q = self.p.t_q * (self.p.t_q_primary if ray_type == RayType.PRIMARY else 1.0)
        self.tri_bound = self.p.subtree_tri_bound(ray_type)  # (the front's scheduled subtrees)
        self.overlays = bool(self.p.overdraw_overlay and be.overlays_enabled)
        # GPU-driven steady state: a front's first pass (and its next ones while its refinement is
        # unfinished, cold_passes) runs the synchronous algorithm (builds the front), unless the front
        # starts on the device (ChcrtParams.cold_start: front.cold is False from the start)
        self.gpu = be.gpu_driven and (front.frames > 0 or be.device_cold) and not front.cold
        self.culled = False  # this pass's queries went through the coarse cull (stats read late)
        self.n_survivor_groups = 0
        self.survivor_items: moderngl.Buffer | None = None  # the survivors' items (None: be.kept_boxes)
        self.cull_taken: tuple | None = None  # the cull in the device fronts' buffers (run)
        self.rays_taken: tuple | None = None  # the rays counted in them (run)
        self.cull_by_reach = False  # device fronts: this pass culls by reach alone (_run_device)
        self.probe_base = -1  # work_probe: META index the pass's draws sum their work into (-1: no probe)
        self.lca_pairs: np.ndarray | None = None  # GPU-driven: slots of visible pairs drawn through an LCA
        self.untested: np.ndarray | None = None  # GPU-driven: invisible pairs only covered by LCA traversals
        self.refine_from = 0  # query fragments spent before the synchronous refinement (cold_query_budget)
        self.bounds = np.zeros((0, 2, 4), np.int64)  # the last _run_queries' passing bounds per query and box
        # hit_hint: the front's last hit triangle per pixel (None: first pass, or hints off)
        self.hint = be.hints.get(self.pinfo.key) if be.use_hints else None

    def _bind(self) -> None:
        be, tg = self.be, self.tg
        be.bc.gpu_scene.bind()
        if be.cache is not None:  # out-of-core: the intersection reads nodes and triangles from the cache
            be.cache.bind(BIND_NODES, BIND_TRIS)
            be.bc.gpu_scene.bind_texels(be.cache.nodes_buf, be.cache.tris_buf)
            be.cache.begin_pass()
        self.rays.origin.use(0)
        self.rays.direction.use(1)
        if self.hint is not None:
            self.hint.use(HINT_UNIT)
        tg.best.bind_to_image(BIND_IMG_CHC_BEST, read=True, write=True)
        tg.overdraw.bind_to_image(BIND_IMG_CHC_OVERDRAW, read=True, write=True)
        tg.batch.bind_to_image(BIND_IMG_CHC_BATCH, read=True, write=True)
        if self.gpu:
            self.be.gpu_counts.bind_to_storage_buffer(BIND_CHC_COUNT, 0, COUNT_BYTES)
        else:
            self.be.count_buf.bind_to_storage_buffer(BIND_CHC_COUNT)

    def _init(self, zeroed: bool = False) -> None:
        """The init draw (hits, depth, images cleared; active rays counted); `zeroed`: the ray-count
        slots were zeroed on the device already (device fronts), else they are written here."""
        ctx = self.ctx
        if not zeroed:
            (self.be.gpu_counts if self.gpu else self.be.count_buf).write(self.be._zero_counts)
            iostats.to_device(COUNT_BYTES)
        fbo = self.hit_fbo
        fbo.use()
        fbo.scissor = None
        fbo.depth_mask = True
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "1"
        # the overlay images are cleared whenever the renderer wants overlays (shown, even if uncounted)
        self.be.prog_init["countOverlays"] = int(self.be.overlays_enabled)
        # its stores land after the last pass's image atomics (bestBits, overlay counts), not under them
        ctx.memory_barrier(moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        self.be.quad.render(self.be.prog_init)  # draws through FullscreenQuad are counted there
        # the next draws prune with bestBits and count into the images and SSBOs this one reset:
        # without the barrier a GPU may run them on last pass's values (llvmpipe runs in order)
        ctx.memory_barrier(moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.stats["draws"] += 1

    def _count_rays(self) -> None:
        """The pass's active rays into the ray-count slots (zeroed on the device), in place of the
        init draw of a pass that traces the whole BVH, by chc_count_rays.comp: one invocation copies
        the ray generation's count into slot 0 where it made one (PassInfo.ray_count; instead of
        reading every ray, 0.7 ms at 640x360 on llvmpipe), else it counts the rays. (Not a buffer
        copy: on NVIDIA that one made the host wait for the GPU in every pass, chc_count_rays.comp.)"""
        count = self.pinfo.ray_count
        prog = self.be.count_rays
        w, h = self.size
        prog["raySize"] = (w, h)
        prog["copySlot"] = -1 if count is None else count.offset // 4
        if count is not None:
            # (after the ray generation's atomics and the slots' zeroing: shader writes, then a read)
            self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
            count.buffer.bind_to_storage_buffer(BIND_COUNTERS)
            prog.run(1, 1)
        else:
            prog.run(-(-w // 64), -(-h // 64))  # a work group per 64x64 pixel region
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.stats["draws"] += 1
        iostats.gl_draw()

    def _clear_hits(self) -> None:
        """The init draw's clears without the draw (a device pass whose tile bounds initialise the
        rays): hits none (t = inf, id -1), no hit subtree, depth 1 everywhere (a pixel without a ray
        keeps it: every intersection draw discards on its bestBits first). Overlay images are
        not touched (overlays take the init draw)."""
        tg, hits = self.tg, self.hits
        clear_float_texture(hits.t, float("inf"))
        clear_int_texture(hits.id, -1)
        clear_int_texture(tg.subtree, -1)
        clear_float_texture(tg.depth, 1.0)

    def _gather(self) -> None:
        """Representative rays per finest tile, for the front-to-back order of subtrees."""
        tg = self.tg
        prog = self.be.prog_gather
        prog["raySize"] = tuple(self.size)
        prog["level"] = self.front.max_level
        self.ctx.disable(moderngl.DEPTH_TEST)
        tg.gather_fbo.use()
        tg.gather_fbo.scissor = None
        self.be.quad.render(prog)
        self.stats["draws"] += 1
        g = tg.gather_size[0]
        o, d = (np.frombuffer(glio.read(tg.gather_fbo, components=4, dtype="f4", attachment=a),
                              np.float32).reshape(g, g, 4) for a in (0, 1))
        self.rep = (o, d)
        self.ctx.enable(moderngl.DEPTH_TEST)

    def _sync(self) -> None:
        if self.p.sync_phases:
            self.ctx.finish()

    def _read_ray_count(self) -> None:
        if not self.rays_read:
            self.stats["rays"] = int(np.frombuffer(glio.read(self.be.count_buf), np.uint32).sum())
            self.rays_read = True

    def _order_keys(self, pairs: np.ndarray) -> np.ndarray:
        """Sort key within a tile: distance from the tile's representative ray origin to the box
        (front to back) where we have one, else more visible pixels first."""
        f = self.front
        if self.rep is None:
            return -f.pixels[pairs].astype(np.float64)
        o, d = self.rep
        shift = f.max_level - f.level[pairs].astype(np.int64)
        gx = np.minimum(f.tx[pairs].astype(np.int64) << shift, o.shape[1] - 1)
        gy = np.minimum(f.ty[pairs].astype(np.int64) << shift, o.shape[0] - 1)
        org = o[gy, gx, :3].astype(np.float64)
        valid = d[gy, gx, 3] > o[gy, gx, 3]
        nd = f.node[pairs]
        lo = self.nt.box_min[nd].astype(np.float64)
        hi = self.nt.box_max[nd].astype(np.float64)
        gap = np.maximum(np.maximum(lo - org, org - hi), 0.0)
        dist = np.sqrt((gap * gap).sum(axis=1))
        return np.where(valid, dist, -f.pixels[pairs].astype(np.float64))

    def _draw_subtrees(self, pairs: np.ndarray, slots: np.ndarray | None = None) -> None:
        """Intersect scheduled pairs: grouped by tile, up to max_batch subtree roots per batch.
        `slots` (GPU-driven): per pair, the count slot its rays' box entries are counted into."""
        if len(pairs) == 0:
            return
        f = self.front
        self.stats["subtrees_scheduled"] += len(pairs)
        nd, lvl, tx, ty = (f.node[pairs].astype(np.int64), f.level[pairs].astype(np.int64),
                           f.tx[pairs].astype(np.int64), f.ty[pairs].astype(np.int64))
        sl = np.full(len(pairs), -1, np.int64) if slots is None else np.asarray(slots, np.int64)
        if self.gpu:
            # the GPU-driven pass never splits a tile into batches (closest-hit passes order a
            # record's items by gap on the device: chc_visorder.comp); merged, a pixel's subtrees of
            # every tile level are one record: one fragment traverses them all with one shrinking tmax
            if self.p.merge_tiles:
                nd, lvl, tx, ty, sl = to_finest_tiles(nd, lvl, tx, ty, sl)
            keys = np.zeros(len(nd))
        else:
            keys = self._order_keys(pairs)
        tile = (lvl << 40) | (tx << 20) | ty
        order = np.lexsort((keys, tile))
        nd, lvl, tx, ty, tile, sl = nd[order], lvl[order], tx[order], ty[order], tile[order], sl[order]
        starts = np.flatnonzero(np.r_[True, tile[1:] != tile[:-1]])
        ends = np.r_[starts[1:], len(nd)]
        rects = tile_rects(lvl[starts], tx[starts], ty[starts], self.size)
        lca_max = self.p.lca_subtrees
        if lca_max > 0 and self.be.cache is None and ((ends - starts) > lca_max).any():
            # tiles that see many subtrees traverse their lowest common ancestor once
            many = (ends - starts) > lca_max
            lca = self.nt.group_lca(nd, starts)
            keep = ~np.repeat(many, ends - starts)
            covered = sl[~keep]
            self.lca_pairs = covered[covered >= 0]
            tile_of_item = np.repeat(np.arange(len(starts)), ends - starts)
            nd = np.concatenate([nd[keep], lca[many]])
            sl = np.concatenate([sl[keep], np.full(int(many.sum()), -1, np.int64)])  # not counted
            tile_of_item = np.concatenate([tile_of_item[keep], np.flatnonzero(many)])
            o = np.argsort(tile_of_item, kind="stable")
            nd, sl = nd[o], sl[o]
            counts = np.bincount(tile_of_item, minlength=len(starts))
            starts = np.cumsum(counts) - counts
            ends = starts + counts
            self.stats["lca_tiles"] += int(many.sum())
        self._draw_batches(nd, sl, rects, starts, ends)

    def _draw_batches(self, nd: np.ndarray, sl: np.ndarray, rects: np.ndarray, starts: np.ndarray,
                      ends: np.ndarray, finest: np.ndarray | None = None) -> None:
        """Draw the items nd[starts[i]:ends[i]] over tile rectangle rects[i] (nearest first where
        sorted), in batches of at most max_batch items per record. `finest` (GPU-driven, gap_order):
        the finest tile index of each rectangle; the records' items are then sorted by their gap
        from the tile's ray origins on the GPU before the draw (_order_by_gap)."""
        mb = self.p.max_batch
        self.be.items.upload(self._subtree_items(nd, sl))
        self.be.bind_items(self.be.items.buf)
        # batches: per tile, consecutive runs of at most max_batch subtrees (nearest first)
        nbatch = -(-(ends - starts) // mb)
        tile_of = np.repeat(np.arange(len(starts)), nbatch)
        k = np.arange(len(tile_of)) - np.repeat(np.cumsum(nbatch) - nbatch, nbatch)
        bstart = starts[tile_of] + k * mb
        bcount = np.minimum(mb, ends[tile_of] - bstart)
        live = (rects[tile_of, 2] > 0) & (rects[tile_of, 3] > 0)
        self.stats["tile_batches_1"] += int((nbatch == 1).sum())
        self.stats["tile_batches_2"] += int((nbatch == 2).sum())
        self.stats["tile_batches_3plus"] += int((nbatch >= 3).sum())
        self.stats["batch_tiles"] += len(starts)
        self.stats["batches"] += int(live.sum())
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        fbo = self.hit_fbo
        fbo.use()
        if self.be.batched:
            prog = self.be.prog_isect_g if self.gpu else self.be.prog_isect_b
            prog["raySize"] = tuple(self.size)
            recs = np.zeros(int(live.sum()), DRAW_DTYPE)
            recs["rect"] = rects[tile_of[live]]
            recs["info"][:, 0] = bstart[live]
            recs["info"][:, 1] = bcount[live]
            if finest is not None:
                recs["info"][:, 3] = finest[tile_of[live]]
            self.be.draws.upload(recs)
            draws = 0
            if len(recs) and finest is not None:
                self._order_by_gap(len(recs))
                fbo.use()
            if len(recs):
                fbo.scissor = None
                self._isect_uniforms(prog)
                (self.be.vao_isect_g if self.gpu else self.be.vao_isect_b).render(
                    moderngl.TRIANGLES, vertices=6, instances=len(recs))
                draws = 1
                iostats.gl_draw()  # an instanced draw straight on the VAO (quads count themselves)
        else:
            prog = self.be.prog_isect
            self._isect_uniforms(prog)
            u_base, u_count = prog["itemBase"], prog["itemCount"]
            render = self.be.quad.render
            draws = 0
            rect_list = rects.tolist()
            for t, b, c in zip(tile_of[live].tolist(), bstart[live].tolist(), bcount[live].tolist(), strict=True):
                fbo.scissor = tuple(rect_list[t])
                u_base.value = b
                u_count.value = c
                render(prog)
                draws += 1
        self.stats["intersect_draws"] += draws
        self.stats["draws"] += draws

    def _tile_bounds(self, level: int, tiles: int, init_rays: bool = False) -> None:
        """The ray-origin box and farthest reach of each of the `tiles` tiles of `level`
        (chc_tilebounds.comp, one dispatch) into be.tile_bounds (grown when too small), after the
        image writes of the draw before it (bestBits); `init_rays`: there was no init draw
        (_clear_hits), this dispatch sets bestBits from the rays and counts them."""
        be, ctx = self.be, self.ctx
        if be.tile_bounds.size < TILE_BOUND_BYTES * tiles:
            be.tile_bounds.release()
            be.tile_bounds = ctx.buffer(reserve=TILE_BOUND_BYTES * tiles)
        be.tile_bounds.bind_to_storage_buffer(BIND_CHC_TILES)
        ctx.memory_barrier(moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        comp = be.tilebounds_init if init_rays else be.tilebounds
        comp["raySize"] = tuple(self.size)
        comp["level"] = level
        comp.run(tiles)
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT
                           | (moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT if init_rays else 0))

    def _order_by_gap(self, nrec: int) -> None:
        """gap_order, before the visible pairs' draw: the ray origin box of every finest tile
        (chc_tilebounds.comp), then per record its items' gaps from it and the items sorted by gap
        (chc_visorder.comp), in place in the items buffer. Two dispatches whatever the tiles."""
        be, ctx = self.be, self.ctx
        level = self.front.max_level
        self._tile_bounds(level, 1 << (2 * level))  # after the init draw's bestBits
        be.visorder["nRecords"] = nrec
        be.visorder["coneCull"] = int(self.p.cone_cull)
        be.visorder.run(-(-nrec // 64))
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.TEXTURE_FETCH_BARRIER_BIT)
        self.stats["draws"] += 2
        iostats.gl_draw(2)

    def _subtree_items(self, nd: np.ndarray, slots: np.ndarray | None = None) -> np.ndarray:
        """Intersection items of scheduled subtrees (canonical BVH nodes `nd`); p2 = the count slot
        of the pair (GPU-driven), -1 for none."""
        nt = self.nt
        items = np.zeros(len(nd), ITEM_DTYPE)
        items["bmin"] = nt.box_min[nd]
        items["bmax"] = nt.box_max[nd]
        items["ref"] = nt.gpu_ref[nd] if self.be.cache is None else self.be.cache.item_refs(nd)
        items["count"] = nt.gpu_count[nd]
        items["id"] = nd
        items["p0"] = self.be.bvh_first[nd]
        items["p1"] = nt.count[nd]
        items["p2"] = -1 if slots is None else slots
        return items

    def _isect_uniforms(self, prog: moderngl.Program) -> None:
        prog["anyHit"] = int(self.any_hit)
        prog["countOverlays"] = int(self.overlays)
        # not in a pass captured for the overlays: there every hit names the scheduled subtree that
        # holds it (subtree_batches), and a hint's triangle need not lie in this tile's subtrees
        prog["useHint"] = int(self.hint is not None and not self.overlays)
        if prog.get("gapOrder", None) is not None:
            prog["gapOrder"] = int(self.p.gap_order)
        if prog.get("mergeKept", None) is not None:
            prog["mergeKept"] = 0  # set by the draw of a device front's visible records (merge_kept)

    def run(self) -> dict[str, float]:
        be, f = self.be, self.front
        # the cull a later sample may take (DeviceFronts.cull_key): whatever this pass does next, it
        # names the buffers' cull again only if it leaves them as they are
        self.cull_taken = self.rays_taken = None
        if be.devfronts is not None:
            self.cull_taken, be.devfronts.cull_key = be.devfronts.cull_key, None
            self.rays_taken, be.devfronts.rays_key = be.devfronts.rays_key, None
        self._sync()  # diagnostics: do not charge the ray generation to phase 1
        try:
            if self.gpu and be.device_front:
                self._run_device()
            elif self.gpu:
                self._run_gpu()
            else:
                self._run_sync()
        finally:
            if be.cache is not None:
                be.bc.gpu_scene.bind()  # later passes (shading) read the scene's triangles
                t = be.cache.t
                self.stats.update(upload_bvh_mb=t.bvh_bytes / MB, upload_geom_mb=t.geom_bytes / MB,
                                  subtrees_uploaded=t.uploads, cache_hits=t.hits, cache_evictions=t.evictions,
                                  upload_syncs=t.syncs, in_core_pct=100.0 * be.cache.plan.in_core_fraction)
            self.ctx.disable(moderngl.DEPTH_TEST)
            self.ctx.depth_func = "<"
            self.hit_fbo.scissor = None
            self.tg.query_fbo.scissor = None
        # a device front counts these on the device (ChcrtBackend.end_frame); a GPU-driven pass that traced
        # the whole BVH left its front as it is (not pulled up, not counted)
        if f.device is None and not (self.gpu and self.stats["full_bvh_passes"]):
            self.stats["pull_ups"] = f.pull_up(1 if be.gpu_driven else 0)
            self.stats["visible_pairs"] = int((f.state[: f.n] == VISIBLE).sum())
            self.stats["invisible_pairs"] = int((f.state[: f.n] == INVISIBLE).sum())
            self.stats["inner_pairs"] = int((f.state[: f.n] == INNER).sum())
        self.stats["gpu_driven"] = int(self.gpu)
        self.stats["device_front_passes"] = int(f.device is not None)
        if be.device_front and self.p.temporal and f.device is None and not (f.full_bvh or f.cold):
            # the front's synchronous refinement is done: it moves to the device now (one upload)
            f.device = be.device_fronts().attach(f, 1 << (2 * f.max_level))
        return {k: float(v) for k, v in self.stats.items()}

    def _heavy_tiles(self, cv: np.ndarray, ci: np.ndarray) -> np.ndarray:
        """Per finest tile (visible pair counts `cv`, invisible `ci`): does it traverse the lowest
        common ancestor of its pairs instead of testing them (over `lca_subtrees` visible pairs or
        `lca_pairs` pairs in all; never for primary rays unless `lca_primary`)?"""
        heavy = np.zeros(cv.shape, bool)
        if self.ray_type == RayType.PRIMARY and not self.p.lca_primary:
            return heavy
        if self.p.lca_subtrees > 0:
            heavy |= cv > self.p.lca_subtrees
        if self.p.lca_pairs > 0:
            heavy |= cv + ci > self.p.lca_pairs
        return heavy

    def _queries_and_traversal(self, full: bool, cull: Callable[[], None] | None) -> None:
        """Phases 2 and 3 of a GPU-driven pass: `cull` (the invisible pairs some ray may still enter,
        into the survivors' records) and their intersection; or, for incoherent rays (`full`), the
        whole BVH for every ray (`cull` None: the cull ran before the visible records, merge_kept).
        Incoherent rays: nearly every tile would traverse from (about) the
        root; the glsl traversal does exactly that, without the per-tile records. (chcrt's own shader
        from the root with the hit hint: the same nodes per diffuse ray, 31.0 against 31.5, and no
        faster: the hint bounds a closest-hit ray that front-to-back order finds early.)"""
        prof = self.be.bc.profiler
        with prof.phase("chc:2-queries"):
            if not full and cull is not None:
                cull()
            self._sync()
        with prof.phase("chc:3-traversal"):
            if full:
                self.be.finisher.run(self.rays, self.pinfo, self.hits)
                self.stats["full_bvh_passes"] = 1
                self.stats["draws"] += 1
            else:
                self._intersect_survivors()
            self._sync()

    def _intersect_survivors(self) -> None:
        """The invisible pairs that survived the cull, in one indirect instanced draw (items: the
        kept pairs, records: the survivors), counting into the pairs' slots."""
        if not self.n_survivor_groups:
            return
        be = self.be
        # the survivors read bestBits as the visible records left it (with merge_kept no dispatch in between)
        self.ctx.memory_barrier(moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        be.bind_items(self.survivor_items or be.kept_boxes)
        be.survivors.bind_to_storage_buffer(BIND_CHC_DRAWS)
        self._draw_records_indirect(be.query_indirect)

    def _use_hit_target(self) -> None:
        """The intersection draws' target: the hit framebuffer, whole, through the depth test (LESS)."""
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.hit_fbo.use()
        self.hit_fbo.scissor = None

    def _draw_records_indirect(self, command: moderngl.Buffer, merge_kept: bool = False) -> None:
        """The records bound at BIND_CHC_DRAWS (items at BIND_CHC_ITEMS) in one indirect instanced
        draw of the counting intersection program, its draw command at the start of `command`;
        `merge_kept`: visible records also test their tiles' merged kept pairs (the tile plans at
        BIND_FR_TILES)."""
        be = self.be
        self._use_hit_target()
        prog, vao = be.prog_isect_g, be.vao_isect_g
        if self.probe_base >= 0:  # work_probe: this pass sums its work on the sampled pixels
            prog, vao, _ = be.probe_programs()
            prog["probeStride"] = int(self.p.work_probe_stride)
            prog["probeBase"] = self.probe_base
            be.device_fronts().meta.bind_to_storage_buffer(FRONT_SSBO["BIND_FR_META"])
        prog["raySize"] = tuple(self.size)
        self._isect_uniforms(prog)
        if prog.get("mergeKept", None) is not None:
            prog["mergeKept"] = int(merge_kept)
        vao.render_indirect(command, moderngl.TRIANGLES, count=1)
        self.stats["draws"] += 1
        self.stats["intersect_draws"] += 1
        iostats.gl_draw()

    def frame_number(self) -> int:
        return self.be.frame

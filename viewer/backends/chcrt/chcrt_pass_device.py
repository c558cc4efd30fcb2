"""chcrt, the GPU-driven pass on a device-resident front (chcrt_devfront.py): a fixed number of
launches, nothing read back within the pass; and the work probe that decides whether a front still
pays. Mixed into ChcrtPass (chcrt_pass.py), whose state and shared steps it uses."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.chcrt.chcrt_devfront import (
    ARGS_VISORDER,
    FRONT_SSBO,
    META_INTS,
    META_PROBE_FRONT,
    DeviceFront,
    DeviceFronts,
)
from viewer.backends.chcrt.chcrt_layout import (
    BIND_CHC_CANDIDATES,
    BIND_CHC_DRAWS,
    BIND_CHC_INDIRECT,
    BIND_CHC_QUERIES,
    BIND_CHC_QUERY_COUNTS,
    COUNT_BYTES,
    COUNT_SLOTS,
    DRAW_DTYPE,
    ITEM_DTYPE,
)
from viewer.effects import RayType
from viewer.gl.textures import copy_texture


class DeviceFrontSteps:
    """The GPU-driven pass with the front on the device."""

    def _run_device(self) -> None:
        """The GPU-driven pass on a device front (chcrt_devfront.py): plan (5 dispatches), the visible
        records (with gap_order in closest-hit passes: 2 dispatches, then one indirect draw), the cull
        (2 dispatches) and the survivors (one indirect draw), the pass's counts, the refinement (4
        dispatches). Nothing is uploaded or read back; the same launches whatever the tiles, pairs and
        subtrees. With merge_kept the cull runs before the visible records (on the same tile bounds
        as their gap order: one dispatch fewer) and most tiles' kept pairs ride in their visible
        record (chc_querycull.comp). A pass that traces the whole BVH (its synchronous refinement
        said so: full_bvh, or its last plan: the device front's `full`) only plans, to refresh what the host
        decides from; one whose front saved too little when last measured (work_probe) does not plan.
        A measuring pass (work_probe) adds one dispatch and draws the probe build of the intersection."""
        be, f, p = self.be, self.front, self.p
        prof = be.bc.profiler
        dv = be.device_fronts()
        level = f.max_level
        n_tiles = 1 << (2 * level)
        dev = f.device  # attached once its refinement was done, unless it found the rays incoherent
        if dev is None and not f.full_bvh:
            if f.frames == 0 and p.cold_start_pairs > 0:
                # a device cold start: its first levels split on the host, as if every pair were entered
                self.stats["presplit_waves"] = f.presplit(self.nt, self.t_q, p.max_subtree_height, self.tri_bound,
                                                          p.cold_start_pairs * n_tiles)
            # (at its first pass: a device cold start, settling from this pass on)
            dev = f.device = dv.attach(f, n_tiles, settled=f.frames > 0)
            # settle_probe: the young front is presumed wasteful until measured (its later sample passes
            # trace the whole BVH; it starts about the root, where its rays do the full traversal's work)
            dev.wasteful = not dev.settled and p.settle_probe and p.work_probe > 0
        full = f.full_bvh or dev.full
        sub = int(p.cull_sublevels)
        while sub > 0 and min(self.size) >> (level + sub) < 4:
            sub -= 1
        # share_sample_fronts: a later sample pass of a shared front in this frame; an any-hit one takes
        # the plan the frame's first left in the device fronts' buffers (no other plan since)
        frame = self.frame_number()
        later = p.share_sample_fronts and dev is not None and dev.decided_frame == frame
        plan_key = None if dev is None else (dev.slot, frame, tuple(self.size), level, sub)
        probe = wasted = False
        if dev is not None:
            no_hint = be.use_hints and self.hint is None
            if later:
                # the frame's first pass decided (no probe); a front found wasteful when last measured
                # sends the frame's other samples through the whole BVH even while its first pass brings
                # it up to date or measures it (warm_up, probe: that one pass is enough for either)
                wasted = not full and (dev.decided_wasted or dev.wasteful)
                dev.shared = True
            elif (not dev.settled and dev.shared and p.settle_probe and p.work_probe > 0 and not full
                  and not no_hint):
                # settle_probe: a settling front shared by later sample passes is measured in the
                # frame's first pass, which still runs and refines it (the front settles only through
                # its own passes); the later samples of the next frame follow that measurement
                probe = True
                dev.decided_frame, dev.decided_wasted = frame, False
            elif (dev.passes == 0 and no_hint) or not dev.settled:
                # the front's first measurement waits for a pass with hit hints (a shared front's first
                # device pass can be a sample's first pass, in the frame that built it): without them
                # its rays do more work than in every later pass (city-near ao:20 at 640x360: 0.73 of
                # the full traversal's tests, against 0.46 a frame later); and no front is measured
                # before it has settled (a device cold start's young front does the full traversal's
                # work and more: city-near's AO front measured 0.70 in its first pass, then traced the
                # whole BVH, unrefined, until its next measurement)
                dev.decided_frame, dev.decided_wasted = frame, False
            else:
                probe, wasted = self._probe_plan(dev, full)
                dev.decided_frame, dev.decided_wasted = frame, wasted
                dev.passes += 1
            full = full or wasted
            dev.work_ratio_full = p.work_ratio_full_any if self.any_hit else p.work_ratio_full
            self.stats["wasted_front_passes"] = int(wasted)
        reuse = later and self.any_hit and not full and dv.last_plan == plan_key
        self.stats["shared_front_passes"] = int(later)  # (its refinement left to the frame's first pass)
        self.stats["shared_plan_passes"] = int(reuse)  # (its plan too)
        capacity = 0 if dev is None else dev.capacity
        need = COUNT_BYTES + 4 * (capacity + 3)
        if be.gpu_counts.size < need:
            be.gpu_counts.release()
            be.gpu_counts = self.ctx.buffer(reserve=1 << (need - 1).bit_length())
        report = self.pinfo.report
        merge = be.merge_kept and sub == 0 and not full
        # without overlays, the init draw is left out: with merged kept pairs the tile bounds
        # below set bestBits and count the rays, texture clears do the rest (chc_tilebounds.comp
        # CHC_INIT_RAYS); a whole-BVH pass only counts its rays (the glsl traversal writes every hit)
        fused = merge and not be.overlays_enabled
        # any-hit rays whose samples share origins, tmax and activity (RayType.samples_share_origins,
        # AO) cull their tiles' invisible pairs by reach alone (their directions fill a hemisphere:
        # without the cone and side planes city-near's AO was no slower, docs/results/chcrt.md), so the
        # cull of the frame's first pass holds for the later samples that take its plan: they keep
        # its outputs, its rays' bestBits and ray counts instead of their own tile bounds and cull
        by_reach = (fused and self.any_hit and p.share_sample_fronts and self.ray_type.samples_share_origins
                    and dev is not None)
        cull_key = (plan_key, capacity, be.gpu_counts.glo)
        take_cull = reuse and by_reach and self.cull_taken == cull_key
        self.cull_by_reach = by_reach
        # a whole-BVH pass counts its rays only for the statistics: one whose samples share their
        # activity keeps the counts an earlier pass of the frame left (rays_key) instead
        shares = self.ray_type.samples_share_origins
        rays_key = (self.frame_number(), int(self.ray_type), tuple(self.size), be.gpu_counts.glo)
        keep_rays = (shares and self.rays_taken == rays_key and not reuse and (dev is None or wasted)
                     and not be.overlays_enabled)
        common = dict(ray_slots=COUNT_SLOTS, frame=self.frame_number(), max_level=level, threshold=self.threshold,
                      requery_interval=p.requery_interval, seed=p.seed, report=report)
        with prof.phase("chc:0-setup"):
            if reuse:
                # the plan stands (records, items, tile plans, arguments): only the pass's counts
                # and the survivors' command zeroed (no tile plan, no front META touched); the cull
                # below still covers every invisible pair for this pass's rays (take_cull: the first
                # pass's cull, by reach, covers them; its outputs, ray counts and command stay)
                dv.clear(be.gpu_counts, be.query_indirect, ray_slots=COUNT_SLOTS, capacity=capacity, slot=0,
                         keep_cull=take_cull)
                self.stats["draws"] += 1
            elif dev is None or wasted:
                # no front, or one that saves too little (work_probe): nothing to plan (the front's
                # META keeps its last plan for the host's decisions), only the pass's counts zeroed
                # (a later sample pass keeps the front's META row: what the frame's first pass measured
                # and the overflows it found, read after the frame)
                dv.clear(be.gpu_counts, be.query_indirect, ray_slots=COUNT_SLOTS, capacity=capacity,
                         slot=0 if dev is None or later else dev.slot, keep_rays=keep_rays)
                self.stats["draws"] += 1
            else:
                primary_only = self.ray_type == RayType.PRIMARY and not p.lca_primary
                dv.plan(dev, be.gpu_counts, be.query_indirect, size=tuple(self.size), max_batch=p.max_batch,
                        lca_pairs=p.lca_pairs, lca_subtrees=p.lca_subtrees, heavy_allowed=not primary_only,
                        cull_sub=sub, count_due_only=p.count_due_only, full=full, reset_meta=not later, **common)
                dv.last_plan = None if full else plan_key
                self.stats["draws"] += 3 if full else 5
            self._bind()
            if fused:
                self._clear_hits()
            elif full and not be.overlays_enabled:
                if keep_rays:
                    self.stats["shared_ray_counts"] = 1
                else:
                    self._count_rays()
            else:
                self._init(zeroed=True)
            be.gpu_counts.bind_to_storage_buffer(BIND_CHC_QUERY_COUNTS, COUNT_BYTES, 4 * (capacity + 3))
            if probe:
                self._probe_full(dv, dev)
            if take_cull:
                # the first pass's bestBits from its rays: these rays have the same tmax and activity
                # (a copy after the previous pass's image atomics on bestBits: ordered by the barrier)
                self.ctx.memory_barrier(moderngl.TEXTURE_UPDATE_BARRIER_BIT)
                copy_texture(self.tg.best, self.tg.best_init)
                self.stats["draws"] += 1
                self.stats["shared_cull_passes"] = 1
                iostats.gl_draw()
            elif merge:
                self._tile_bounds(level, n_tiles, init_rays=fused)  # (else after the init draw's bestBits)
                self.stats["draws"] += 1
                iostats.gl_draw()
                if by_reach:  # kept for the later samples (a copy after image stores: every barrier)
                    self.ctx.memory_barrier(moderngl.ALL_BARRIER_BITS)
                    copy_texture(self.tg.best_init, self.tg.best)
                    self.stats["draws"] += 1
                    iostats.gl_draw()
                self._cull_device(dv, dev, level, sub, merge=True)
            self._sync()
        with prof.phase("chc:1-intersect-visible"):
            if not full:
                self._draw_device_visible(dv, level, n_tiles, bounds_ready=merge, merge=merge)
            self._sync()
        self.n_survivor_groups = 1  # the survivors' count is the device's: their draw is indirect
        self.survivor_items = dv.vis_items if merge else None  # None: be.kept_boxes, as the cull leaves it
        self._queries_and_traversal(full, None if merge else lambda: self._cull_device(dv, dev, level, sub))
        with prof.phase("chc:4-final-intersect"):
            dv.pass_end(be.gpu_counts, ray_slots=COUNT_SLOTS, capacity=capacity, report=report)
            self.stats["draws"] += 1
            if not (full or later):  # (a shared front: refined by its frame's first pass)
                dv.refine(dev, be.gpu_counts, t_q=self.t_q, max_height=p.max_subtree_height,
                          max_tris=self.tri_bound, **common)
                self.stats["draws"] += 4
        if by_reach:  # the cull's outputs stand as it left them (ChcrtPass.run resets this first)
            dv.cull_key = cull_key
        if shares:  # the ray slots hold this pass's rays' counts (counted, or kept: the same rays)
            dv.rays_key = rays_key
        self.rays_read = True  # counted on the device, reported by end_frame

    def _draw_device_visible(self, dv: DeviceFronts, level: int, n_tiles: int, bounds_ready: bool = False,
                             merge: bool = False) -> None:
        """The visible records the device planned, in one indirect instanced draw (instances: the
        records); closest-hit passes first sort each record's items by gap (gap_order_visible), on
        the tile bounds of the init draw (computed here unless `bounds_ready`). `merge`: the records
        carry their tiles' merged kept pairs (merge_kept)."""
        be, ctx, p = self.be, self.ctx, self.p
        be.bind_items(dv.vis_items)
        dv.records.bind_to_storage_buffer(BIND_CHC_DRAWS)
        dv.tiles.bind_to_storage_buffer(FRONT_SSBO["BIND_FR_TILES"])  # the merged kept ranges
        if p.gap_order and p.gap_order_visible and not self.any_hit:
            if not bounds_ready:
                self._tile_bounds(level, n_tiles)  # after the init draw's bestBits
            dv.args.bind_to_storage_buffer(BIND_CHC_INDIRECT, 0, 16)
            be.visorder_dev["coneCull"] = int(p.cone_cull)
            be.visorder_dev.run_indirect(dv.args, ARGS_VISORDER)
            ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
                               | moderngl.TEXTURE_FETCH_BARRIER_BIT)
            n = 1 if bounds_ready else 2
            self.stats["draws"] += n
            iostats.gl_draw(n)
        if be.visible_stage == "compute":
            self._dispatch_visible(level, merge)
        else:
            self._draw_records_indirect(dv.args, merge_kept=merge)

    def _dispatch_visible(self, level: int, merge: bool) -> None:
        """visible_stage=compute: the visible records the device planned (records at BIND_CHC_DRAWS,
        tile plans at BIND_FR_TILES, items bound) in one dispatch, an invocation per pixel over its
        finest tile's records (chc_visible.comp), then one full-screen draw that writes the hits
        through the depth test (chc_visible_resolve.frag). `merge`: the tiles' last records carry
        their merged kept pairs."""
        be, ctx = self.be, self.ctx
        w, h = (int(v) for v in self.size)
        comp = be.visible_program(self.probe_base >= 0)
        if self.probe_base >= 0:  # work_probe: this pass sums its work on the sampled pixels
            comp["probeStride"] = int(self.p.work_probe_stride)
            comp["probeBase"] = self.probe_base
            be.device_fronts().meta.bind_to_storage_buffer(FRONT_SSBO["BIND_FR_META"])
        be.bind_visible_hits((w, h))
        self._isect_uniforms(comp)
        comp["raySize"] = (w, h)
        comp["maxLevel"] = int(level)
        comp["mergeKept"] = int(merge)
        comp["keptAfter"] = int(merge)  # the kept pairs no record carries, after the records (the cull's mergeAll)
        comp["keptChunk"] = int(self.p.max_batch)
        # (the ray set-up's images and buffers were written by dispatches that each end with a barrier)
        comp.run(-(-w // 8), -(-h // 8))
        # the hit words -> the resolve draw; bestBits' atomics -> the survivors' loads (their own barrier)
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        self._use_hit_target()
        prog = be.prog_visible_resolve
        prog["anyHit"] = int(self.any_hit)
        prog["width"] = w
        be.quad.render(prog)
        self.stats["draws"] += 2
        self.stats["intersect_draws"] += 1
        iostats.gl_draw()  # (the dispatch; the quad counts its draw)

    def _cull_device(self, dv: DeviceFronts, dev, level: int, sub: int, merge: bool = False) -> None:
        """The invisible items the device planned, culled per cull tile (chc_tilebounds.comp, then
        chc_querycull.comp over the ranges chc_front_plan.comp wrote) into the survivors' records and
        their indirect draw command; buffers sized for the device's item capacity. `merge`
        (merge_kept, before the visible records, on the tile bounds already computed): the kept
        items go after the visible ones in dv.vis_items, and the kept ranges of tiles with a visible
        record into their tile plans (their last record carries them) instead of survivors' records."""
        be, ctx, p = self.be, self.ctx, self.p
        cl = level + sub
        n_cull = 1 << (2 * cl)
        kept = (dv.inv_cap << (2 * sub)) * ITEM_DTYPE.itemsize
        recs = ((dv.inv_cap + (1 << (2 * level))) << (2 * sub)) * DRAW_DTYPE.itemsize
        if not merge and be.kept_boxes.size < kept:
            be.kept_boxes.release()
            be.kept_boxes = ctx.buffer(reserve=kept)
        if be.survivors.size < recs:
            be.survivors.release()
            be.survivors = ctx.buffer(reserve=recs)
        be.bind_items(dv.inv_items)
        dv.cull.bind_to_storage_buffer(BIND_CHC_QUERIES)
        (dv.vis_items if merge else be.kept_boxes).bind_to_storage_buffer(BIND_CHC_CANDIDATES)
        dv.tiles.bind_to_storage_buffer(FRONT_SSBO["BIND_FR_TILES"])
        be.survivors.bind_to_storage_buffer(BIND_CHC_DRAWS)
        be.query_indirect.bind_to_storage_buffer(BIND_CHC_INDIRECT)
        if not merge:
            self._tile_bounds(cl, n_cull)  # after the visible pairs' bestBits
        be.querycull["keptOffset"] = dv.kept_offset if merge else 0
        if be.merge_kept:
            be.querycull["mergeKept"] = int(merge)
            # visible_stage=compute: every tile's kept pairs go to the tile plans for the compute dispatch
            # (_dispatch_visible), none to the survivors' fragment draw
            be.querycull["mergeAll"] = int(merge and be.visible_stage == "compute")
        be.querycull["nQueries"] = n_cull
        be.querycull["maxItems"] = p.max_batch
        be.querycull["pixelSlot"] = dev.capacity
        be.querycull["cull"] = int(p.coarse_cull)
        be.querycull["sortByGap"] = int(p.gap_order)
        be.querycull["coneCull"] = int(p.cone_cull and not self.cull_by_reach)
        be.querycull.run(-(-n_cull // 64))
        ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT
                           | moderngl.TEXTURE_FETCH_BARRIER_BIT)
        n = 1 if merge else 2
        self.stats["draws"] += n
        iostats.gl_draw(n)

    def _probe_plan(self, dev: DeviceFront, full: bool) -> tuple[bool, bool]:
        """work_probe, for a device front's pass: (does this pass measure its work, does it trace the
        whole BVH because its front saved too little when last measured). A front measures at its
        first device pass with hit hints and then every work_probe passes (a shared front: passes
        counted once a frame, _run_device); one found wasteful traces the whole BVH in between,
        except in the pass before a measurement, which brings its front up to date (a whole-BVH pass
        refines nothing), so that the measurement sees a current front."""
        k, n = dev.passes, self.p.work_probe
        if n <= 0 or full:
            return False, False
        probe = k == 0 or k % n == n - 1
        warm_up = n > 1 and k % n == n - 2
        return probe, dev.wasteful and not (probe or warm_up)

    def prewarm(self, hint: moderngl.Texture | None) -> None:
        """Make the device fronts' programs and draw or dispatch every program of the steady passes
        (the device fronts' ten, the tile bounds, cull, visible order and ray count, the counting
        intersection and, with work_probe, its probe build and chc_probe.comp) once with nothing to
        do (an indirect draw or dispatch of zero) in the GL state of a steady pass (its targets, ray
        and hint textures), after the first pass of a front headed for the device. A driver
        compiles a program when it is linked (GL) and, llvmpipe, its machine code at its first draw
        or dispatch in a new state (150-250 ms for chc_intersect.frag; with no shader cache on disk,
        a fresh machine, about 1.5 s for all of them: conference-walk's first device pass took
        1,761 ms); both happen here, in that cold frame, not in a steady one."""
        be, ctx = self.be, self.ctx
        dv = be.device_fronts()
        vaos = [be.vao_isect_g]
        comps = [be.tilebounds, be.tilebounds_init, be.querycull, be.count_rays, be.visorder_dev]
        if be.p.work_probe > 0:
            _, vao, comp = be.probe_programs()
            vaos.append(vao)
            comps.append(comp)
        if be.visible_stage == "compute":
            comps += [be.visible_program(False), *([be.visible_program(True)] if be.p.work_probe > 0 else [])]
        self.hint = hint
        self._bind()
        # every texture the steady draws sample bound as they will be: llvmpipe keys a program's
        # machine code by its samplers' formats and targets too (an unbound item unit: a second compile)
        be.bind_items(dv.vis_items)
        zero = ctx.buffer(bytes(DRAW_DTYPE.itemsize))  # an indirect dispatch of zero; one empty record
        one = ctx.buffer(np.array([6, 1, 0, 0], np.uint32).tobytes())  # 6 vertices, 1 instance
        iostats.to_device(DRAW_DTYPE.itemsize + 16)
        self._use_hit_target()
        # an indirect draw, as the steady passes draw, of one record with an empty rectangle: no
        # fragment, but a driver that skips an indirect draw of zero before choosing its machine
        # code (llvmpipe) compiles it here
        zero.bind_to_storage_buffer(BIND_CHC_DRAWS)
        for vao in vaos:
            vao.program["mergeKept"] = 0
            vao.render_indirect(one, moderngl.TRIANGLES, count=1)
        one.release()
        ctx.memory_barrier(moderngl.ALL_BARRIER_BITS)  # (the empty draws wrote nothing either: as below)
        for comp in comps:
            comp.run_indirect(zero)
        dv.prewarm(zero)
        # (nothing above ran an invocation that writes, but GL cannot know: the next pass starts
        # fenced, as tests/gl_hazards.py checks)
        ctx.memory_barrier(moderngl.ALL_BARRIER_BITS)
        ctx.disable(moderngl.DEPTH_TEST)
        zero.release()
        iostats.gl_draw(len(vaos) + len(comps))
        be.steady_warm = True

    def _probe_full(self, dv: DeviceFronts, dev: DeviceFront) -> None:
        """work_probe: the sampled rays through the whole BVH (chc_probe.comp), their work into the
        front's META row; the pass's intersection draws add theirs (the WORK_PROBE program)."""
        be = self.be
        comp = be.probe_programs()[2]
        stride = int(self.p.work_probe_stride)
        w, h = (int(v) for v in self.size)
        runs = -(-w // (8 * stride)) * -(-(h - stride // 2) // stride)  # runs of 8 pixels (chc_probe.comp)
        comp["raySize"] = (w, h)
        comp["probeStride"] = stride
        self.probe_base = dev.slot * META_INTS + META_PROBE_FRONT
        comp["probeBase"] = self.probe_base
        comp["anyHit"] = int(self.any_hit)
        dv.meta.bind_to_storage_buffer(FRONT_SSBO["BIND_FR_META"])
        comp.run(-(-runs // 8))
        self.stats["draws"] += 1
        iostats.gl_draw()
        self.stats["work_probe_passes"] = 1
        dev.measured = True  # end_frame reads it

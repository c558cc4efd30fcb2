"""CHC+RT (Mattausch, Bittner, Jaspe, Gobbetti, Wimmer, Pajarola, EG 2015): coherent hierarchical
culling for ray tracing, with the rasterizer's occlusion queries.

Query pairs are (screen tile, BVH node) (see chcrt_front.py). Per pass (Algorithm 1 of the paper):

0. ``chc:0-setup`` (the GPU-driven pass on a device front only): the device plans the pass, the
   init draw clears the hit buffers and counts the rays, and (merge_kept) the tile bounds and the
   cull of the invisible pairs run; what follows is the records' draws.
1. ``chc:1-intersect-visible``: clear (device fronts: in phase 0), then intersect the pairs that
   were visible last frame (their scheduled subtrees, batched by tile, up to `max_batch` per draw).
   This primes the depth buffer with this frame's rays and geometry, so everything after it stays
   exact.
2. ``chc:2-queries``: query the pairs that were invisible last frame; the invisible pairs of one
   tile share multi-queries (up to `max_multi` pairs per draw; a failed multi-query is repeated
   pair by pair). Visible leaves are re-queried every `requery_interval` frames (random phase).
3. ``chc:3-traversal``: pairs that became visible are refined (split rule) and their children
   queried, wave by wave (a wave's queries are issued together, then read); terminated visible
   pairs are scheduled and intersected whenever `schedule_batch` of them are waiting. In batched
   mode a query also returns, per box it drew, the bounds of the pixels that passed it, and a
   child's query is drawn only over those bounds (inside its own tile): an object-space child's
   boxes lie inside its own box of the parent's query (a child tile: inside both), and the nearest
   hits only shrink, so no pixel outside can pass (same counts, far fewer query fragments:
   sibenik's cold 320x180 frame 78.3M -> 28.7M, its CPU time 9.3-9.7 s -> 5.3-5.5 s).
4. ``chc:4-final-intersect``: the remaining scheduled pairs (device fronts: the pass's counts and
   the refinement); in every pass also the rays handed over at llvmpipe's loop limit and the copy
   of the hit hints.

Then invisibility is pulled up one level (siblings that are all invisible are merged).

Exactness. Depth = distance along the ray times a power of two (exact, so the depth test compares
distances exactly) in a DEPTH_COMPONENT32F buffer (moderngl only makes 24-bit depth textures: the
storage is re-specified through GL). Queries pass where a box entry <= the pixel's nearest hit so
far (the `tl <= hit.t` of traverseBVH); the hit buffer is written through the depth test (LESS),
so no memory barrier is needed between draws (glMemoryBarrier is a glFinish on llvmpipe) and a
stale image read only costs work. Conservative mode (visible_threshold = 0) therefore returns
the glsl baseline's nearest hit, bit for bit in t, except on ties: two triangles at the same true
distance (shared edges, coplanar overlaps), where the winner depends on the visiting order in
glsl too. Any-hit rays agree on hit/miss (which occluder is reported depends on the order).
See chc_intersect_record.glsl for llvmpipe's loop limit and how rays that would reach it are finished.

Overlays (TraceResult.overlays, R32I at the ray-batch size, overwritten by the next pass while
overlays are wanted, `overlays_enabled`; left as they are otherwise):
``query_overdraw`` (query fragments per pixel, imageAtomicAdd) and ``subtree_id`` (canonical BVH
node of the scheduled subtree that produced the pixel's hit, -1 for none). Counters: see
``ChcrtPass.stats`` (chcrt_pass.py; the spec's eight plus per-tile batch counts, waves, re-queries, pull-ups).

Temporal state: one pair hierarchy per pass key (ray type, sample, light: PassInfo.key); with
share_sample_fronts one per effect and light (ChcrtBackend.front_key), hit hints per pass key.

Query modes. ``query_mode=hw`` (the paper's): every query is one scissored draw inside one hardware
occlusion query, every intersection batch one scissored draw. ``query_mode=batched`` (default): a
wave of queries, or all batches of one intersection step, is ONE instanced draw (chc_tile.vert
places each instance on its tile); query fragments make the depth test's comparison themselves
against bestBits and count into their query's slot with an atomic add, read back once per wave.
Same query results (bestBits can only be stale towards passing), far fewer draws and waits.

GPU-driven steady state (``gpu_driven``, default; docs/backends/chcrt-submission.md). Only a front's
first pass (and, for a deep BVH, the few after it until its refinement completes: ``cold_passes``)
runs the algorithm above. Every later pass is a fixed number of launches: the visible pairs (one
draw, all subtrees over a finest tile in one record), per finest tile the rays' origin box and reach (one
dispatch), the invisible pairs some ray may still enter (one dispatch) and their intersection (one
indirect draw). The intersection is the query: box entries before the nearest hit so far are
counted per pair, read once after the pass, and the front is refined for the next frame. A finest
tile with many pairs traverses the lowest common ancestor of all of them instead (its invisible
pairs are then not queried), and a pass where most tiles do that runs a full traversal
(`lca_pairs`, `lca_subtrees`, `full_bvh_fraction`): incoherent rays cost about what glsl costs. A
front's first pass stops refining when its queries cost more than a traversal (`cold_full_bvh`) and
traces the whole BVH; if that refinement was coherent (`cold_wave_queries`), its next pass goes on
refining from there with a fresh budget, so a deep BVH (city 10 M) gets its front in two frames
(`cold_passes`). A front whose tiles would mostly take the LCA fallback, or whose refinement cost
too much per BVH level (incoherent rays), or that stopped `cold_passes` times, stays on full
traversals.

Cold start (`cold_start`, default `auto`: `device` where fronts live on the device and are kept
between frames). The synchronous first pass above waits for every wave of queries; on a GPU that
made the cold frame the slowest of all (an H200: 163-183 ms for camera rays against 9.5 steady,
12.3 s of queries at city 10 M). A device cold start skips it: the new front, (screen, root) split
on the host by the split rule as if every pair were entered for its first levels (within
`cold_start_pairs` pairs per finest tile), goes to the device at its first pass, and every pass is
the steady pass from then on, its counts refining the front one level a pass. Exact from the first
pass (the cull keeps every pair some ray may enter); its first passes cost about a whole-BVH
traversal, and the front has settled when
a pass splits at most `settle_splits` of its pairs (`settling_fronts` counts those that have not);
the work probe's decisions wait for that. A settling front shared by sample passes
(`settle_probe`) is presumed wasteful until measured: the frame's first pass runs and refines it,
and measures it from the first frame with hit hints, and the later samples trace the whole BVH
while the last measurement says so. `cold_start=sync` runs the paper's first pass (the bench-chcrt
studies take it unless told otherwise; `--study coldstart` compares the two).

Gap order (`gap_order`, `gap_order_visible`): in the GPU-driven pass each record's items are sorted on
the device by a lower bound of their distance from the tile's ray origins, and a ray stops testing
them at the first one beyond its nearest hit (exact: such a box cannot be entered before the hit).
Cone cull (`cone_cull`): the same dispatch bounds each tile's ray directions (a cone and four side
planes, chc_tilecone.glsl), and boxes beside every ray of the tile are dropped from the records.
Primary-ray fronts are deeper (`t_q_primary`) and never take the LCA fallback (`lca_primary`).

Work probe (`work_probe`): a device front's pass now and then sums, on a sparse grid of pixels, the box
and triangle tests its draws do, and one dispatch (chc_probe.comp) those of the full traversal for
the same rays; read with the front's META row after the frame, a front that saves too little
(`work_ratio_full`, `work_ratio_full_any`: far views, Sibenik's nave) traces the whole BVH until its
next measurement.

Hit hints (`hit_hint`): every ray first tests the triangle its pixel hit in the front's previous
pass (copied on the device after each pass): any-hit rays that hit it are done, closest-hit rays
start with its distance as tmax. Exact: a hint hit is a real hit, and the traversal still finds
anything nearer.

Parameters come from ChcrtParams: `--backend-params "visible_threshold=20,t_q=0.4"` (alias
`--chcrt`) on the command line, or the RTWALK_CHCRT environment variable (the registry merges them).
"""

from __future__ import annotations

import math
import time

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.base import BackendContext, TraceResult, WorkCounters
from viewer.backends.chcrt.chcrt_cache import MB, CachePlan, SubtreeCache
from viewer.backends.chcrt.chcrt_devfront import FRONT_SSBO, DeviceFronts
from viewer.backends.chcrt.chcrt_front import NodeTables, PairFront
from viewer.backends.chcrt.chcrt_layout import (
    BIND_CHC_DRAWS,
    BIND_CHC_ITEMS,
    BIND_CHC_QUERIES,
    BIND_CHC_QUERY_COUNTS,
    BIND_CHC_VIS_HITS,
    BINDINGS,
    COUNT_BYTES,
    COUNT_SLOTS,
    DRAW_DTYPE,
    HERE,
    HINT_UNIT,
    ITEM_DTYPE,
    ITEM_UNIT,
    MAX_BOXES,
    TILE_BOUND_BYTES,
    tile_bounds_group,
)
from viewer.backends.chcrt.chcrt_params import ChcrtParams
from viewer.backends.chcrt.chcrt_pass import ChcrtPass
from viewer.backends.gl_traversal import ResumableTraversal, max_visits, visit_cost
from viewer.backends.interface import BackendInfo, OverlaySpec
from viewer.gl.buffers import StreamBuffer
from viewer.gl.limits import check_storage_block
from viewer.gl.programs import FullscreenQuad, compute_shader
from viewer.gl.stages import resolve_stage
from viewer.gl.textures import TexelView, copy_texture, float_depth_texture, float_texture, int_texture
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.screen_tiles import max_tile_level


class _Targets:
    """GL objects at one ray-batch size."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int], max_level: int):
        self.size = size
        self.depth = float_depth_texture(ctx, size)
        self.best = int_texture(ctx, size)
        # bestBits as the tile bounds set it from the rays (tmax bits, -1 = no ray), for later samples
        # whose rays share their origins and reach (ChcrtPass._run_device)
        self.best_init = int_texture(ctx, size)
        self.overdraw = int_texture(ctx, size)
        self.subtree = int_texture(ctx, size)
        self.batch = int_texture(ctx, size)
        self.query_fbo = ctx.framebuffer(depth_attachment=self.depth)
        self.query_fbo.depth_mask = False
        g = 1 << max_level
        self.gather_size = (g, g)
        self.gather_o = float_texture(ctx, (g, g), 4)
        self.gather_d = float_texture(ctx, (g, g), 4)
        self.gather_fbo = ctx.framebuffer(color_attachments=[self.gather_o, self.gather_d])
        self.hits: HitBuffer | None = None
        self.hit_fbo: moderngl.Framebuffer | None = None

    def hit_framebuffer(self, ctx: moderngl.Context, hits: HitBuffer) -> moderngl.Framebuffer:
        if self.hits is not hits or self.hit_fbo is None:
            if self.hit_fbo is not None:
                self.hit_fbo.release()
            self.hit_fbo = ctx.framebuffer(color_attachments=[hits.t, hits.id, self.subtree],
                                           depth_attachment=self.depth)
            self.hits = hits
        return self.hit_fbo

    def release(self) -> None:
        for obj in (self.hit_fbo, self.query_fbo, self.gather_fbo, self.depth, self.best, self.best_init, self.overdraw,
                    self.subtree, self.batch, self.gather_o, self.gather_d):
            if obj is not None:
                obj.release()


PHASES = ("chc:0-setup", "chc:1-intersect-visible", "chc:2-queries", "chc:3-traversal", "chc:4-final-intersect")
COUNTERS = ("queries", "multi_queries", "failed_multi_queries", "visible_pairs", "invisible_pairs",
            "subtrees_scheduled", "draws", "rays", "upload_bvh_mb", "upload_geom_mb", "settling_fronts")


class ChcrtBackend:
    info = BackendInfo(
        "chcrt", "CHC+RT: occlusion-query culling of (screen tile, BVH node) pairs, temporal fronts",
        params=ChcrtParams,
        overlays=(OverlaySpec("query_overdraw", "heat", "query_overdraw", "query tests per pixel"),
                  OverlaySpec("subtree_batches", "ids", "subtree_id", "hit subtree; subtrees in the tile's batches",
                              counts="batch_subtrees")),
        counters=COUNTERS, phases=PHASES)

    def __init__(self, bc: BackendContext, params: ChcrtParams | None = None):
        self.bc = bc
        self.ctx = bc.ctx
        self.p = params or ChcrtParams()
        self.p.validate()
        self.params = self.p
        self.nt = NodeTables.from_bvh(bc.bvh)
        self.bvh_first = np.asarray(bc.bvh.node_first, np.int32)
        diag = max(float(getattr(bc.scene, "diagonal", 1.0)), 1e-30)
        e = min(max(math.frexp(diag)[1] + 24, -100), 100)
        self.depth_scale = float(np.float32(math.ldexp(1.0, -e)))  # exact power of two
        progs = bc.programs.with_path(HERE)
        self.work = WorkCounters(self.ctx)
        wd = {**self.work.defines, **BINDINGS, **bc.gpu_scene.trace_defines()}
        # one subtree at a time is on the traversal stack (chc_intersect_record.glsl); subtrees found visible by
        # the GPU-driven pass, and lowest common ancestors, can be as high as the tree
        stack = max(self.p.max_subtree_height, int(self.nt.height[0]), 1) + 2
        # GPU-driven steady state (ChcrtParams.gpu_driven); device fronts are made on the first steady
        # pass (ChcrtParams.device_front): their SSBO binding points go up to 33, a driver with fewer
        # keeps the host-planned fronts. merge_kept needs device fronts: only then do the counting
        # intersection, the cull and the visible order carry its code (CHC_MERGE_KEPT)
        self.cache = self._make_cache(bc)
        self.batched = self.p.query_mode == "batched"
        self.gpu_driven = self.p.gpu_driven and self.batched and self.cache is None
        bindings = int(self.ctx.info.get("GL_MAX_SHADER_STORAGE_BUFFER_BINDINGS", 0) or 0)
        self.device_front = (self.gpu_driven and self.p.device_front and self.p.merge_tiles and self.p.lca_invisible
                             and bindings > max(FRONT_SSBO.values()))
        self.merge_kept = self.device_front and self.p.merge_kept
        # cold_start: a new front starts on the device and settles over its first passes (no waits), or is
        # refined by the paper's synchronous passes (without device fronts or temporal fronts, always)
        self.device_cold = self.device_front and (self.p.cold_start == "device"
                                                  or (self.p.cold_start == "auto" and self.p.temporal))
        self.merge_defs = {"CHC_MERGE_KEPT": 1} if self.merge_kept else {}
        iwd = {**wd, "LEAF_CACHE": int(self.p.leaf_cache)}  # intersection programs only
        if self.cache is not None:
            iwd["CHC_OOC"] = 1
        self.prog_init = progs.get("fullscreen.vert", "chc_init.frag", BINDINGS)
        self.prog_query = progs.get("fullscreen.vert", "chc_query.frag", {"CHC_MAX_ITEMS": MAX_BOXES, **wd})
        # rays that would reach llvmpipe's loop limit are finished by the glsl resumable traversal;
        # it counts into the same work counters (full-BVH passes and resumed rays are work too)
        self.full_bvh_stage = resolve_stage(self.ctx, self.p.full_bvh_stage)  # (auto: what this device runs faster)
        self.visible_stage = resolve_stage(self.ctx, self.p.visible_stage)
        self.finisher = ResumableTraversal(bc, self.work, stage=self.full_bvh_stage)
        iwd.update(self.finisher.resume_defines)  # (no hand-over code where no ray is handed over)
        # per scheduled item: the item loop, its leaf's triangles and the entered leaves' loop after the
        # item loop, and the query counts' loop
        items_loops = self.p.max_batch * (self.finisher.max_leaf + 3)
        # no loop limit (not llvmpipe): no ray is handed over, the finisher never reads its counter
        visits = (max_visits(self.finisher.max_leaf, stack, items_loops, limit=self.finisher.limit)
                  if self.finisher.limit is not None else len(self.nt.left) + 1)
        # the counting program's visible records may carry as many kept pairs again (merge_kept): the
        # item loops run twice as long
        visits_g = visits
        if self.merge_kept:
            visits_g = (max_visits(self.finisher.max_leaf, stack, 2 * items_loops, limit=self.finisher.limit)
                        if self.finisher.limit is not None else visits)
        self.prog_isect = progs.get("fullscreen.vert", "chc_intersect.frag",
                                    {"CHC_MAX_ITEMS": self.p.max_batch, "STACK_SIZE": stack, "CHC_MAX_VISITS": visits,
                                     **iwd})
        self.prog_gather = progs.get("fullscreen.vert", "chc_gather.frag", BINDINGS)
        self.prog_query_b = progs.get("chc_tile.vert", "chc_query.frag",
                                      {"CHC_MAX_ITEMS": MAX_BOXES, "CHC_BATCHED": 1, **wd})
        self.prog_isect_b = progs.get("chc_tile.vert", "chc_intersect.frag",
                                      {"CHC_MAX_ITEMS": self.p.max_batch, "CHC_BATCHED": 1, "STACK_SIZE": stack,
                                       "CHC_MAX_VISITS": visits, **iwd})
        self.vao_query_b = self.ctx.vertex_array(self.prog_query_b, [])
        self.vao_isect_b = self.ctx.vertex_array(self.prog_isect_b, [])
        # GPU-driven: the same intersection, counting box entries into the pairs' slots (the queries)
        isect_g = {"CHC_MAX_ITEMS": self.p.max_batch, "CHC_BATCHED": 1, "STACK_SIZE": stack,
                   "CHC_MAX_VISITS": visits_g, "CHC_COUNT_ITEMS": 1, **iwd, **self.merge_defs}
        self.prog_isect_g = progs.get("chc_tile.vert", "chc_intersect.frag", isect_g)
        self.vao_isect_g = self.ctx.vertex_array(self.prog_isect_g, [])
        # work_probe: the same program measuring its work, and the full traversal of the same rays
        # (made with the device fronts)
        self._probe_defines = ({**isect_g, "WORK_PROBE": 1}, {**wd, "STACK_SIZE": stack})
        self.probe: tuple[moderngl.Program, moderngl.VertexArray, moderngl.ComputeShader] | None = None
        # visible_stage=compute (chc_visible.comp, made on first use): the counting intersection with
        # one invocation per pixel over its tile's records, under ONE loop budget where the loop limit
        # applies: each record charges its item loops (and the overlay's loop over them) in node visits
        vis = {k: v for k, v in isect_g.items() if k != "CHC_BATCHED"}
        if self.finisher.limit is not None:
            record_loops = (2 if self.merge_kept else 1) * items_loops + 2 * self.p.max_batch
            vis["CHC_MAX_VISITS"] = max_visits(self.finisher.max_leaf, stack, limit=self.finisher.limit)
            vis["CHC_RECORD_VISITS"] = visit_cost(self.finisher.max_leaf, record_loops)
        self._visible_defines = vis
        self.visible: dict[bool, moderngl.ComputeShader] = {}  # by WORK_PROBE
        self.visible_hits: moderngl.Buffer | None = None  # 3 words a pixel (chc_visible.comp VisHits)
        self.prog_visible_resolve = progs.get("fullscreen.vert", "chc_visible_resolve.frag", BINDINGS)
        self.prog_visible_resolve["depthScale"] = self.depth_scale
        self.steady_warm = False  # the steady passes' programs were drawn once, empty (ChcrtPass.prewarm)
        for prog in (self.prog_init, self.prog_query, self.prog_isect, self.prog_gather, self.prog_query_b,
                     self.prog_isect_b, self.prog_isect_g):
            prog["rayOrigin"] = 0
            prog["rayDir"] = 1
            if prog.get("hintId", None) is not None:
                prog["hintId"] = HINT_UNIT
            if prog.get("depthScale", None) is not None:
                prog["depthScale"] = self.depth_scale
        self.quad = FullscreenQuad(self.ctx)
        self.items = StreamBuffer(self.ctx, ITEM_DTYPE.itemsize, BIND_CHC_ITEMS)
        self.item_texels = TexelView(ITEM_UNIT)  # what the fragment shaders read items through (bind_items)
        self.draws = StreamBuffer(self.ctx, DRAW_DTYPE.itemsize, BIND_CHC_DRAWS)
        self.query_counts = StreamBuffer(self.ctx, 4, BIND_CHC_QUERY_COUNTS)
        self.count_buf = self.ctx.buffer(reserve=4 * COUNT_SLOTS)
        self._zero_counts = bytes(4 * COUNT_SLOTS)
        tb_defs = {**BINDINGS, "TILE_BOUNDS_GROUP": tile_bounds_group(self.ctx.info.get("GL_RENDERER"))}
        self.tilebounds = compute_shader(self.ctx, "chc_tilebounds.comp", tb_defs, (HERE,))
        # (the build that also initialises the rays: a device pass without an init draw)
        self.tilebounds_init = compute_shader(self.ctx, "chc_tilebounds.comp", {**tb_defs, "CHC_INIT_RAYS": 1},
                                              (HERE,))
        self.count_rays = compute_shader(self.ctx, "chc_count_rays.comp", BINDINGS, (HERE,))
        self.count_rays["rayOrigin"] = 0
        self.count_rays["rayDir"] = 1
        self.querycull = compute_shader(self.ctx, "chc_querycull.comp", {**BINDINGS, **self.merge_defs}, (HERE,))
        self.visorder = compute_shader(self.ctx, "chc_visorder.comp", BINDINGS, (HERE,))
        self.devfronts: DeviceFronts | None = None
        self.visorder_dev: moderngl.ComputeShader | None = None
        for comp in (self.tilebounds, self.tilebounds_init):
            comp["rayOrigin"] = 0
            comp["rayDir"] = 1
        self.all_queries = StreamBuffer(self.ctx, DRAW_DTYPE.itemsize, BIND_CHC_QUERIES)
        self.survivors = self.ctx.buffer(reserve=DRAW_DTYPE.itemsize * 4096)
        self.kept_boxes = self.ctx.buffer(reserve=ITEM_DTYPE.itemsize * 4096)
        self.query_indirect = self.ctx.buffer(reserve=16)
        self.tile_bounds = self.ctx.buffer(reserve=TILE_BOUND_BYTES * 64)
        self.gpu_counts = self.ctx.buffer(reserve=COUNT_BYTES + 4 * 4096)
        self.queries: list[moderngl.Query] = []
        self.targets: _Targets | None = None
        self.fronts: dict[tuple, PairFront] = {}
        # hit_hint: per front, the triangle each pixel's ray hit in the front's last pass (R32I)
        self.hints: dict[tuple, moderngl.Texture] = {}
        self.use_hints = self.p.hit_hint and self.cache is None  # out-of-core: cache slots, not triangle ids
        self.rng = np.random.default_rng(self.p.seed)
        self.frame = 0
        self.last_stats: dict[str, float] = {}
        # fill the overlay textures (query overdraw, subtree id, batch sizes): set per frame by the
        # renderer (on only while an overlay view is shown or saved: the counting costs time)
        self.overlays_enabled = True

    def _make_cache(self, bc: BackendContext) -> SubtreeCache | None:
        """The out-of-core subtree cache when a GPU budget is set (chcrt_cache)."""
        p = self.p
        if p.gpu_budget_mb <= 0 and p.gpu_budget_fraction <= 0:
            return None
        bvh, scene = bc.bvh, bc.scene
        if p.gpu_budget_mb > 0:
            budget = int(p.gpu_budget_mb * MB)
        else:
            budget = int(p.gpu_budget_fraction * CachePlan.scene_bytes_of(bvh))
        return SubtreeCache(self.ctx, bvh, scene.triangles, scene.material_ids, budget, p.subtree_tri_bound(),
                            p.max_subtree_height)

    def _clear_fronts(self) -> None:
        """Forget every front (on the device too) and its hit hints."""
        if self.devfronts is not None:
            self.devfronts.last_plan = None
        for f in self.fronts.values():
            if f.device is not None and self.devfronts is not None:
                self.devfronts.detach(f.device)
            f.device = None
        self.fronts.clear()
        for tex in self.hints.values():
            tex.release()
        self.hints.clear()

    def _keep_hint(self, key: tuple, hits: HitBuffer) -> None:
        """hit_hint: copy this pass's hit triangles (hits.id) to the front's hint texture (one copy
        on the device, read by the front's next pass)."""
        tex = self.hints.get(key)
        if tex is None:
            tex = self.hints[key] = int_texture(self.ctx, tuple(hits.size))
        copy_texture(tex, hits.id)
        iostats.gl_draw()

    def probe_programs(self) -> tuple[moderngl.Program, moderngl.VertexArray, moderngl.ComputeShader]:
        """work_probe: the counting intersection that sums its work on the sampled pixels (with its
        VAO), and chc_probe.comp (the full traversal of the same rays); made with the device fronts."""
        if self.probe is None:
            isect, full = self._probe_defines
            prog = self.bc.programs.with_path(HERE).get("chc_tile.vert", "chc_intersect.frag", isect)
            for name, unit in (("rayOrigin", 0), ("rayDir", 1), ("hintId", HINT_UNIT)):
                if prog.get(name, None) is not None:
                    prog[name] = unit
            prog["depthScale"] = self.depth_scale
            comp = compute_shader(self.ctx, "chc_probe.comp", full, (HERE,))
            comp["rayOrigin"] = 0
            comp["rayDir"] = 1
            self.probe = (prog, self.ctx.vertex_array(prog, []), comp)
        return self.probe

    def visible_program(self, probe: bool) -> moderngl.ComputeShader:
        """visible_stage=compute: chc_visible.comp, with WORK_PROBE when `probe` (made on first use)."""
        comp = self.visible.get(probe)
        if comp is None:
            defines = {**self._visible_defines, "WORK_PROBE": 1} if probe else self._visible_defines
            comp = compute_shader(self.ctx, "chc_visible.comp", defines, (HERE,))
            for name, unit in (("rayOrigin", 0), ("rayDir", 1), ("hintId", HINT_UNIT)):
                comp[name] = unit
            comp["depthScale"] = self.depth_scale
            self.visible[probe] = comp
        return comp

    def bind_visible_hits(self, size: tuple[int, int]) -> None:
        """visible_stage=compute: the per-pixel hit words for rays of `size`, bound (grown on demand)."""
        nbytes = 12 * int(size[0]) * int(size[1])
        if self.visible_hits is None or self.visible_hits.size < nbytes:
            check_storage_block(self.ctx, nbytes, f"chcrt visible_stage=compute at {size[0]}x{size[1]}")
            if self.visible_hits is not None:
                self.visible_hits.release()
            self.visible_hits = self.ctx.buffer(reserve=nbytes)
        self.visible_hits.bind_to_storage_buffer(BIND_CHC_VIS_HITS)

    # -- Backend protocol ----------------------------------------------------------------------
    def bind_items(self, buf: moderngl.Buffer) -> None:
        """`buf` as the items of the next draws and dispatches: the SSBO at BIND_CHC_ITEMS (compute
        passes) and the buffer texture the fragment shaders read them through (loadItem)."""
        buf.bind_to_storage_buffer(BIND_CHC_ITEMS)
        self.item_texels.attach(buf)

    def device_fronts(self) -> DeviceFronts:
        """The device fronts' shared buffers and programs (made on first use)."""
        if self.devfronts is None:
            self.devfronts = DeviceFronts(self.ctx, self.nt, BINDINGS)
            self.visorder_dev = compute_shader(self.ctx, "chc_visorder.comp",
                                               {**BINDINGS, "CHC_RECORDS_IN_BUFFER": 1, **self.merge_defs}, (HERE,))
            if self.p.work_probe > 0:
                self.probe_programs()  # compiled with the first front's upload, not in a steady pass
        return self.devfronts

    def begin_frame(self, frame_index: int) -> None:
        self.frame = int(frame_index)
        if not self.p.temporal:
            self._clear_fronts()

    def end_frame(self) -> dict[str, float]:
        """After the frame's finish: the statistics of the device passes since the last call (one read
        that waits for nothing; a caller of trace() outside the Renderer calls it to get them).
        A device front whose last plan sent at least full_bvh_fraction of its tiles to their lowest
        common ancestor traces the whole BVH in its next pass, and plans again to decide the one
        after (the host plan decides within the pass; the device's choice comes one pass later and
        is exact either way)."""
        if self.devfronts is None:
            return {}
        stats, rows = self.devfronts.end_frame()
        frac = self.p.full_bvh_fraction
        settling = 0
        probed = {"work_probe_fronts": 0.0, "work_probe_rays": 0.0, "work_probe_front": 0.0, "work_probe_full": 0.0}
        for slot, row in rows.items():
            dev = self.devfronts.fronts[slot]
            dev.full = frac > 0 and row.tiles > 0 and row.heavy_tiles >= frac * row.tiles
            if not dev.settled and row.n > 0 and (dev.full or row.splits <= self.p.settle_splits * row.n):
                dev.settled = True  # (a front that traces the whole BVH refines no more: settled too)
            settling += int(not dev.settled)
            if dev.measured and row.probe_rays > 0 and row.probe_full > 0:
                # work_probe: the front's pass measured its work against the full traversal's
                dev.measured = False
                dev.wasteful = row.probe_front > dev.work_ratio_full * row.probe_full
                for k, v in zip(probed, (1, row.probe_rays, row.probe_front, row.probe_full), strict=True):
                    probed[k] += v
        stats["settling_fronts"] = float(settling)  # device cold starts still refining a level a pass
        if probed["work_probe_fronts"]:
            stats.update(probed)
            stats["work_probe_ratio"] = probed["work_probe_front"] / probed["work_probe_full"]
        return stats

    def release(self) -> None:
        if self.targets is not None:
            self.targets.release()
            self.targets = None
        for sb in (self.items, self.draws, self.query_counts, self.all_queries):
            sb.buf.release()
        self.item_texels.release()
        if self.probe is not None:
            self.probe[1].release()
            self.probe[2].release()
            self.probe = None
        for comp in self.visible.values():
            comp.release()
        self.visible.clear()
        if self.visible_hits is not None:
            self.visible_hits.release()
            self.visible_hits = None
        for obj in (self.vao_isect_g, self.gpu_counts, self.tilebounds, self.tilebounds_init, self.count_rays,
                    self.querycull, self.survivors, self.query_indirect, self.tile_bounds, self.kept_boxes):
            obj.release()
        self._clear_fronts()
        if self.devfronts is not None:
            self.devfronts.release()
            self.visorder_dev.release()
            self.devfronts = self.visorder_dev = None
        for vao in (self.vao_query_b, self.vao_isect_b):
            vao.release()
        self.count_buf.release()
        if self.cache is not None:
            self.cache.release()
        self.finisher.release()
        self.work.release()
        self.queries.clear()  # moderngl 5 queries have no release(); dropped with the context

    def scene_changed(self, bc: BackendContext) -> None:
        """Moved triangles, refitted BVH: new node tables (query boxes) and, with a GPU budget, a
        new out-of-core subtree cache (phase "build:chcrt"). The GpuScene's buffers were rewritten
        in place. The fronts are kept when the tree's topology is unchanged (a refit keeps every
        node id, child link and triangle range, so each front node still names the same subtree;
        its visibility guess is only a schedule: every ray is still traced exactly). A tree with
        another topology resets them."""
        t0 = time.perf_counter()
        same = (len(bc.bvh.node_left) == len(self.nt.left) and np.array_equal(bc.bvh.node_left, self.nt.left)
                and np.array_equal(bc.bvh.node_right, self.nt.right)
                and np.array_equal(np.asarray(bc.bvh.node_first, np.int32), self.bvh_first))
        self.bc = bc
        self.finisher.bc = bc
        self.nt = NodeTables.from_bvh(bc.bvh)
        self.bvh_first = np.asarray(bc.bvh.node_first, np.int32)
        if self.cache is not None:
            self.cache.release()
            self.cache = self._make_cache(bc)
        if not same:
            self._clear_fronts()
        if self.devfronts is not None:
            self.devfronts.set_nodes(self.nt)  # the device fronts' boxes and ranges
        ms = (time.perf_counter() - t0) * 1e3
        bc.profiler.record("build:chcrt", ms, ms)

    def reset(self) -> None:
        """Forget the temporal state (every front restarts from (screen, root))."""
        self._clear_fronts()

    def tile_level(self, size: tuple[int, int]) -> int:
        return max_tile_level(size, self.p.min_tile_fraction)

    def front_key(self, pinfo: PassInfo) -> tuple[int, int, int]:
        """The pair front a pass uses: its own (PassInfo.key), or with share_sample_fronts the one of
        its effect's sample 0 (the samples' rays have the same origins and the same distribution of
        directions). Hit hints stay per pass key."""
        if self.p.share_sample_fronts:
            return int(pinfo.ray_type), 0, int(pinfo.light)
        return pinfo.key

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        ray_type = pinfo.ray_type
        size = tuple(rays.size)
        max_level = max_tile_level(size, self.p.min_tile_fraction)
        if self.targets is None or self.targets.size != size or self.targets.gather_size[0] != 1 << max_level:
            if self.targets is not None:
                self.targets.release()
            self.targets = _Targets(self.ctx, size, max_level)
            self._clear_fronts()
        key = pinfo.key
        front_key = self.front_key(pinfo)
        front = self.fronts.get(front_key)
        if front is None:
            front = PairFront(size, max_level, self.rng, self.p.requery_interval)
            front.cold = not self.device_cold  # (a device cold start: its first pass is a device pass)
            self.fronts[front_key] = front
        tr = ChcrtPass(self, front, rays, ray_type, hits, pinfo)
        self.work.begin(size)
        self.finisher.bind_flags(size)
        stats = tr.run()
        # the rays handed over at the loop limit, and the hint copy: tracing work, timed with the
        # pass's last phase (phases of one name add up) rather than left to the next phase's wait. A
        # GPU-driven pass that traced the whole BVH ran no chcrt draw: nothing was handed over, and
        # the finisher's counter is not read again
        handed_over = not (stats["gpu_driven"] and stats["full_bvh_passes"])
        nothing = {"draws": 0, "resumed_rays": 0}
        if self.finisher.limit is None and not self.use_hints:  # nothing to hand over, no hints: no phase
            fin = self.finisher.run(rays, pinfo, hits, resume_only=True)
        else:
            with self.bc.profiler.phase("chc:4-final-intersect"):
                fin = self.finisher.run(rays, pinfo, hits, resume_only=True) if handed_over else nothing
                if self.use_hints:
                    self._keep_hint(key, hits)
        # the steady passes' programs made and run once, empty, in the first pass of a front that goes
        # (or may go, after more cold passes) to the device: frame 1, not a steady frame
        if self.device_front and not self.steady_warm and not front.full_bvh:
            with self.bc.profiler.phase("chc:0-setup"):  # tracing work of this (cold) frame
                tr.prewarm(self.hints.get(key))
        stats["resumed_rays"] = fin["resumed_rays"]
        stats["continuation_draws"] = fin["draws"]
        stats["visible_compute"] = int(self.visible_stage == "compute")  # (the stages auto chose here)
        stats["full_bvh_compute"] = int(self.full_bvh_stage == "compute")
        stats.update(self.work.end())
        front.frames += 1
        self.last_stats = stats
        return TraceResult(stats=stats, overlays={"query_overdraw": self.targets.overdraw,
                                                  "subtree_id": self.targets.subtree,
                                                  "batch_subtrees": self.targets.batch})

    def query(self, i: int) -> moderngl.Query:
        while len(self.queries) <= i:
            self.queries.append(self.ctx.query(samples=True))
        return self.queries[i]

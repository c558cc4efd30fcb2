"""ChcrtParams: chcrt's documented parameters (`--chcrt`, RTWALK_CHCRT; see chcrt.py for the method)."""

from __future__ import annotations

from dataclasses import dataclass

from viewer.backends.interface import param
from viewer.effects import RayType
from viewer.errors import RtwalkError
from viewer.gl.stages import STAGE_CHOICES

QUERY_MODES = ("batched", "hw")
COLD_STARTS = ("auto", "sync", "device")
MAX_LEAF_CACHE = 16
OOC_SUBTREE_TRIS = 4096  # out of core: the largest subtree, one cache entry (max_subtree_tris = 0)
NO_TRI_BOUND = (1 << 31) - 1  # in core: no triangle bound (an int32 for the shaders' uniform)


@dataclass
class ChcrtParams:
    t_q: float = param(0.5, "split in object space if A_node/A_root > t_q * A_tile/A_screen")
    t_q_primary: float = param(0.7, "primary-ray fronts split with t_q times this (1 = t_q): a deeper front, fewer "
                               "nodes per camera ray below its pairs at more pair tests (their boxes beside a tile "
                               "are culled: cone_cull); other fronts keep t_q (AO: a deeper front goes full-BVH)")
    min_tile_fraction: float = param(0.015, "smallest tile, fraction of the screen (paper: 200x200 at 1080p)")
    max_subtree_height: int = param(24, "scheduled subtrees: traversal stack bound (paper: 24)")
    max_subtree_tris: int = param(0, "scheduled subtrees: triangle bound; 0 = auto (subtree_tri_bound): "
                                  f"{OOC_SUBTREE_TRIS} out of core (a subtree is one cache entry) and for shadow "
                                  "rays, none for the other rays in core (the height bound and the split rule end "
                                  "the cut)")
    requery_interval: int = param(3, "n: visible leaves are re-queried every n frames")
    schedule_batch: int = param(16, "m: newly visible leaves are intersected in batches of m")
    max_batch: int = param(24, "subtree roots per intersection draw")
    max_multi: int = param(24, "invisible pairs per multi-query")
    visible_threshold: int = param(0, "aggressive mode: a pair with <= this many passing pixels is culled")
    overdraw_overlay: bool = param(True, "allow the overlays (the renderer turns them on only when shown/saved)")
    front_to_back: bool = param(True, "order scheduled subtrees by a representative ray (primary/shadows)")
    sync_phases: bool = param(False, "glFinish at the end of each phase: exact per-phase times (diagnostics)")
    query_mode: str = param("batched",
                            "'hw': one hardware occlusion query and one scissored draw per query or batch (the paper); "
                            "'batched': a wave of queries (or all batches of an intersection step) in one instanced "
                            "draw, queries counted by shader atomics (same pass condition as the depth test)")
    leaf_cache: int = param(0,
                            "leaf cache (paper 5.2): leaves a ray enters are collected, up to this many, and their "
                            "triangles tested together in one loop (coherent delayed tests); 0 tests each leaf at once")
    gpu_budget_mb: float = param(0.0, "out-of-core (paper 5.4): GPU budget for the ray tracer's BVH + "
                                 "triangles in MB (0 = everything resident); scheduled subtrees then live in a "
                                 "round-robin cache")
    gpu_budget_fraction: float = param(0.0, "out-of-core budget as a fraction of the scene's BVH + triangles (0 = off)")
    seed: int = param(1, "random phase of the visible-leaf re-queries")
    temporal: bool = param(True,
                           "False: every frame starts cold from (screen, root) (measures what temporal coherence buys)")
    gpu_driven: bool = param(True, "GPU-driven steady state (query_mode=batched, no GPU budget): once a front's "
                             "synchronous refinement is done (its first pass, or cold_passes), its invisible "
                             "pairs are queried in one instanced draw, a compute pass turns the passing queries "
                             "into one indirect intersection draw, and the counts are read once at the end of "
                             "the pass; False: the synchronous algorithm every pass")
    lca_subtrees: int = param(24, "a tile with more visible subtrees than this traverses their lowest common "
                              "ancestor instead (0 = never)")
    merge_tiles: bool = param(True, "GPU-driven: a pixel's visible subtrees of all tile levels in one record")
    lca_invisible: bool = param(True, "GPU-driven (needs merge_tiles): a finest tile over a limit (lca_subtrees "
                                "visible pairs, or lca_pairs pairs in all) traverses the lowest common ancestor "
                                "of ALL its pairs once, and its invisible pairs are not queried; False: the LCA "
                                "replaces only the visible pairs and the invisible ones are still queried")
    cull_sublevels: int = param(0, "GPU-driven: the coarse cull and the invisible pairs' draw work on tiles this many "
                                "quadtree levels below the finest pair tiles (a tighter origin box and reach per "
                                "tile, fewer fragments; each tile keeps >= 4 pixels a side), 0 = the finest tiles")
    full_bvh_fraction: float = param(0.8, "GPU-driven with lca_invisible: when at least this fraction of the finest "
                                     "tiles would traverse an LCA (incoherent rays), the pass traces every ray "
                                     "through the whole BVH with the glsl traversal instead, and the front is left "
                                     "as it is (0 = never)")
    full_bvh_stage: str = param("auto", "where the glsl traversal runs in chcrt's whole-BVH passes and for the "
                                "rays handed over at the loop limit: 'fragment', 'compute' or 'auto' (glsl's `stage`; "
                                "the same hits)")
    lca_pairs: int = param(64, "GPU-driven with lca_invisible: a finest tile with more visible + invisible pairs "
                           "than this traverses their lowest common ancestor (0 = no limit)")
    lca_primary: bool = param(False, "GPU-driven: primary-ray passes take the LCA fallback too (lca_pairs, "
                              "lca_subtrees); False: a primary ray's tile always tests its pairs (more than max_batch "
                              "in several records): camera rays are coherent, and from about the root a tile's rays "
                              "visit glsl's ~27 nodes against ~14 below their pairs")
    coarse_cull: bool = param(True, "GPU-driven: a compute pass culls the queries whose boxes lie beyond the "
                              "farthest distance any ray of their tile may still reach")
    cold_start: str = param("auto", "how a new front gets its pairs: 'sync' (the paper's Algorithm 1: the front's "
                            "first passes refine it from (screen, root) through waves of queries whose results "
                            "the host waits for within the pass), 'device' (with device fronts, else as sync: "
                            "the front starts on the device (cold_start_pairs) and each pass refines it one level "
                            "from its own counts, as a steady pass does: no wait, no read, the same launches as a "
                            "steady pass; every pass is exact, and the first ones cost about a whole-BVH "
                            "traversal until the front has settled; the work probe waits for that) or 'auto' "
                            "(device where fronts live on the device (device_front) and are kept between frames "
                            "(temporal), else sync)")
    cold_start_pairs: int = param(16, "cold_start=device: before its first pass the new front is split on the "
                                  "host by the split rule as if every pair were entered, level by level while it "
                                  "holds at most this many pairs per finest tile (0: it starts as (screen, root)); "
                                  "those levels are the ones every view enters, and pairs no ray enters are culled "
                                  "and pulled up (settled after 2-9 frames instead of 9-16: city-near, sibenik-walk, "
                                  "city 10 M)")
    settle_splits: float = param(0.05, "cold_start=device: a front has settled once a pass splits at most this "
                                 "fraction of its pairs; the work probe measures settled fronts only (a young one "
                                 "would look wasteful). A young front splits 7-29 % of its pairs a pass, a settled "
                                 "one 1-4 % while the camera moves (city-near and sibenik-walk, camera rays and "
                                 "AO at 640x360, cold_start_pairs=0)")
    settle_probe: bool = param(True, "cold_start=device with share_sample_fronts and work_probe: while a front "
                               "shared by several sample passes (AO, diffuse, soft shadows) settles, the frame's "
                               "first pass measures its work every frame and still runs and refines it; the "
                               "later samples trace the whole BVH while the last measurement found the young "
                               "front wasteful (False: every pass runs the settling front)")
    cold_full_bvh: bool = param(True, "a front's synchronous refinement stops once so many finest tiles are over "
                                "the LCA limits that the GPU-driven pass would trace the whole BVH "
                                "(full_bvh_fraction), or once its query fragments exceed cold_query_budget per "
                                "ray, and the pass traces every ray with the full traversal instead; the front's "
                                "later passes do the same (incoherent rays) until the fronts are reset, unless "
                                "only the budget stopped a coherent refinement (cold_wave_queries): then the next "
                                "pass refines on (cold_passes)")
    cold_query_budget: float = param(48.0, "cold_full_bvh: query fragments per active ray of a synchronous pass's "
                                     "refinement (its waves; the re-queries of the pairs known are not counted) "
                                     "after which it stops refining (a full traversal tests about 50-60 boxes per "
                                     "ray; 0 = no budget)")
    cold_passes: int = param(2, "cold_full_bvh: a pass that stopped refining on cold_query_budget, its rays still "
                             "coherent (cold_wave_queries), traces the whole BVH, and the front's next pass goes "
                             "on refining with a fresh budget; after this many such stops every pass traces the "
                             "whole BVH (1 = at the first)")
    cold_wave_queries: float = param(5.5, "cold_full_bvh: a front stopped by cold_query_budget counts as coherent "
                                     "(cold_passes) while its refinement cost at most this many query fragments "
                                     "per active ray and wave (one BVH level; a traversal tests about 2 boxes per "
                                     "level): camera and AO rays of city 10 M cost 3.8-4.1, diffuse rays of "
                                     "city 150 k 6.9-8.2 (640x360)")
    gap_order: bool = param(True, "GPU-driven: the cull writes each tile's invisible pairs nearest first (by a lower "
                            "bound of their distance from the tile's ray origins), and a ray stops testing them at "
                            "the first one beyond its nearest hit (exact)")
    gap_order_visible: bool = param(True, "gap_order for the visible pairs' records too, in closest-hit passes: two "
                                    "dispatches before their draw (the tiles' ray origin boxes, the records' items "
                                    "sorted by gap); any-hit passes keep the visible items unsorted")
    cone_cull: bool = param(True, "GPU-driven: per tile a cone around its rays' directions and four side planes "
                            "(camera rays: the tile's frustum); the cull drops invisible pairs and, with "
                            "gap_order_visible, the visible pairs' records drop items whose box lies outside them "
                            "(no ray of the tile can enter it; exact); not in the cull of rays whose samples "
                            "share a cull (share_sample_fronts)")
    count_due_only: bool = param(True, "GPU-driven: only the visible pairs whose re-query is due this frame count "
                                 "the rays that enter them (the others' counts are never read; each count is a "
                                 "shader atomic per entered pair and ray); False: every visible pair counts")
    device_front: bool = param(True, "GPU-driven (with merge_tiles and lca_invisible): once its synchronous "
                               "refinement is done (its first pass, or cold_passes) a front lives on the device, "
                               "and each pass plans its records, culls, draws and refines the front in a fixed "
                               "chain of dispatches and indirect draws, with nothing read back in the pass "
                               "(statistics arrive after the frame); False: the host plans the records and reads "
                               "the counts back at the end of every pass")
    merge_kept: bool = param(True, "device fronts (with cull_sublevels=0): the cull runs before the visible pairs' "
                             "draw, and a tile with a visible record and at most max_batch kept invisible pairs "
                             "tests them in its last visible record's fragments, after that record's visible "
                             "pairs (one fragment per ray instead of two; its cull reaches as far as the rays' "
                             "tmax); other tiles keep the survivors' draw")
    visible_stage: str = param("auto", "device fronts: where the visible records are intersected: 'fragment' (one "
                               "instanced draw, a fragment per record and pixel), 'compute' (one dispatch, an "
                               "invocation per pixel over its tile's records, the ray set up once; then one "
                               "full-screen draw writes the hits through the depth test; the same hits) or 'auto' "
                               "(glsl's `stage`: fragment on a software rasterizer, which runs it faster, else compute "
                               "where a probe finds compute shaders 2x faster, as on an NVIDIA H100/H200)")
    work_probe: int = param(16, "device fronts: every this many passes (and at a front's first device pass) the "
                            "pass measures its work on a sparse grid of rays (box and triangle tests, "
                            "work_probe_stride) against the full traversal's for the same rays; a front that "
                            "saves too little (work_ratio_full) traces the whole BVH until a later measurement, "
                            "two passes of the front before it, says otherwise (0 = never measure)")
    work_probe_stride: int = param(8, "work_probe: the sampled pixels are runs of 8 neighbours in a row (a SIMD "
                                   "group's), every this many runs of every this many rows (8: 1/64 of the rays)")
    work_ratio_full: float = param(0.8, "work_probe, closest-hit rays: a front whose rays do more than this "
                                   "fraction of the full traversal's box and triangle tests saves no time, and "
                                   "traces the whole BVH instead (llvmpipe, the table2 frames at 640x360: city-near's "
                                   "camera rays at 0.60 run 0.92-1.07x glsl (0.62 and 1.2x at 1280x720), city-far's at "
                                   "0.93 0.68x, sibenik's at 0.96 0.81x)")
    work_ratio_full_any: float = param(0.65, "work_probe, any-hit rays (shadows, AO): the same limit (the same "
                                       "frames: city-near's AO at 0.44-0.51 runs 1.1-1.2x glsl; sponza's at 0.82-0.88 "
                                       "0.53x, conference's at 0.81-0.84 0.63x, city-far's at 0.92-1.01 0.84x, "
                                       "sibenik's at 0.99-1.02 0.78x)")
    share_sample_fronts: bool = param(True, "the sample passes of an effect (AO, diffuse, a light's soft "
                                      "shadows) share one front; on device fronts only the first of them in a "
                                      "frame measures (work_probe) and refines it (a front found wasteful: the "
                                      "later ones trace the whole BVH meanwhile); later any-hit ones also take its "
                                      "plan and run only their tile bounds, cull and draws (AO, whose samples share "
                                      "their origins and reach: the first pass culls by reach alone and the later "
                                      "ones take its cull and its rays' bestBits too), later closest-hit ones "
                                      "plan again (their visible order sorts the items for their own rays); exact "
                                      "either way (the cull covers every invisible pair for each pass's "
                                      "rays); False: one front per sample")
    hit_hint: bool = param(True, "temporal: each ray first tests the triangle its pixel hit in this front's previous "
                           "pass (a shadow cache for every ray type): an any-hit ray that hits it is done, a "
                           "closest-hit ray traverses with its distance as tmax (exact); not with a GPU budget, nor in "
                           "a pass captured for the overlays")

    @property
    def out_of_core(self) -> bool:
        return self.gpu_budget_mb > 0 or self.gpu_budget_fraction > 0

    def subtree_tri_bound(self, ray_type: RayType | None = None) -> int:
        """The triangle bound of the subtrees a front of `ray_type` schedules (None: any front's):
        max_subtree_tris, or (0) OOC_SUBTREE_TRIS out of core and for shadow rays (hard and soft),
        and none for the other rays in core. Why none: the bound forces the cut below subtrees the
        split rule would keep, and on a large scene that multiplies a tile's pairs; with 4096, city
        10 M's AO fronts had over lca_pairs pairs in 98 % of their tiles and traced the whole BVH
        (chcrt 0.97x glsl, primary+ao:4 at 640x360; 1.21x without a bound, 1.22x with 32,768, 1.11x
        with 8,192; city 1 M, 3 M and the test scenes unchanged or better). Rays towards a light
        were faster with the bound there (hard shadows 31 against 37 ms, soft 60 against 71;
        docs/results/chcrt.md)."""
        if self.max_subtree_tris > 0:
            return self.max_subtree_tris
        to_light = ray_type in (RayType.SHADOW, RayType.SOFT)
        return OOC_SUBTREE_TRIS if self.out_of_core or to_light else NO_TRI_BOUND

    def validate(self, source: str = "chcrt") -> None:
        if not (1 <= self.max_batch <= 24 and 1 <= self.max_multi <= 24):
            raise RtwalkError(f"{source}: max_batch and max_multi must be in 1..24")
        if self.gpu_budget_mb < 0 or not 0 <= self.gpu_budget_fraction <= 1:
            raise RtwalkError(f"{source}: gpu_budget_mb must be >= 0 and gpu_budget_fraction in 0..1")
        if not 0 <= self.leaf_cache <= MAX_LEAF_CACHE:
            raise RtwalkError(f"{source}: leaf_cache must be in 0..{MAX_LEAF_CACHE}")
        if self.full_bvh_stage not in STAGE_CHOICES or self.visible_stage not in STAGE_CHOICES:
            raise RtwalkError(f"{source}: full_bvh_stage and visible_stage must be one of {', '.join(STAGE_CHOICES)}")
        if self.cold_start not in COLD_STARTS:
            raise RtwalkError(f"{source}: cold_start must be one of {', '.join(COLD_STARTS)}")
        if self.query_mode not in QUERY_MODES:
            raise RtwalkError(f"{source}: query_mode must be one of {', '.join(QUERY_MODES)}")
        if not (self.t_q > 0 and self.t_q_primary > 0 and 0 < self.min_tile_fraction <= 1
                and self.max_subtree_height >= 1
                and self.max_subtree_tris >= 0 and self.requery_interval >= 1 and self.schedule_batch >= 1
                and self.visible_threshold >= 0 and self.lca_subtrees >= 0 and self.lca_pairs >= 0
                and self.cold_query_budget >= 0 and self.cold_passes >= 1 and self.cold_wave_queries >= 0
                and 0 <= self.cull_sublevels <= 4 and 0 <= self.full_bvh_fraction <= 1
                and self.work_probe >= 0 and self.work_probe_stride >= 1 and self.work_ratio_full > 0
                and self.work_ratio_full_any > 0 and 0 <= self.settle_splits <= 1 and self.cold_start_pairs >= 0):
            raise RtwalkError(f"{source}: t_q, t_q_primary, min_tile_fraction and work_ratio_full(_any) must be > 0, "
                              "thresholds and cold_start_pairs >= 0, counts >= 1, cull_sublevels in 0..4, "
                              "full_bvh_fraction and settle_splits in 0..1")

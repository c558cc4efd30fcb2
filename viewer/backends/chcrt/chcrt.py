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
See chc_intersect.frag for llvmpipe's loop limit and how rays that would reach it are finished.

Overlays (TraceResult.overlays, R32I at the ray-batch size, overwritten by the next pass while
overlays are wanted, `overlays_enabled`; left as they are otherwise):
``query_overdraw`` (query fragments per pixel, imageAtomicAdd) and ``subtree_id`` (canonical BVH
node of the scheduled subtree that produced the pixel's hit, -1 for none). Counters: see
``_Pass.stats`` (the spec's eight plus per-tile batch counts, waves, re-queries, pull-ups).

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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.base import BackendContext, TraceResult, WorkCounters
from viewer.backends.chcrt.chcrt_cache import MB, CachePlan, SubtreeCache
from viewer.backends.chcrt.chcrt_devfront import (
    ARGS_VISORDER,
    FRONT_SSBO,
    META_INTS,
    META_PROBE_FRONT,
    DeviceFront,
    DeviceFronts,
)
from viewer.backends.chcrt.chcrt_front import INNER, INVISIBLE, VISIBLE, NodeTables, PairFront
from viewer.backends.gl_traversal import ResumableTraversal, max_visits
from viewer.backends.interface import BackendInfo, OverlaySpec, param
from viewer.effects import RayType
from viewer.errors import RtwalkError
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_NODES, BIND_TRIS, backend_bindings
from viewer.gl.buffers import StreamBuffer
from viewer.gl.programs import FullscreenQuad, compute_shader
from viewer.gl.textures import (
    TexelView,
    clear_float_texture,
    clear_int_texture,
    copy_texture,
    float_depth_texture,
    float_texture,
    int_texture,
)
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.screen_tiles import max_tile_level, tile_rects

HERE = Path(__file__).resolve().parent  # the chc_* shaders

# chcrt's own binding points (viewer.gl.bindings.backend_bindings checks them against the table)
SSBO = {"BIND_CHC_ITEMS": 5,  # (tile, node) items of a batch draw
        "BIND_CHC_COUNT": 6,  # active ray count
        "BIND_CHC_DRAWS": 7,  # per-instance tile draws
        "BIND_CHC_QUERY_COUNTS": 8,  # per-query passed-fragment counts
        "BIND_CHC_CANDIDATES": 4,  # GPU-driven: the invisible pairs the cull kept (items)
        "BIND_CHC_INDIRECT": 12,  # GPU-driven: the indirect draw command being built
        "BIND_CHC_QUERIES": 13,  # GPU-driven: every query record of the pass, before the coarse cull
        "BIND_CHC_TILES": 14}  # GPU-driven: per finest tile, ray origin box and farthest reach
IMAGE = {"BIND_IMG_CHC_BEST": 0,  # packed closest hit per pixel
         "BIND_IMG_CHC_OVERDRAW": 1,  # query fragments per pixel (overlay)
         "BIND_IMG_CHC_BATCH": 2}  # subtrees in the pixel's batches (overlay)
HINT_UNIT = 2  # texture unit of the hit hints (rays: units 0 and 1)
ITEM_UNIT = 3  # texture unit of the items' buffer texture (chc_common.glsl loadItem)
# with the device fronts' (chcrt_devfront.py), and the items' texture unit
BINDINGS = {**backend_bindings({**SSBO, **FRONT_SSBO}, IMAGE), "BIND_TEX_CHC_ITEMS": ITEM_UNIT}
(BIND_CHC_ITEMS, BIND_CHC_COUNT, BIND_CHC_DRAWS, BIND_CHC_QUERY_COUNTS, BIND_CHC_CANDIDATES, BIND_CHC_INDIRECT,
 BIND_CHC_QUERIES, BIND_CHC_TILES) = SSBO.values()
BIND_IMG_CHC_BEST, BIND_IMG_CHC_OVERDRAW, BIND_IMG_CHC_BATCH = IMAGE.values()

# gap: written by chc_querycull.comp for the invisible pairs' items (a lower bound of the distance from
# every ray origin of the tile to the box, world units); 0 in host-made items
# (chc_records.glsl ChcItem: p2 = the pair's count slot, p0/p1 = its triangle range, id = its node)
ITEM_DTYPE = np.dtype([("bmin", "<f4", 3), ("ref", "<i4"), ("bmax", "<f4", 3), ("count", "<i4"),
                       ("gap", "<f4"), ("p2", "<i4"), ("p0", "<i4"), ("p1", "<i4"), ("id", "<i4"), ("pad2", "<i4", 3)])
assert ITEM_DTYPE.itemsize == 64
DRAW_DTYPE = np.dtype([("rect", "<i4", 4), ("info", "<i4", 4)])  # x, y, w, h; item base, count, query slot
QUERY_MODES = ("batched", "hw")
COUNT_SLOTS = 64
COUNT_BYTES = 4 * COUNT_SLOTS  # GPU-driven counts buffer: ray counts, then query counts from this offset
MAX_BOXES = 48  # boxes per query draw (max_multi pairs x 2 child boxes)
MAX_LEAF_CACHE = 16
TILE_BOUND_BYTES = 112  # chc_tilecone.glsl TileBound: origin box + reach, direction cone, side planes


@dataclass
class ChcrtParams:
    t_q: float = param(0.5, "split in object space if A_node/A_root > t_q * A_tile/A_screen")
    t_q_primary: float = param(0.7, "primary-ray fronts split with t_q times this (1 = t_q): a deeper front, fewer "
                               "nodes per camera ray below its pairs at more pair tests (their boxes beside a tile "
                               "are culled: cone_cull); other fronts keep t_q (AO: a deeper front goes full-BVH)")
    min_tile_fraction: float = param(0.015, "smallest tile, fraction of the screen (paper: 200x200 at 1080p)")
    max_subtree_height: int = param(24, "scheduled subtrees: traversal stack bound (paper: 24)")
    max_subtree_tris: int = param(4096, "scheduled subtrees: triangle bound")
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
    lca_pairs: int = param(64, "GPU-driven with lca_invisible: a finest tile with more visible + invisible pairs "
                           "than this traverses their lowest common ancestor (0 = no limit)")
    lca_primary: bool = param(False, "GPU-driven: primary-ray passes take the LCA fallback too (lca_pairs, "
                              "lca_subtrees); False: a primary ray's tile always tests its pairs (more than max_batch "
                              "in several records): camera rays are coherent, and from about the root a tile's rays "
                              "visit glsl's ~27 nodes against ~14 below their pairs")
    coarse_cull: bool = param(True, "GPU-driven: a compute pass culls the queries whose boxes lie beyond the "
                              "farthest distance any ray of their tile may still reach")
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
                            "(no ray of the tile can enter it; exact)")
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
                             "draw, and a tile with one visible record and at most max_batch kept invisible pairs "
                             "tests them in that record's fragments, after its visible pairs (one fragment per ray "
                             "instead of two; its cull reaches as far as the rays' tmax); other tiles keep the "
                             "survivors' draw")
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
                                      "frame measures (work_probe) and refines it; later any-hit ones also take its "
                                      "plan and run only their tile bounds, cull and draws, later closest-hit ones "
                                      "plan again (their visible order sorts the items for their own rays); exact "
                                      "either way (the cull still covers every invisible pair for each pass's "
                                      "rays); False: one front per sample")
    hit_hint: bool = param(True, "temporal: each ray first tests the triangle its pixel hit in this front's previous "
                           "pass (a shadow cache for every ray type): an any-hit ray that hits it is done, a "
                           "closest-hit ray traverses with its distance as tmax (exact); not with a GPU budget, nor in "
                           "a pass captured for the overlays")

    def validate(self, source: str = "chcrt") -> None:
        if not (1 <= self.max_batch <= 24 and 1 <= self.max_multi <= 24):
            raise RtwalkError(f"{source}: max_batch and max_multi must be in 1..24")
        if self.gpu_budget_mb < 0 or not 0 <= self.gpu_budget_fraction <= 1:
            raise RtwalkError(f"{source}: gpu_budget_mb must be >= 0 and gpu_budget_fraction in 0..1")
        if not 0 <= self.leaf_cache <= MAX_LEAF_CACHE:
            raise RtwalkError(f"{source}: leaf_cache must be in 0..{MAX_LEAF_CACHE}")
        if self.query_mode not in QUERY_MODES:
            raise RtwalkError(f"{source}: query_mode must be one of {', '.join(QUERY_MODES)}")
        if not (self.t_q > 0 and self.t_q_primary > 0 and 0 < self.min_tile_fraction <= 1
                and self.max_subtree_height >= 1
                and self.max_subtree_tris >= 1 and self.requery_interval >= 1 and self.schedule_batch >= 1
                and self.visible_threshold >= 0 and self.lca_subtrees >= 0 and self.lca_pairs >= 0
                and self.cold_query_budget >= 0 and self.cold_passes >= 1 and self.cold_wave_queries >= 0
                and 0 <= self.cull_sublevels <= 4 and 0 <= self.full_bvh_fraction <= 1
                and self.work_probe >= 0 and self.work_probe_stride >= 1 and self.work_ratio_full > 0
                and self.work_ratio_full_any > 0):
            raise RtwalkError(f"{source}: t_q, t_q_primary, min_tile_fraction and work_ratio_full(_any) must be > 0, "
                              "thresholds >= 0, counts >= 1, cull_sublevels in 0..4, full_bvh_fraction in 0..1")


def _to_finest_tiles(nd: np.ndarray, lvl: np.ndarray, tx: np.ndarray, ty: np.ndarray, sl: np.ndarray,
                     top: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each (node, tile) copied onto the tiles of level `top` (default: the deepest present) that its
    tile covers (a tile of level L is exactly its four children of level L + 1)."""
    top = int(lvl.max()) if top is None else top
    sh = top - lvl
    copies = np.left_shift(1, 2 * sh)
    idx = np.repeat(np.arange(len(nd)), copies)
    k = np.arange(len(idx)) - np.repeat(np.cumsum(copies) - copies, copies)
    s = sh[idx]
    side = np.left_shift(1, s)
    return (nd[idx], np.full(len(idx), top, np.int64), (tx[idx] << s) + k % side, (ty[idx] << s) + k // side,
            sl[idx])


def _clip_rects(rects: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Rects (x, y, w, h) cut to clip boxes (x0, y0, x1, y1, ends exclusive); empty ones get w = h = 0."""
    x0 = np.maximum(rects[:, 0], clip[:, 0])
    y0 = np.maximum(rects[:, 1], clip[:, 1])
    w = np.minimum(rects[:, 0] + rects[:, 2], clip[:, 2]) - x0
    h = np.minimum(rects[:, 1] + rects[:, 3], clip[:, 3]) - y0
    empty = (w <= 0) | (h <= 0)
    return np.stack([x0, y0, np.where(empty, 0, w), np.where(empty, 0, h)], 1)


def _union(bounds: np.ndarray) -> np.ndarray:
    """(n, 2, 4) per-box bounds -> (n, 4) bounds of both (an empty one has x0 > x1, y0 > y1)."""
    return np.concatenate([bounds[:, :, :2].min(1), bounds[:, :, 2:].max(1)], 1)


def _bounds_of_parents(split: np.ndarray, bounds: np.ndarray, children: np.ndarray, f: PairFront,
                       nt: NodeTables) -> np.ndarray:
    """Per child pair, where its query can pass: the parent's (`split`, per-box query bounds
    `bounds`) passing bounds of the child's node box for an object-space child (the parent's query
    drew its two children's boxes, left first), of both boxes for a child tile."""
    if len(children) == 0:
        return np.zeros((0, 4), np.int64)
    parents = f.parent[children]
    order = np.argsort(split)
    b = bounds[order[np.searchsorted(split[order], parents)]]
    out = _union(b)
    pn, cn = f.node[parents], f.node[children]
    obj = cn != pn
    box = np.where(cn == nt.left[pn], 0, 1)
    out[obj] = b[obj, box[obj]]
    return out


def _host_read(ctx: moderngl.Context, read) -> bytes:
    """A blocking device -> host read, counted (viewer.iostats: bytes, one host sync), after the
    barrier that makes the shaders' atomic counts visible to it (viewer.gl.io.host_barrier)."""
    glio.host_barrier(ctx)
    with iostats.timed_sync():
        data = read()
    iostats.to_host(len(data))
    return data


def _upload(sb: StreamBuffer, data: np.ndarray | bytes) -> None:
    sb.upload(data)  # counted by StreamBuffer (viewer.gl.io)


class _Targets:
    """GL objects at one ray-batch size."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int], max_level: int):
        self.size = size
        self.depth = float_depth_texture(ctx, size)
        self.best = int_texture(ctx, size)
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
        for obj in (self.hit_fbo, self.query_fbo, self.gather_fbo, self.depth, self.best, self.overdraw,
                    self.subtree, self.batch, self.gather_o, self.gather_d):
            if obj is not None:
                obj.release()


PHASES = ("chc:0-setup", "chc:1-intersect-visible", "chc:2-queries", "chc:3-traversal", "chc:4-final-intersect")
COUNTERS = ("queries", "multi_queries", "failed_multi_queries", "visible_pairs", "invisible_pairs",
            "subtrees_scheduled", "draws", "rays", "upload_bvh_mb", "upload_geom_mb")


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
        # one subtree at a time is on the traversal stack (chc_intersect.frag); subtrees found visible by
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
        self.merge_defs = {"CHC_MERGE_KEPT": 1} if self.merge_kept else {}
        iwd = {**wd, "LEAF_CACHE": int(self.p.leaf_cache)}  # intersection programs only
        if self.cache is not None:
            iwd["CHC_OOC"] = 1
        self.prog_init = progs.get("fullscreen.vert", "chc_init.frag", BINDINGS)
        self.prog_query = progs.get("fullscreen.vert", "chc_query.frag", {"CHC_MAX_ITEMS": MAX_BOXES, **wd})
        # rays that would reach llvmpipe's loop limit are finished by the glsl resumable traversal;
        # it counts into the same work counters (full-BVH passes and resumed rays are work too)
        self.finisher = ResumableTraversal(bc, self.work)
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
        self.steady_warm = False  # the steady passes' programs were drawn once, empty (_Pass.prewarm)
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
        self.tilebounds = compute_shader(self.ctx, "chc_tilebounds.comp", BINDINGS, (HERE,))
        # (the build that also initialises the rays: a device pass without an init draw)
        self.tilebounds_init = compute_shader(self.ctx, "chc_tilebounds.comp", {**BINDINGS, "CHC_INIT_RAYS": 1},
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
        return SubtreeCache(self.ctx, bvh, scene.triangles, scene.material_ids, budget, p.max_subtree_tris,
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
        probed = {"work_probe_fronts": 0.0, "work_probe_rays": 0.0, "work_probe_front": 0.0, "work_probe_full": 0.0}
        for slot, row in rows.items():
            dev = self.devfronts.fronts[slot]
            dev.full = frac > 0 and row.tiles > 0 and row.heavy_tiles >= frac * row.tiles
            if dev.measured and row.probe_rays > 0 and row.probe_full > 0:
                # work_probe: the front's pass measured its work against the full traversal's
                dev.measured = False
                dev.wasteful = row.probe_front > dev.work_ratio_full * row.probe_full
                for k, v in zip(probed, (1, row.probe_rays, row.probe_front, row.probe_full), strict=True):
                    probed[k] += v
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
            self.fronts[front_key] = front
        tr = _Pass(self, front, rays, ray_type, hits, pinfo)
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


class _Pass:
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
        self.overlays = bool(self.p.overdraw_overlay and be.overlays_enabled)
        # GPU-driven steady state: a front's first pass (and its next ones while its refinement is
        # unfinished, cold_passes) runs the synchronous algorithm (builds the front)
        self.gpu = be.gpu_driven and front.frames > 0 and not front.cold
        self.culled = False  # this pass's queries went through the coarse cull (stats read late)
        self.n_survivor_groups = 0
        self.survivor_items: moderngl.Buffer | None = None  # the survivors' items (None: be.kept_boxes)
        self.probe_base = -1  # work_probe: META index the pass's draws sum their work into (-1: no probe)
        self.lca_pairs: np.ndarray | None = None  # GPU-driven: slots of visible pairs drawn through an LCA
        self.untested: np.ndarray | None = None  # GPU-driven: invisible pairs only covered by LCA traversals
        self.refine_from = 0  # query fragments spent before the synchronous refinement (cold_query_budget)
        self.bounds = np.zeros((0, 2, 4), np.int64)  # the last _run_queries' passing bounds per query and box
        # hit_hint: the front's last hit triangle per pixel (None: first pass, or hints off)
        self.hint = be.hints.get(self.pinfo.key) if be.use_hints else None

    # -- GL helpers -------------------------------------------------------------------------------
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
        self.be.quad.render(self.be.prog_init)  # draws through FullscreenQuad are counted there
        # the next draws prune with bestBits and count into the images and SSBOs this one reset:
        # without the barrier a GPU may run them on last pass's values (llvmpipe runs in order)
        ctx.memory_barrier(moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.stats["draws"] += 1

    def _count_rays(self) -> None:
        """The pass's active rays into the ray-count slots (chc_count_rays.comp, one dispatch), in
        place of the init draw of a pass that traces the whole BVH."""
        w, h = self.size
        self.be.count_rays["raySize"] = (w, h)
        self.be.count_rays.run(-(-w // 64), -(-h // 64))  # a work group per 64x64 pixel region
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
        o, d = (np.frombuffer(_host_read(self.ctx, lambda a=a: tg.gather_fbo.read(components=4, dtype="f4",
                                                                                  attachment=a)),
                              np.float32).reshape(g, g, 4) for a in (0, 1))
        self.rep = (o, d)
        self.ctx.enable(moderngl.DEPTH_TEST)

    def _sync(self) -> None:
        if self.p.sync_phases:
            self.ctx.finish()

    def _read_ray_count(self) -> None:
        if not self.rays_read:
            self.stats["rays"] = int(np.frombuffer(_host_read(self.ctx, self.be.count_buf.read), np.uint32).sum())
            self.rays_read = True

    # -- queries ------------------------------------------------------------------------------------
    def _run_queries(self, groups: list[np.ndarray], clip: np.ndarray | None = None) -> np.ndarray:
        """One query per group of pairs (all pairs of a group share a tile); returns samples passed.
        `clip` (per group x0, y0, x1, y1, ends exclusive): only these pixels of the tile can pass
        (an ancestor's passing bounds); a query left with no pixel is answered 0 without a draw.
        The passing pixels' bounds of each query are left in self.bounds, (nq, 2, 4): those of its
        first box, then of all its other boxes (the whole clipped rect for both where the mode does
        not measure them).

        All queries are issued first, then all results are read (one wait per wave)."""
        nq = len(groups)
        if nq == 0:
            self.bounds = np.zeros((0, 2, 4), np.int64)
            return np.zeros(0, np.int64)
        f, nt = self.front, self.nt
        sizes = np.array([len(g) for g in groups])
        pairs = np.concatenate(groups)
        owner, bmin, bmax = nt.query_boxes(f.node[pairs])
        group_of_pair = np.repeat(np.arange(nq), sizes)
        gbox = group_of_pair[owner]
        nbox = np.bincount(gbox, minlength=nq)
        base = np.cumsum(nbox) - nbox
        items = np.zeros(len(owner), ITEM_DTYPE)
        items["bmin"] = bmin
        items["bmax"] = bmax
        items["id"] = f.node[pairs][owner]
        _upload(self.be.items, items)
        self.be.bind_items(self.be.items.buf)
        first = np.cumsum(sizes) - sizes
        rects = f.rects(pairs[first]).astype(np.int64)
        if clip is not None:
            rects = _clip_rects(rects, clip)
        live = (rects[:, 2] > 0) & (rects[:, 3] > 0)
        self.stats["query_pixels"] += int((rects[:, 2] * rects[:, 3]).sum())
        self.stats["queries"] += int(live.sum())
        whole = np.stack([rects[:, 0], rects[:, 1], rects[:, 0] + rects[:, 2], rects[:, 1] + rects[:, 3]], 1)
        self.bounds = np.repeat(whole[:, None, :], 2, 1)
        if self.be.batched:
            out = self._queries_batched(rects, base, nbox, live)
        else:
            out = self._queries_hw(rects, base, nbox, live)
        self._read_ray_count()
        return out

    def _queries_batched(self, rects: np.ndarray, base: np.ndarray, nbox: np.ndarray,
                         live: np.ndarray) -> np.ndarray:
        """All queries in one instanced draw; results from one buffer read."""
        nq = len(rects)
        recs = np.zeros(nq, DRAW_DTYPE)
        recs["rect"] = rects
        recs["info"][:, 0] = base
        recs["info"][:, 1] = nbox
        recs["info"][:, 2] = np.arange(nq)
        recs = recs[live]
        _upload(self.be.draws, recs)
        init = np.zeros(9 * nq, np.uint32)  # counts, then per query and box slot the passing bounds
        init[nq:].reshape(nq, 2, 4)[:, :, :2] = 0xFFFFFFFF  # (min x, min y, max x, max y)
        _upload(self.be.query_counts, init)
        prog = self.be.prog_query_b
        prog["countOverdraw"] = int(self.overlays)
        prog["boundsBase"] = nq
        prog["raySize"] = tuple(self.size)
        fbo = self.tg.query_fbo
        fbo.use()
        fbo.scissor = None
        self.ctx.disable(moderngl.DEPTH_TEST)
        if len(recs):
            self.be.vao_query_b.render(moderngl.TRIANGLES, vertices=6, instances=len(recs))
            self.stats["draws"] += 1
            iostats.gl_draw()
        raw = np.frombuffer(_host_read(self.ctx, lambda: self.be.query_counts.buf.read(size=36 * nq)),
                            np.uint32).astype(np.int64)
        out = raw[:nq]
        b = raw[nq:].reshape(nq, 2, 4).copy()
        b[:, :, 2:] += 1  # ends exclusive; a box no pixel passed keeps x0 > x1: empty
        passed = out > 0
        self.bounds[passed] = b[passed]
        self.ctx.enable(moderngl.DEPTH_TEST)
        return out

    def _queries_hw(self, rects: np.ndarray, base: np.ndarray, nbox: np.ndarray, live: np.ndarray) -> np.ndarray:
        """The paper's way: one scissored draw inside one occlusion query object per query."""
        prog = self.be.prog_query
        prog["countOverdraw"] = int(self.overlays)
        fbo = self.tg.query_fbo
        fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        u_base, u_count = prog["itemBase"], prog["itemCount"]
        render = self.be.quad.render
        used = []
        for i, (x, y, w, h) in enumerate(rects.tolist()):
            if not live[i]:
                used.append(None)
                continue
            fbo.scissor = (x, y, w, h)
            u_base.value = int(base[i])
            u_count.value = int(nbox[i])
            q = self.be.query(i)
            with q:
                render(prog)
            used.append(q)
        n = int(live.sum())
        self.stats["draws"] += n  # (the scissored quads count themselves, viewer.gl.io)
        iostats.gl_query(n)
        with iostats.timed_sync():  # the first result waits for the draws; the others are then ready
            out = np.array([q.samples if q is not None else 0 for q in used], np.int64)
        iostats.sync(max(n - 1, 0))  # one result read per query object
        iostats.to_host(8 * n)
        return out

    # -- intersection -------------------------------------------------------------------------------
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

    def _intersect(self, pairs: np.ndarray) -> None:
        """Intersect scheduled pairs. Out-of-core (paper 5.4): pairs whose subtree is cached first,
        then the others after their upload, in chunks that never overwrite a subtree still to be drawn."""
        cache = self.be.cache
        if cache is None or len(pairs) == 0:
            self._draw_subtrees(pairs)
            return
        nd = self.front.node[pairs]
        hit = cache.cached(nd)
        cache.t.hits += len(np.unique(nd[hit]))
        self._draw_subtrees(pairs[hit])
        rest = pairs[~hit]
        if len(rest) == 0:
            return
        rest_nd = nd[~hit]
        chunk: list[int] = []
        for n in np.unique(rest_nd).tolist():
            if chunk and not set(cache.evicts(n)).isdisjoint(chunk):
                self._draw_subtrees(rest[np.isin(rest_nd, chunk)])
                chunk = []
            cache.upload(n)
            chunk.append(n)
        self._draw_subtrees(rest[np.isin(rest_nd, chunk)])

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
                nd, lvl, tx, ty, sl = _to_finest_tiles(nd, lvl, tx, ty, sl)
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
        _upload(self.be.items, self._subtree_items(nd, sl))
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
            _upload(self.be.draws, recs)
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
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
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

    # -- Algorithm 1 --------------------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        be, f = self.be, self.front
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

    def _run_sync(self) -> None:
        """Algorithm 1 with query results read back within the pass (waves of queries)."""
        be, f, p = self.be, self.front, self.p
        prof = be.bc.profiler
        thr = self.threshold
        with prof.phase("chc:1-intersect-visible"):
            self._bind()
            self._init()
            if p.front_to_back and self.ray_type in (RayType.PRIMARY, RayType.SHADOW, RayType.SOFT):
                self._gather()
            visible = f.leaves(VISIBLE)
            self._intersect(visible)
            self.stats["phase1_subtrees"] = len(visible)
            self._sync()

        with prof.phase("chc:2-queries"):
            invisible = f.leaves(INVISIBLE)
            groups = f.multi_query_groups(invisible, p.max_multi)
            multi = [len(g) > 1 for g in groups]
            due = visible[f.requery_due(visible, self.frame_number())] if len(visible) else visible
            groups += [due[i:i + 1] for i in range(len(due))]
            self.stats["requeries"] = len(due)
            multi += [False] * len(due)
            res = self._run_queries(groups)
            qb = self.bounds
            n_inv_groups = len(groups) - len(due)
            became_visible = []
            retry: list[np.ndarray] = []
            wave_b: list[np.ndarray] = []  # passing bounds of each pair of `wave`: its children query within them
            retry_b: list[np.ndarray] = []  # a failed multi-query's bounds: its pairs pass only there
            for i in range(n_inv_groups):
                g = groups[i]
                if multi[i]:
                    self.stats["multi_queries"] += 1
                    if res[i] > thr:
                        self.stats["failed_multi_queries"] += 1
                        retry.append(g)
                        retry_b.append(np.repeat(_union(qb[i:i + 1]), len(g), 0))
                elif res[i] > thr:
                    became_visible.append(g)
                    wave_b.append(qb[i:i + 1])
                    f.pixels[g] = res[i]
                if res[i] <= thr:
                    f.age[g] += 1
            if len(due):
                rq = res[n_inv_groups:]
                f.state[due[rq <= thr]] = INVISIBLE
                f.age[due] = 0
                f.pixels[due] = rq
            wave = np.concatenate(became_visible) if became_visible else np.zeros(0, np.int64)
            wbounds = np.concatenate(wave_b) if wave_b else np.zeros((0, 2, 4), np.int64)
            pending = np.concatenate(retry) if retry else np.zeros(0, np.int64)
            pclip = np.concatenate(retry_b) if retry_b else np.zeros((0, 4), np.int64)
            self._sync()

        with prof.phase("chc:3-traversal"):
            scheduled: list[np.ndarray] = []
            n_sched = 0
            full = False  # cold_full_bvh: the refinement stopped, every ray takes the full traversal
            self.refine_from = self.stats["query_pixels"]  # the budget counts the refinement's queries
            while True:
                if len(wave):
                    term, obj, _ = f.classify(wave, self.nt, self.t_q, p.max_subtree_height,
                                              p.max_subtree_tris)
                    done = wave[term]
                    f.state[done] = VISIBLE
                    if len(done):
                        scheduled.append(done)
                        n_sched += len(done)
                    split = wave[~term]
                    children = f.subdivide(split, obj[~term], self.nt) if len(split) else split
                    pending = np.concatenate([pending, children])
                    pclip = np.concatenate([pclip, _bounds_of_parents(split, wbounds[~term], children, f, self.nt)])
                    wave = np.zeros(0, np.int64)
                if n_sched >= p.schedule_batch:
                    self._intersect(np.concatenate(scheduled))
                    scheduled, n_sched = [], 0
                if len(pending) == 0:
                    break
                why = self._incoherent()
                if why:
                    # this pass traces the whole BVH; a front stopped by its budget goes on refining
                    # in its next pass (cold_passes), an incoherent one stays on full traversals
                    full = True
                    f.cold_stops += why == "budget"
                    f.full_bvh = why == "incoherent" or f.cold_stops >= p.cold_passes
                    break
                self.stats["query_waves"] += 1
                res = self._run_queries([np.array([i]) for i in pending], pclip)
                vis = res > thr
                f.pixels[pending] = res
                f.age[pending[~vis]] += 1
                wave = pending[vis]
                wbounds = self.bounds[vis]
                pending = np.zeros(0, np.int64)
                pclip = np.zeros((0, 4), np.int64)
            self._sync()

        f.cold = full and not f.full_bvh  # refined to the end (or given up): later passes are GPU-driven
        with prof.phase("chc:4-final-intersect"):
            if full:
                # the hits found so far are replaced by the full traversal's (exact); the front keeps
                # what was refined, its untested pairs invisible (the next pass queries them, or, with
                # full_bvh, goes full-BVH too)
                self.be.finisher.run(self.rays, self.pinfo, self.hits)
                self.stats["full_bvh_passes"] = 1
                self.stats["draws"] += 1
            elif scheduled:
                self._intersect(np.concatenate(scheduled))
            self._read_ray_count()
            self._sync()

    def _incoherent(self) -> str | None:
        """cold_full_bvh, before each wave of a front's synchronous refinement (the GPU-driven pass
        follows it): "incoherent" when the GPU-driven pass would trace the whole BVH with the front as
        it stands (at least full_bvh_fraction of the finest tiles over lca_pairs pairs or lca_subtrees
        visible ones, as in _tile_plan); when this pass's refinement has cost more than a full
        traversal (cold_query_budget; the refinement's queries only, so that a pass that goes on
        with a front stopped before gets as far again whatever its re-queries of the known pairs
        cost), "budget" if it cost at most cold_wave_queries per ray and wave (coherent rays in a
        deep BVH: the front's next pass goes on), else "incoherent"; None: refine on."""
        p, f = self.p, self.front
        if not (p.cold_full_bvh and self.be.gpu_driven and f.cold and p.lca_invisible and p.merge_tiles
                and p.full_bvh_fraction > 0 and (p.lca_pairs > 0 or p.lca_subtrees > 0)):
            return None
        vis, inv = f.leaves(VISIBLE), f.leaves(INVISIBLE)
        heavy = self._heavy_tiles(self._per_finest_tile(vis), self._per_finest_tile(inv))
        if heavy.mean() >= p.full_bvh_fraction:
            return "incoherent"
        self._read_ray_count()
        spent = self.stats["query_pixels"] - self.refine_from
        rays = max(self.stats["rays"], 1)
        if p.cold_query_budget > 0 and spent > p.cold_query_budget * rays:
            waves = max(self.stats["query_waves"], 1)
            return "budget" if spent <= p.cold_wave_queries * rays * waves else "incoherent"
        return None

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

    def _per_finest_tile(self, pairs: np.ndarray) -> np.ndarray:
        """How many of `pairs` cover each finest tile (2^L x 2^L counts; a pair of a coarser tile
        covers all finest tiles inside it)."""
        f = self.front
        top = f.max_level
        out = np.zeros((1 << top, 1 << top), np.int64)
        lvl = f.level[pairs].astype(np.int64)
        for L in np.unique(lvl).tolist():
            sel = pairs[lvl == L]
            m = 1 << L
            c = np.bincount(f.ty[sel].astype(np.int64) * m + f.tx[sel].astype(np.int64), minlength=m * m)
            s = 1 << (top - L)
            out += np.repeat(np.repeat(c.reshape(m, m), s, axis=0), s, axis=1)
        return out

    # -- GPU-driven steady state ------------------------------------------------------------------
    def _run_gpu(self) -> None:
        """One pass in a fixed number of launches: the visible pairs (1 draw), the ray bounds of every
        finest tile (1 dispatch), the cull of the invisible pairs against them (1 dispatch) and the
        intersection of the survivors (1 indirect draw). The query is the intersection itself: a
        ray that enters a pair's box before its nearest hit so far counts into the pair's slot (the
        query's pass condition), so no separate query pass runs. One read of the counts at the end;
        the front is refined on the host for the next frame."""
        be, f = self.be, self.front
        prof = be.bc.profiler
        with prof.phase("chc:1-intersect-visible"):
            visible = f.leaves(VISIBLE)
            invisible = f.leaves(INVISIBLE)
            if self.threshold > 0 and len(invisible):
                # aggressive mode: a pair culled before (<= threshold rays entered) is not tested again
                # until its re-query is due
                invisible = invisible[(f.age[invisible] == 0) | f.requery_due(invisible, self.frame_number())]
            nslots = len(visible) + len(invisible)
            need = COUNT_BYTES + 4 * (nslots + 3)
            if be.gpu_counts.size < need:
                be.gpu_counts.release()
                be.gpu_counts = self.ctx.buffer(reserve=1 << (need - 1).bit_length())
            self._bind()
            self._init()
            be.gpu_counts.write(bytes(4 * (nslots + 3)), offset=COUNT_BYTES)
            iostats.to_device(4 * (nslots + 3))
            be.gpu_counts.bind_to_storage_buffer(BIND_CHC_QUERY_COUNTS, COUNT_BYTES, 4 * (nslots + 3))
            inv_copies = None
            full = f.full_bvh  # its synchronous refinement found the rays incoherent (cold_full_bvh)
            if full:
                pass
            elif self.p.lca_invisible and self.p.merge_tiles:
                vis_items, inv_copies = self._tile_plan(visible, invisible)
                n = 1 << f.max_level
                full = 0 < self.p.full_bvh_fraction <= self.stats["lca_tiles"] / (n * n)
                if not full:
                    nd, tile, sl = vis_items
                    self._draw_finest(nd, tile, self._due_slots(visible, sl))
            else:
                self._draw_subtrees(visible, self._due_slots(visible, np.arange(len(visible))))
            self.stats["phase1_subtrees"] = 0 if full else len(visible)
            self._sync()
        self._queries_and_traversal(full, lambda: self._cull_invisible(invisible, len(visible), nslots, inv_copies))
        with prof.phase("chc:4-final-intersect"):
            raw = np.frombuffer(_host_read(self.ctx, lambda: be.gpu_counts.read(size=COUNT_BYTES + 4 * (nslots + 3))),
                                np.uint32).astype(np.int64)
            self.stats["rays"] = int(raw[:COUNT_SLOTS].sum())
            cnt = raw[COUNT_SLOTS:]
            self.stats["query_pixels"] = int(cnt[nslots])
            self.stats["query_records_drawn"] = int(cnt[nslots + 1])
            self.rays_read = True
            if not full:  # a full-BVH pass counted nothing: the front stays as it is
                self._refine(visible, invisible, cnt[:nslots])

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

    # -- device-resident front ----------------------------------------------------------------------
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
            dev = f.device = dv.attach(f, n_tiles)
        full = f.full_bvh or dev.full
        sub = int(p.cull_sublevels)
        while sub > 0 and min(self.size) >> (level + sub) < 4:
            sub -= 1
        # share_sample_fronts: a later sample pass of a shared front in this frame; an any-hit one takes
        # the plan the frame's first left in the device fronts' buffers (no other plan since)
        frame = self.frame_number()
        later = p.share_sample_fronts and dev is not None and dev.decided_frame == frame
        plan_key = None if dev is None else (dev.slot, frame, tuple(self.size), level, sub)
        reuse = later and self.any_hit and not full and dv.last_plan == plan_key
        probe = wasted = False
        if dev is not None:
            if later:
                wasted = dev.decided_wasted  # the frame's first pass decided (no probe)
            elif dev.passes == 0 and be.use_hints and self.hint is None:
                # the front's first measurement waits for a pass with hit hints (a shared front's first
                # device pass can be a sample's first pass, in the frame that built it): without them
                # its rays do more work than in every later pass (city-near ao:20 at 640x360: 0.73 of
                # the full traversal's tests, against 0.46 a frame later)
                dev.decided_frame, dev.decided_wasted = frame, False
            else:
                probe, wasted = self._probe_plan(dev, full)
                dev.decided_frame, dev.decided_wasted = frame, wasted
                dev.passes += 1
            full = full or wasted
            dev.work_ratio_full = p.work_ratio_full_any if self.any_hit else p.work_ratio_full
            self.stats["wasted_front_passes"] = int(wasted)
        self.stats["shared_front_passes"] = int(later)  # (its refinement left to the frame's first pass)
        self.stats["shared_plan_passes"] = int(reuse)  # (its plan too)
        capacity = 0 if dev is None else dev.capacity
        need = COUNT_BYTES + 4 * (capacity + 3)
        if be.gpu_counts.size < need:
            be.gpu_counts.release()
            be.gpu_counts = self.ctx.buffer(reserve=1 << (need - 1).bit_length())
        report = self.pinfo.report
        merge = be.merge_kept and sub == 0 and not full
        common = dict(ray_slots=COUNT_SLOTS, frame=self.frame_number(), max_level=level, threshold=self.threshold,
                      requery_interval=p.requery_interval, seed=p.seed, report=report)
        with prof.phase("chc:0-setup"):
            if reuse:
                # the plan stands (records, items, tile plans, arguments): only the pass's counts
                # and the survivors' command zeroed (no tile plan, no front META touched); the cull
                # below still covers every invisible pair for this pass's rays
                dv.clear(be.gpu_counts, be.query_indirect, ray_slots=COUNT_SLOTS, capacity=capacity, slot=0)
                self.stats["draws"] += 1
            elif dev is None or wasted:
                # no front, or one that saves too little (work_probe): nothing to plan (the front's
                # META keeps its last plan for the host's decisions), only the pass's counts zeroed
                dv.clear(be.gpu_counts, be.query_indirect, ray_slots=COUNT_SLOTS, capacity=capacity,
                         slot=0 if dev is None else dev.slot)
                self.stats["draws"] += 1
            else:
                primary_only = self.ray_type == RayType.PRIMARY and not p.lca_primary
                dv.plan(dev, be.gpu_counts, be.query_indirect, size=tuple(self.size), max_batch=p.max_batch,
                        lca_pairs=p.lca_pairs, lca_subtrees=p.lca_subtrees, heavy_allowed=not primary_only,
                        cull_sub=sub, count_due_only=p.count_due_only, full=full, **common)
                dv.last_plan = None if full else plan_key
                self.stats["draws"] += 3 if full else 5
            self._bind()
            # without overlays, the init draw is left out: with merged kept pairs the tile bounds
            # below set bestBits and count the rays, texture clears do the rest (chc_tilebounds.comp
            # CHC_INIT_RAYS); a whole-BVH pass only counts its rays (the glsl traversal writes every hit)
            fused = merge and not be.overlays_enabled
            if fused:
                self._clear_hits()
            elif full and not be.overlays_enabled:
                self._count_rays()
            else:
                self._init(zeroed=True)
            be.gpu_counts.bind_to_storage_buffer(BIND_CHC_QUERY_COUNTS, COUNT_BYTES, 4 * (capacity + 3))
            if probe:
                self._probe_full(dv, dev)
            if merge:
                self._tile_bounds(level, n_tiles, init_rays=fused)  # (else after the init draw's bestBits)
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
                          max_tris=p.max_subtree_tris, **common)
                self.stats["draws"] += 4
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
            ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT)
            n = 1 if bounds_ready else 2
            self.stats["draws"] += n
            iostats.gl_draw(n)
        self._draw_records_indirect(dv.args, merge_kept=merge)

    def _cull_device(self, dv: DeviceFronts, dev, level: int, sub: int, merge: bool = False) -> None:
        """The invisible items the device planned, culled per cull tile (chc_tilebounds.comp, then
        chc_querycull.comp over the ranges chc_front_plan.comp wrote) into the survivors' records and
        their indirect draw command; buffers sized for the device's item capacity. `merge`
        (merge_kept, before the visible records, on the tile bounds already computed): the kept
        items go after the visible ones in dv.vis_items, and single-record tiles' kept ranges into
        their tile plans instead of survivors' records."""
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
        be.querycull["nQueries"] = n_cull
        be.querycull["maxItems"] = p.max_batch
        be.querycull["pixelSlot"] = dev.capacity
        be.querycull["cull"] = int(p.coarse_cull)
        be.querycull["sortByGap"] = int(p.gap_order)
        be.querycull["coneCull"] = int(p.cone_cull)
        be.querycull.run(-(-n_cull // 64))
        ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        n = 1 if merge else 2
        self.stats["draws"] += n
        iostats.gl_draw(n)

    def _due_slots(self, visible: np.ndarray, sl: np.ndarray) -> np.ndarray:
        """Count slots of visible-pair items (index into `visible`, -1 = not counted): with
        count_due_only, only pairs whose re-query is due this frame keep theirs (_refine reads no
        other visible pair's count), so the other items cost no atomic per entering ray."""
        if not self.p.count_due_only or len(visible) == 0:
            return sl
        due = self.front.requery_due(visible, self.frame_number())
        ok = sl >= 0
        ok[ok] = due[sl[ok]]
        return np.where(ok, sl, -1)

    def _cull_invisible(self, invisible: np.ndarray, slot0: int, nslots: int,
                        copies: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
        """Upload the invisible pairs copied onto the finest tiles they cover (intersection items
        with their count slots, sorted by tile), then on the GPU: per finest tile the rays' origin box
        and farthest reach (chc_tilebounds.comp), and per finest tile the pairs some ray may still
        enter (chc_querycull.comp), as records of the indirect intersection draw. `copies` (node,
        finest tile, slot): the copies left by _tile_plan (those of LCA tiles dropped). With
        cull_sublevels the bounds, the cull and the records are per sub-tile (each reads its finest
        tile's pairs): rays near a short hit no longer share a tile with far-reaching ones."""
        be, ctx, f = self.be, self.ctx, self.front
        level = f.max_level
        n = 1 << level
        ntiles = n * n
        if copies is None:
            nd, _, tx, ty, sl = _to_finest_tiles(
                f.node[invisible].astype(np.int64), f.level[invisible].astype(np.int64),
                f.tx[invisible].astype(np.int64), f.ty[invisible].astype(np.int64),
                slot0 + np.arange(len(invisible), dtype=np.int64), level)
            tile = ty * n + tx
        else:
            nd, tile, sl = copies
        self.n_survivor_groups = len(nd)
        self.stats["queries"] += len(invisible)
        if not len(nd):
            return
        order = np.argsort(tile, kind="stable")
        _upload(be.items, self._subtree_items(nd[order], sl[order]))
        be.bind_items(be.items.buf)
        counts = np.bincount(tile, minlength=ntiles)
        sub = int(self.p.cull_sublevels)
        while sub > 0 and min(self.size) >> (level + sub) < 4:
            sub -= 1
        cl = level + sub  # the cull's tile level
        m = 1 << cl
        nsub = m * m
        all_t = np.arange(nsub)
        sx, sy = all_t % m, all_t // m
        parent = (sy >> sub) * n + (sx >> sub)
        ranges = np.zeros(nsub, DRAW_DTYPE)
        ranges["rect"] = tile_rects(np.full(nsub, cl), sx, sy, self.size)
        ranges["info"][:, 0] = (np.cumsum(counts) - counts)[parent]
        ranges["info"][:, 1] = counts[parent]
        mb = self.p.max_batch
        need = max(int((-(-counts // mb)).sum()) << (2 * sub), 1) * DRAW_DTYPE.itemsize
        if be.survivors.size < need:
            be.survivors.release()
            be.survivors = ctx.buffer(reserve=1 << (need - 1).bit_length())
        need = max(len(nd) << (2 * sub), 1) * ITEM_DTYPE.itemsize
        if be.kept_boxes.size < need:
            be.kept_boxes.release()
            be.kept_boxes = ctx.buffer(reserve=1 << (need - 1).bit_length())
        _upload(be.all_queries, ranges)
        be.query_indirect.write(np.array([6, 0, 0, 0], np.uint32).tobytes())
        iostats.to_device(16)
        be.kept_boxes.bind_to_storage_buffer(BIND_CHC_CANDIDATES)
        be.survivors.bind_to_storage_buffer(BIND_CHC_DRAWS)
        be.query_indirect.bind_to_storage_buffer(BIND_CHC_INDIRECT)
        self._tile_bounds(cl, nsub)  # after the visible pairs' bestBits
        be.querycull["nQueries"] = nsub
        be.querycull["maxItems"] = mb
        be.querycull["pixelSlot"] = nslots
        be.querycull["cull"] = int(self.p.coarse_cull)
        be.querycull["sortByGap"] = int(self.p.gap_order)
        be.querycull["coneCull"] = int(self.p.cone_cull)
        be.querycull.run(-(-nsub // 64))
        ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.stats["draws"] += 2
        iostats.gl_draw(2)

    def _tile_plan(self, visible: np.ndarray, invisible: np.ndarray
                   ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """GPU-driven, per finest tile: the visible and invisible pairs over it (copied onto the
        finest tiles), as (node, tile, count slot). A tile with more than `lca_pairs` pairs in all (or
        `lca_subtrees` visible ones) would test every pair's box per ray (incoherent rays: more box tests
        than one
        full traversal); it traverses the lowest common ancestor of all its pairs once instead (the
        front is a cut of the BVH, so that subtree holds all of them: exact), and its invisible
        pairs are neither queried nor counted (they keep their state, see _refine)."""
        f, nt = self.front, self.nt
        level = f.max_level
        n = 1 << level
        nv = len(visible)

        def copies(pairs: np.ndarray, slot0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            nd, _, tx, ty, sl = _to_finest_tiles(
                f.node[pairs].astype(np.int64), f.level[pairs].astype(np.int64), f.tx[pairs].astype(np.int64),
                f.ty[pairs].astype(np.int64), slot0 + np.arange(len(pairs), dtype=np.int64), level)
            return nd, ty * n + tx, sl

        vn, vt, vs = copies(visible, 0)
        inn, it, isl = copies(invisible, nv)
        heavy = self._heavy_tiles(np.bincount(vt, minlength=n * n), np.bincount(it, minlength=n * n))
        hv, hi = heavy[vt], heavy[it]
        tiles = np.concatenate([vt[hv], it[hi]])
        nodes = np.concatenate([vn[hv], inn[hi]])
        o = np.argsort(tiles, kind="stable")
        tiles, nodes = tiles[o], nodes[o]
        starts = np.flatnonzero(np.r_[True, tiles[1:] != tiles[:-1]]) if len(tiles) else np.zeros(0, np.int64)
        lca = nt.group_lca(nodes, starts)
        self.lca_pairs = vs[hv]
        self.stats["lca_tiles"] += len(starts)
        dropped = np.ones(len(invisible), bool)
        dropped[isl[~hi] - nv] = False
        self.untested = invisible[dropped]
        vis = (np.concatenate([vn[~hv], lca]), np.concatenate([vt[~hv], tiles[starts]]),
               np.concatenate([vs[~hv], np.full(len(starts), -1, np.int64)]))
        return vis, (inn[~hi], it[~hi], isl[~hi])

    def _draw_finest(self, nd: np.ndarray, tile: np.ndarray, sl: np.ndarray) -> None:
        """GPU-driven: intersect items (node, finest tile, count slot) in one instanced draw: one
        record per finest tile (more where a tile has more than max_batch items)."""
        if len(nd) == 0:
            return
        f = self.front
        level = f.max_level
        n = 1 << level
        self.stats["subtrees_scheduled"] += len(nd)
        o = np.argsort(tile, kind="stable")
        nd, tile, sl = nd[o], tile[o], sl[o]
        starts = np.flatnonzero(np.r_[True, tile[1:] != tile[:-1]])
        ends = np.r_[starts[1:], len(nd)]
        t = tile[starts]
        rects = tile_rects(np.full(len(t), level), t % n, t // n, self.size)
        order = self.p.gap_order and self.p.gap_order_visible and not self.any_hit
        self._draw_batches(nd, sl, rects, starts, ends, t if order else None)

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
        for comp in comps:
            comp.run_indirect(zero)
        dv.prewarm(zero)
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

    def _refine(self, visible: np.ndarray, invisible: np.ndarray, cnt: np.ndarray) -> None:
        """Apply this pass's counts to the front (for the next frame): an invisible pair that rays
        entered becomes visible (terminated) or is split (its children are tested next frame);
        culled pairs age; a visible leaf whose re-query is due and that no ray entered (its own
        count, or a lowest common ancestor standing for it: then it is left visible) becomes
        invisible."""
        f, p, thr = self.front, self.p, self.threshold
        nv = len(visible)
        cv, ci = cnt[:nv], cnt[nv:]
        seen = ci > thr
        wave = invisible[seen]
        f.pixels[wave] = ci[seen]
        unseen = invisible[~seen]
        if self.untested is not None and len(self.untested):
            unseen = unseen[~np.isin(unseen, self.untested)]  # not queried (LCA tiles): not aged
        f.age[unseen] += 1
        self.stats["newly_visible_queries"] += int(seen.sum())
        if nv:
            due = f.requery_due(visible, self.frame_number())
            self.stats["requeries"] = int(due.sum())
            gone = due & (cv <= thr) & ~self.lca_covered(visible)
            f.state[visible[gone]] = INVISIBLE
            f.age[visible[due]] = 0
            f.pixels[visible[due]] = cv[due]
        if len(wave):
            term, obj, _ = f.classify(wave, self.nt, self.t_q, p.max_subtree_height, p.max_subtree_tris)
            f.state[wave[term]] = VISIBLE
            split = wave[~term]
            if len(split):
                f.subdivide(split, obj[~term], self.nt)

    def lca_covered(self, visible: np.ndarray) -> np.ndarray:
        """Visible pairs drawn through a lowest common ancestor this pass (their counts are not theirs)."""
        out = np.zeros(len(visible), bool)
        if self.lca_pairs is not None:
            out[self.lca_pairs] = True
        return out

    def frame_number(self) -> int:
        return self.be.frame

"""voxelwalk: reflection rays through a uniform grid, walked by each ray alone or with coherence
enforced by sorting (Guntury, "Raytracing Dynamic Scenes on GPU", IIIT Hyderabad 2011, ch. 5).

The grid is the shared one of viewer.accel.grid (sorted triangle-cell pairs), by default with
ugrid's second level (viewer.accel.grid2: dense top cells get a sub-grid and a short list of their
big triangles; levels=1: the uniform grid alone), built on the OpenCL device at creation and again
when the scene's triangles change (or every frame with rebuild=true, as an animated scene needs).

* IVW (mode=ivw, the default): one work-item per ray walks the grid by 3D-DDA and stops at the first cell that
  holds a hit inside the cell (ivw.cl), testing each cell's triangles four at a time. Any-hit rays
  (shadow, soft, AO) always go this way, stopping at their first hit, and so do primary rays
  unless primary=ec: they share the eye, so neighbouring pixels already walk the same cells in the
  same order and sorting them by cell adds nothing (the IVW fast path). A top cell with a
  sub-grid is walked through it (big list, then sub-cells; grid2_walk.cl, shared with ugrid).
* EC (mode=ec: then for the other closest-hit rays; not the default since it loses to IVW on every
  scene measured on this CPU device (mixed-scale reflections 4.0-4.4x clbvh against IVW's 2.7-3.0x,
  the dragon's 5.2-5.3x against 1.6-1.7x, conference IVW/EC 0.62), as on the thesis's cached
  GTX 480 (IVW/EC 0.37-0.54); it won only on the cacheless GTX 280), in iterations of one
  non-empty cell per ray, rays of the same cell processed together, resolved rays dropping out:
  - sort=tile (default, ec_tile.cl): every iteration on the device in one launch: one
    work-group per screen-tile partition of the active rays loops over its iterations (walk to the
    next non-empty cell, counting sort by cell through a local hash table, chunks of at most
    `chunk` rays of one cell with the cell's triangles staged in local memory, resolve). On the
    two-level grid the unit of an iteration is a top cell without sub-grid, a sub-grid's big list
    or one of its non-empty sub-cells (in IVW's order), so rays reaching a dense object are sorted
    by its sub-cells. Units of at most `inline` triangles (default 4, one block) are tested in the
    walk, not sorted (sorting them cost more than their tests: 96% of the mixed scene's reflection
    units), and each ray first walks alone to its first unit to sort (ec_tile_first). A fixed 5
    launches and one wait per pass whatever the iteration count; hits equal IVW's bit for bit.
  - sort=global (the thesis's, ec.cl; also whenever cells != 1): each active ray emits its
    (ray, cell) pairs for its next `cells` non-empty cells (count, scan, write), the pairs are
    radix-sorted by cell over all rays, cut into chunks of at most `chunk` rays, compacted, and
    one work-group per chunk tests the staged triangles; nearest hits by an atomic minimum on
    packed (distance, triangle) keys. About 24 launches per iteration (one wait per pass). It
    walks the top level only (the top lists stay whole on the two-level grid).

With skip=ivw/ec/all, IVW and/or the one-launch EC skip empty 8^3 blocks of top cells whole,
landing on the cell and walk state the cell-by-cell 3D-DDA would reach (walk.cl); off by default
(measured slower on the mixed-scale and dragon benches, docs/backends/voxelwalk.md). Both modes
are exact (the watertight test of viewer/cl/kernels/geometry.cl, the grid's conservative binning,
and the hit-inside-cell rule).
Resolution: `auto` takes grid.py's rule (about `density` cells per triangle, shaped like
the scene's box: extents per axis and triangle density), N fixes N cells on the longest axis (the
thesis used 128^3); the cells per axis are counters res_x/y/z.

Overlays: "iterations" (non-empty cells visited per ray) and "tile_divergence" (distinct first
cells per 8x8 pixel tile). Counters: the grid (res_x/y/z, pairs, build time; once per frame),
EC ray-cell pairs, work-groups after compaction and iterations (EC passes); with overlays shown
(or stats=true) per ray type (suffix _<effect>): iterations per walking ray (mean, max), rays per
cell at the first iteration (mean, max),
the % of rays resolved at the first iteration and the mean tile divergence. The per-iteration
series are in `last_stats` (viewer.bench.voxelwalk reads them).
"""

from __future__ import annotations

from dataclasses import dataclass

from viewer.accel.grid import GridSpec, scene_box
from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.cl_geometry import GeometryBackend
from viewer.backends.interface import BackendInfo, OverlaySpec, param
from viewer.backends.ugrid import top_density
from viewer.backends.voxelwalk.engine import (
    CHUNKS,
    EC_INLINE_MAX,
    EC_SORTS,
    EC_TAIL,
    SKIPS,
    PassStats,
    VoxelWalker,
    tile_divergence,
)
from viewer.effects import RayType
from viewer.errors import RtwalkError
from viewer.rays import HitBuffer, PassInfo, RayBatch

__all__ = ["VoxelwalkParams", "VoxelwalkBackend", "VoxelWalker", "PassStats", "tile_divergence"]

MODES = ("ivw", "ec")


@dataclass
class VoxelwalkParams:
    mode: str = param("ivw", "closest-hit rays: ivw (independent walk; default: faster on every scene measured, as "
                      "on the thesis's cached GPU) or ec (enforced coherence)")
    chunk: int = param(64, "EC: rays per chunk = work-group size")
    resolution: str = param("auto", "auto (grid.py's rule from the scene) or N cells on the longest axis")
    cells: int = param(1, "EC: non-empty cells per ray per iteration (0: every cell the ray crosses at once)")
    primary: str = param("ivw", "closest-hit primary rays: ivw (they share the eye, so neighbouring pixels already "
                         "walk the same cells together and sorting them adds nothing: the IVW fast path) or "
                         "ec (EC them too)")
    sort: str = param("tile", "EC: tile (every iteration in one launch: one work-group per screen-tile partition "
                      "sorts its rays by cell on the device) or global (the thesis: a global radix sort per "
                      "iteration, launches grow with the iterations); cells != 1 always sorts globally")
    density: float = param(0.0, "auto resolution: about this many cells per triangle (0: 2 for levels=1, a coarse "
                           "0.25 top level for levels=2, ugrid's default)")
    rebuild: bool = param(False, "rebuild the grid every frame (animated scenes; timing studies)")
    stats: bool = param(False, "per-iteration statistics every pass (else only while overlays are shown)")
    levels: int = param(2, "2: dense cells' sub-grids too (the two-level grid of viewer.accel.grid2, as ugrid's), "
                        "walked by IVW and the one-launch EC (sort=tile; sort=global walks the top level); "
                        "1: the uniform grid alone")
    inline: int = param(EC_INLINE_MAX, "EC (sort=tile): units (cells, sub-cells, big lists) of at most this many "
                        "triangles are tested in the walk instead of sorted (a one-block unit costs more to sort "
                        "than to test); 0: every unit sorted")
    tail: int = param(EC_TAIL, "EC (sort=tile): a partition down to fewer than this many active rays finishes "
                      "them walking alone (sorting a handful of rays gathers nothing); 0: never")
    skip: str = param("none", "walks that skip empty 8^3 blocks of top cells whole: none, ivw, ec or all (the same "
                      "cells either way; measured slower on the mixed-scale and dragon benches)")

    def validate(self, source: str) -> None:
        if self.mode not in MODES:
            raise RtwalkError(f"{source}: mode must be ivw or ec (got '{self.mode}')")
        if self.chunk not in CHUNKS:
            raise RtwalkError(f"{source}: chunk must be one of 16, 32, 64, 128, 256 (got {self.chunk})")
        if self.resolution != "auto":
            try:
                r = int(self.resolution)
            except ValueError:
                raise RtwalkError(f"{source}: resolution must be auto or a whole number (got '{self.resolution}')") \
                    from None
            if not 1 <= r <= 1024:
                raise RtwalkError(f"{source}: resolution must be auto or in 1..1024 (got {r})")
        if self.primary not in MODES:
            raise RtwalkError(f"{source}: primary must be ivw or ec (got '{self.primary}')")
        if self.sort not in EC_SORTS:
            raise RtwalkError(f"{source}: sort must be tile or global (got '{self.sort}')")
        if not 0 <= self.cells <= 4096:
            raise RtwalkError(f"{source}: cells must be in 0..4096 (got {self.cells})")
        if not self.density >= 0:
            raise RtwalkError(f"{source}: density must be >= 0 (0: automatic; got {self.density})")
        if self.skip not in SKIPS:
            raise RtwalkError(f"{source}: skip must be none, ivw, ec or all (got '{self.skip}')")
        if not 0 <= self.inline <= 4096:
            raise RtwalkError(f"{source}: inline must be in 0..4096 (got {self.inline})")
        if not 0 <= self.tail <= 1 << 20:
            raise RtwalkError(f"{source}: tail must be in 0..1048576 (got {self.tail})")
        if self.levels not in (1, 2):
            raise RtwalkError(f"{source}: levels must be 1 or 2 (got {self.levels})")

    def spec(self) -> GridSpec:
        res = 0 if self.resolution == "auto" else int(self.resolution)
        return GridSpec(density=top_density(self.density, self.levels), resolution=res, max_axis=max(512, res))


class VoxelwalkBackend(GeometryBackend):
    info = BackendInfo(
        "voxelwalk", "OpenCL: uniform grid walked by each ray alone (IVW) or with coherence enforced by sorting "
        "ray-cell pairs by cell (EC)", params=VoxelwalkParams,
        overlays=(OverlaySpec("tile_divergence", "heat", "tile_divergence",
                              "distinct cells per 8x8 pixel tile (first iteration)"),
                  OverlaySpec("iterations", "heat", "iterations", "iterations (non-empty cells visited) per ray")),
        counters=("rays", "res_x", "res_y", "res_z", "grid_build_ms", "pairs", "sorted_pairs", "workgroups",
                  "iterations",
                  "iterations_mean_reflections", "rays_per_cell_reflections", "rays_per_cell_max_reflections",
                  "resolved_first_pct_reflections", "tile_divergence_reflections"),
        device="cl")

    def __init__(self, bc: BackendContext, params: VoxelwalkParams | None = None):
        from viewer.cl import PassStages

        self._start(bc, params)
        if self.params.levels == 2:
            from viewer.accel.grid2 import TwoLevelGrid

            self.grid.release()
            self.grid = TwoLevelGrid(self.ctx)
        self.walker = VoxelWalker(self.ctx, self.grid, self.params.chunk, self.params.cells, self.params.sort,
                                  self.params.skip, self.params.inline, self.params.tail)
        self.stages = PassStages(self.ctx)
        self.last_stats: PassStats | None = None
        self._frame_stats: dict[str, float] = {}  # reported by the frame's first pass (the renderer sums passes)
        self._build_ms = 0.0
        self._rebuild()

    # -- geometry (viewer.backends.cl_geometry) --------------------------------------------
    def _rebuild(self) -> None:
        with self.bc.profiler.cl_phase("voxelwalk:build", self.ctx.queue):
            tris = self._upload_triangles("voxelwalk triangles")
            gs = self.grid.build(self._tris, len(tris), *scene_box(tris), self.params.spec())
        self._build_ms += gs.build_ms  # reported by the next frame

    @property
    def resolution(self) -> tuple[int, int, int]:
        return self.grid.stats.res

    def _frame_started(self) -> None:
        gs = self.grid.stats
        self._frame_stats = {"res_x": float(gs.res[0]), "res_y": float(gs.res[1]), "res_z": float(gs.res[2]),
                             "grid_pairs": float(gs.pairs), "grid_build_ms": self._build_ms}
        self._build_ms = 0.0

    # -- tracing --------------------------------------------------------------------------
    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        rs, hs = self.stages.get(rays.size)
        with self.bc.profiler.cl_phase("voxelwalk:upload", self.ctx.queue):
            rs.upload(rays)
        return self._trace(rs, hs, pinfo, rays.size, hits)

    def trace_device(self, rays, pinfo: PassInfo, hits) -> TraceResult:
        """Trace CL ray buffers (viewer.cl.RayStage layout) into CL hit buffers (HitStage)."""
        return self._trace(rays, hits, pinfo, rays.size, None)

    def _trace(self, rs, hs, pinfo: PassInfo, size: tuple[int, int], hits: HitBuffer | None) -> TraceResult:
        """One pass on CL buffers; `hits` (a RayBatch frame) gets the hits written back."""
        prof = self.bc.profiler
        q = self.ctx.queue
        want = bool(self.overlays_enabled or self.params.stats)
        ec = self.params.mode == "ec" and not pinfo.any_hit and \
            (pinfo.ray_type != RayType.PRIMARY or self.params.primary == "ec")
        with prof.cl_phase(f"trace:{pinfo.ray_type.label}", q):
            if ec:
                ps = self.walker.trace_ec(self._tris, rs.origin, rs.dir, hs.t, hs.tri, rs.n, stats=want,
                                          size=size)
            else:
                ps = self.walker.trace_ivw(self._tris, rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit, stats=want)
        if hits is not None:
            with prof.cl_phase("voxelwalk:download", q):
                hs.download(hits)
        self.last_stats = ps
        # per frame: grid figures once (first pass); ratios per ray type (the renderer sums a frame's passes)
        stats = {"rays": float(rs.n), **self._frame_stats}
        self._frame_stats = {}
        label = pinfo.ray_type.label
        if ec:
            stats.update({"pairs": float(ps.pairs), "sorted_pairs": float(ps.sorted_pairs),
                          "sorted_rays": float(ps.sorted_rays), "workgroups": float(ps.workgroups),
                          "iterations": float(ps.iterations), "ec_reorder_ms": ps.reorder_ms,
                          "ec_trace_ms": ps.trace_ms})
        overlays = {}
        if want and ps.iters is not None:
            if ps.rays_per_cell is not None and len(ps.rays_per_cell):
                stats[f"rays_per_cell_{label}"] = float(ps.rays_per_cell.mean())
                stats[f"rays_per_cell_max_{label}"] = float(ps.rays_per_cell.max())
            res = ps.resolved_fraction()
            if len(res):
                stats[f"resolved_first_pct_{label}"] = 100.0 * float(res[0])
            walked = ps.iters[ps.iters > 0]
            stats[f"iterations_mean_{label}"] = float(walked.mean()) if len(walked) else 0.0
            stats[f"iterations_max_{label}"] = float(walked.max()) if len(walked) else 0.0
            div = None
            if ps.first_cell is not None:
                div, per_tile = tile_divergence(ps.first_cell, size)
                if len(per_tile):
                    stats[f"tile_divergence_{label}"] = float(per_tile.mean())
            if self.overlays_enabled:
                overlays["iterations"] = self.textures.write("iterations", size, ps.iters)
                if div is not None:
                    overlays["tile_divergence"] = self.textures.write("tile_divergence", size, div)
        return TraceResult(stats=stats, overlays=overlays)

    def release(self) -> None:
        self.walker.release()
        self._release_own()

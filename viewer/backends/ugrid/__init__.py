"""ugrid: the uniform-grid baseline (Kalojanov & Slusallek build, Amanatides & Woo 3D-DDA walk).

The grid (viewer.accel.grid) is built on the OpenCL device from the leaf-ordered triangles at
creation and again whenever the scene's triangles change (checked in begin_frame); one work-item
per ray walks it (trace.cl beside this file), testing each visited cell's triangles with the
watertight test of viewer/cl/kernels/geometry.cl. Every ray type is traced the same way;
closest-hit rays stop after the first cell that contains their nearest hit, any-hit rays at
the first hit.

By default (levels=2) the grid is two-level (viewer.accel.grid2: dense top cells get a sub-grid
fitted to their small triangles and a short list of their big ones; the teapot-in-a-stadium case,
docs/results/grids-far-and-mixed.md); levels=1 walks the uniform grid alone.

Parameters (`--backend-params`): density (cells per triangle for the automatic resolution; 0, the
default: 2 for levels=1, a coarse 0.25 for the top of the two-level grid, whose dense cells get
the sub-grids),
resolution (cells along the longest axis; 0 = automatic), max_axis (cap per axis), rebuild
(rebuild the grid every frame, as an animated scene needs), levels, sub_min, sub_density.
Overlay "triangle_tests": triangles tested per ray of the last pass (heat).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.grid import GridSpec, UniformGrid, scene_box
from viewer.accel.grid2 import TOP_DENSITY, SubSpec, TwoLevelGrid
from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.cl_geometry import GeometryBackend
from viewer.backends.interface import BackendInfo, OverlaySpec, param
from viewer.cl import io as clio
from viewer.errors import RtwalkError
from viewer.rays import HitBuffer, PassInfo, RayBatch

KERNEL = Path(__file__).resolve().parent / "trace.cl"
WG = 64


def top_density(density: float, levels: int) -> float:
    """The grid's cells per triangle: `density`, or for 0 the default of a one-level grid (2) or
    of a two-level grid's coarse top level (viewer.accel.grid2.TOP_DENSITY)."""
    if density > 0:
        return density
    return TOP_DENSITY if levels == 2 else GridSpec().density


@dataclass
class UgridParams:
    density: float = param(0.0, "~cells per triangle (automatic resolution, per axis by the scene's extent); 0: 2 "
                           "for levels=1, a coarse 0.25 top level for levels=2 (viewer.accel.grid2.TOP_DENSITY)")
    resolution: int = param(0, ">0: cells along the longest axis instead")
    max_axis: int = param(512, "cap on cells per axis")
    rebuild: bool = param(False, "rebuild every frame (animated scenes; timing studies)")
    levels: int = param(2, "2: dense cells get sub-grids (two-level grid, viewer.accel.grid2); 1: uniform grid")
    sub_min: int = param(16, "small triangles a top cell needs for a sub-grid (levels=2)")
    sub_density: float = param(1.0, "sub-cells per small triangle (levels=2)")
    sub_big: float = param(0.5, "a triangle whose box spans this many top cells on an axis is 'big': kept in its "
                           "cells' short lists, not in their sub-grids (levels=2)")

    def validate(self, source: str) -> None:
        if not self.density >= 0:
            raise RtwalkError(f"{source}: density must be >= 0 (0: automatic; got {self.density})")
        if not 0 <= self.resolution <= 2048:
            raise RtwalkError(f"{source}: resolution must be in 0..2048 (got {self.resolution})")
        if not 1 <= self.max_axis <= 2048:
            raise RtwalkError(f"{source}: max_axis must be in 1..2048 (got {self.max_axis})")
        if self.levels not in (1, 2):
            raise RtwalkError(f"{source}: levels must be 1 or 2 (got {self.levels})")
        if not self.sub_min >= 1:
            raise RtwalkError(f"{source}: sub_min must be >= 1 (got {self.sub_min})")
        if not self.sub_density > 0:
            raise RtwalkError(f"{source}: sub_density must be > 0 (got {self.sub_density})")
        if not self.sub_big > 0:
            raise RtwalkError(f"{source}: sub_big must be > 0 (got {self.sub_big})")

    def spec(self) -> GridSpec:
        return GridSpec(density=top_density(self.density, self.levels), resolution=self.resolution,
                        max_axis=self.max_axis)

    def sub_spec(self) -> SubSpec:
        return SubSpec(min_small=self.sub_min, big_frac=self.sub_big, density=self.sub_density)


class GridTracer:
    """The ugrid trace kernels over a UniformGrid (or a TwoLevelGrid: the nested walk) and the
    device copy of the triangles."""

    def __init__(self, ctx: Any, grid: UniformGrid):
        from viewer.cl import build

        self.ctx, self.grid = ctx, grid
        self.two_level = isinstance(grid, TwoLevelGrid)
        self.kernels = {}
        for count in (False, True):
            defines: dict[str, Any] = {"WG": WG, **({"COUNT_TESTS": None} if count else {}),
                                       **({"TWO_LEVEL": None} if self.two_level else {})}
            prog = build(KERNEL, defines, ctx)
            for idx, sfx in ((False, ""), (True, "_idx"), ("device", "_idxd")):
                self.kernels[(False, count, idx)] = clio.kernel(prog, "trace_closest" + sfx)
                self.kernels[(True, count, idx)] = clio.kernel(prog, "trace_any" + sfx)

    def enqueue(self, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int, any_hit: bool,
                tests: Any = None, index: Any = None, n_device: Any = None) -> None:
        """Trace rays 0..n-1, or with `index` (uint32 buffer) the n rays it lists; with `n_device`
        (a uint32 device buffer) the count listed is read there and n is only its bound."""
        if n == 0:
            return
        g = self.grid
        mode = "device" if n_device is not None else index is not None
        k = self.kernels[(bool(any_hit), tests is not None, mode)]
        extra = (index,) if index is not None else ()
        sub = (g.sub_of, g.subs, g.scells, g.sblocks, g.scb, g.bblocks) if self.two_level else ()
        k(self.ctx.queue, (-(-n // WG) * WG,), (WG,), g.header, g.cells, g.blocks, g.cell_blocks, *sub, ray_o, ray_d,
          out_t, out_id, n_device if n_device is not None else np.int32(n), tests if tests is not None else out_id,
          *extra)


class UgridBackend(GeometryBackend):
    info = BackendInfo("ugrid", "OpenCL: uniform grid (sorted triangle-cell pairs) walked by 3D-DDA, one ray per "
                       "work-item", params=UgridParams,
                       overlays=(OverlaySpec("triangle_tests", "heat", "triangle_tests", "triangles tested per ray"),),
                       counters=("rays", "grid_pairs", "grid_nonempty", "grid_build_ms", "grid2_subgrids",
                                 "grid2_subpairs", "tests_per_ray"), device="cl")

    def __init__(self, bc: BackendContext, params: UgridParams | None = None):
        from viewer.cl import PassStages

        self._start(bc, params)
        if self.params.levels == 2:
            self.grid.release()
            self.grid = TwoLevelGrid(self.ctx, sub=self.params.sub_spec())
        self.tracer = GridTracer(self.ctx, self.grid)
        self.stages = PassStages(self.ctx, extras=1)  # + triangle tests per ray
        self._grid_stats_due = True
        self._rebuild()

    # -- geometry (viewer.backends.cl_geometry) --------------------------------------------
    def _rebuild(self) -> None:
        """Upload the triangles and build the grid (phase "ugrid:build")."""
        with self.bc.profiler.cl_phase("ugrid:build", self.ctx.queue):
            tris = self._upload_triangles("ugrid triangles")
            lo, hi = scene_box(tris)
            self.grid.build(self._tris, len(tris), lo, hi, self.params.spec())

    def _frame_started(self) -> None:
        self._grid_stats_due = True  # the grid's counters go with the frame's first pass only

    # -- tracing --------------------------------------------------------------------------
    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        rs, hs, tests = self.stages.get(rays.size)
        with self.bc.profiler.cl_phase("ugrid:upload", self.ctx.queue):
            rs.upload(rays)
        return self._trace(rs, hs, tests, pinfo, rays.size, hits)

    def trace_device(self, rays, pinfo: PassInfo, hits) -> TraceResult:
        """Trace CL ray buffers (viewer.cl.RayStage layout) into CL hit buffers (HitStage)."""
        return self._trace(rays, hits, None, pinfo, rays.size, None)

    def _trace(self, rs, hs, tests, pinfo: PassInfo, size: tuple[int, int], hits: HitBuffer | None) -> TraceResult:
        """One pass on CL buffers; `hits` (a RayBatch frame) gets the hits written back."""
        prof = self.bc.profiler
        q = self.ctx.queue
        count = bool(self.overlays_enabled) and tests is not None
        with prof.cl_phase(f"trace:{pinfo.ray_type.label}", q):
            self.tracer.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit,
                                tests if count else None)
        if hits is not None:
            with prof.cl_phase("ugrid:download", q):
                hs.download(hits)
        stats = {"rays": float(rs.n)}
        if getattr(self, "_grid_stats_due", True):
            stats.update(self.grid.stats.as_dict())
            self._grid_stats_due = False
        overlays = {}
        if count:
            overlays["triangle_tests"], total = self._overlay_texture(size, tests, rs.n)
            stats["tests_per_ray"] = total / max(rs.active_count(), 1)  # per active ray
        return TraceResult(stats=stats, overlays=overlays)

    def _overlay_texture(self, size: tuple[int, int], buf: Any, n: int):
        from viewer.cl import mapped

        with mapped(self.ctx, buf, (n,), np.int32) as a:
            tex = self.textures.write("triangle_tests", size, a)
            total = float(a.sum())
        return tex, total

    def release(self) -> None:
        self._release_own()

"""voxels: rays traced against a six-separating voxelization of the scene (approximate by design).

The scene (leaf order) is voxelized at `resolution`^3 (viewer.accel.voxelize), a voxel BVH,
KD-tree or octree is built over the voxels (viewer.accel.voxel_bvh / voxel_kd / voxel_octree)
and one OpenCL work-item per ray walks it front to back with a short stack of `stack` entries
and restart from the root (scene.py, *.cl beside this file). A hit reports the voxel's entry
distance and its representative triangle (the triangle whose plane passes nearest the voxel
centre), so every effect shades with that triangle's material and normal. Secondary rays start
`bias` voxel widths along the ray: they leave a voxel surface that the true surface lies inside;
with `leave`, they also skip the whole run of voxels they start in (costs re-traversals; on sponza
at 128^3 it cut shadow-ray false occlusion from 17.5% to 11-14% of rays at 2-5x the time).

The error shrinks with the resolution: the bench reports image error and hit disagreement
against the exact backends (BackendInfo.exact = False keeps it out of the exact agreement tests).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from viewer.accel.voxelize import Voxels, check_resolution, voxelize
from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.interface import BackendInfo, param
from viewer.backends.voxels.scene import STACK_RANGE, STRUCTURES, VoxelTracer, build_structure
from viewer.effects import RayType
from viewer.errors import RtwalkError
from viewer.rays import HitBuffer, PassInfo, RayBatch


@dataclass
class VoxelsParams:
    structure: str = param("bvh", "bvh | kd | octree")
    resolution: int = param(256, "voxels per side (power of two)")
    stack: int = param(8, "short-stack entries (the paper: 4-8); restart from the root when it runs empty")
    bias: float = param(1.5, "secondary rays start this many voxel widths along the ray")
    leave: bool = param(False, "secondary rays skip the run of voxels they start in (the surface they leave)")
    gap: float = param(0.5, "leave: voxels starting within this many voxel widths of the previous exit are one run")

    def validate(self, source: str = "voxels") -> None:
        if self.structure not in STRUCTURES:
            raise RtwalkError(f"{source}: structure must be one of {', '.join(STRUCTURES)} (got '{self.structure}')")
        try:
            check_resolution(self.resolution)
        except RtwalkError as e:
            raise RtwalkError(f"{source}: {e}") from None
        if not STACK_RANGE[0] <= self.stack <= STACK_RANGE[1]:
            raise RtwalkError(f"{source}: stack must be in {STACK_RANGE[0]}..{STACK_RANGE[1]} (got {self.stack})")
        if not (self.bias >= 0 and np.isfinite(self.bias)):
            raise RtwalkError(f"{source}: bias must be >= 0 (got {self.bias})")
        if not (self.gap >= 0 and np.isfinite(self.gap)):
            raise RtwalkError(f"{source}: gap must be >= 0 (got {self.gap})")


_cache: dict = {}  # (triangle buffer identity, resolution) -> Voxels; one scene at a time


def voxels_for(triangles: np.ndarray, resolution: int, quiet: bool = False) -> Voxels:
    """The scene's voxelization, cached for the last scene (bench runs create backends repeatedly)."""
    sample = np.ascontiguousarray(triangles[:: max(1, len(triangles) // 4096)])  # a freed array's address may recur
    key = (triangles.__array_interface__["data"][0], triangles.shape, hash(sample.tobytes()), resolution)
    if key not in _cache:
        from tqdm import tqdm

        bar = tqdm(total=100, desc=f"voxelize {resolution}^3", unit="%", disable=quiet or resolution < 512,
                   file=sys.stderr, leave=False)
        vox = voxelize(triangles, resolution, progress=lambda f, _: bar.update(int(100 * f) - bar.n))
        bar.close()
        if len(_cache) >= 4:
            _cache.pop(next(iter(_cache)))
        _cache[key] = vox
    return _cache[key]


class VoxelsBackend:
    info = BackendInfo("voxels", "OpenCL: rays walk a voxel BVH / KD-tree / octree of the voxelized scene "
                       "(short stack, restart); approximate", params=VoxelsParams,
                       counters=("rays", "voxels"), device="cl", exact=False)

    def __init__(self, bc: BackendContext, params: VoxelsParams | None = None):
        from viewer.cl import PassStages, cl_context
        from viewer.cl.transfer import PixelBuffers

        self.bc = bc
        self.params = params or VoxelsParams()
        self.overlays_enabled = False
        self.ctx = cl_context()
        p = self.params
        self._voxelize(bc)
        st, vs = self.structure.stats, self.voxels.stats
        print(f"voxels: {vs['count']:,} voxels at {p.resolution}^3 in {vs['seconds']:.2f} s; {p.structure}: "
              f"{st['interior_nodes']:,} nodes x {st['node_bytes']} B + {st['leaves']:,} leaves x {st['leaf_bytes']} B"
              f" = {st['memory_bytes'] / 2**20:.1f} MiB, mean leaf depth {st['mean_leaf_depth']:.2f}",
              file=sys.stderr, flush=True)
        self.stages = PassStages(self.ctx, extras=1, extra_access="rw")  # + hit voxel per ray
        self.vox_buffers = PixelBuffers(self.ctx, 1, "rw")  # the hit voxel per ray of device-resident frames

    def _voxelize(self, bc: BackendContext) -> None:
        """Voxelize the scene's triangles and build the chosen structure and its tracer."""
        p = self.params
        self.voxels = voxels_for(bc.scene.triangles, p.resolution)
        self.structure = build_structure(p.structure, self.voxels)
        g = self.voxels.grid
        self.tracer = VoxelTracer(self.structure, g.origin, g.scale, p.stack, ctx=self.ctx)

    def scene_changed(self, bc: BackendContext) -> None:
        """Re-voxelize the moved triangles and rebuild the structure (phase "build:voxels")."""
        self.bc = bc
        t0 = time.perf_counter()
        self.tracer.release()
        self._voxelize(bc)
        ms = (time.perf_counter() - t0) * 1e3
        bc.profiler.record("build:voxels", ms, ms)

    def begin_frame(self, frame_index: int) -> None:
        pass

    def reset(self) -> None:
        pass

    def tile_level(self, size: tuple[int, int]) -> int:
        return -1

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        rs, hs, vox = self.stages.get(rays.size)
        with self.bc.profiler.cl_phase("voxels:upload", self.ctx.queue):
            rs.upload(rays)
        return self._trace(rs, hs, vox, pinfo, hits)

    def trace_device(self, rays, pinfo: PassInfo, hits) -> TraceResult:
        """Trace CL ray buffers (viewer.cl.RayStage layout) into CL hit buffers (HitStage)."""
        vox = self.vox_buffers.get(rays.size)[0]
        return self._trace(rays, hits, vox, pinfo, None)

    def _trace(self, rs, hs, vox, pinfo: PassInfo, hits: HitBuffer | None) -> TraceResult:
        """One pass on CL buffers; `hits` (a RayBatch frame) gets the hits written back."""
        prof = self.bc.profiler
        q = self.ctx.queue
        secondary = pinfo.ray_type != RayType.PRIMARY
        bias = self.params.bias if secondary else 0.0
        with prof.cl_phase(f"trace:{pinfo.ray_type.label}", q):
            self.tracer.enqueue(rs.origin, rs.dir, hs.t, hs.tri, vox, rs.n, pinfo.any_hit, bias,
                                leave=secondary and self.params.leave, gap=self.params.gap)
        if hits is not None:
            with prof.cl_phase("voxels:download", q):
                hs.download(hits)
        return TraceResult(stats={"rays": rs.n, "voxels": self.voxels.count})

    def release(self) -> None:
        self.stages.release()
        self.vox_buffers.release()
        self.tracer.release()

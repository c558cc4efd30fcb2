"""The GLSL baseline: a full-screen fragment shader traverses the whole BVH for every ray.

The traversal itself (resumed in further draws when llvmpipe's loop limit would cut it short) is
viewer.backends.gl_traversal.ResumableTraversal, shared with chcrt.
"""

from __future__ import annotations

from viewer.backends.base import BackendContext, StatelessBackend, TraceResult, WorkCounters
from viewer.backends.gl_traversal import ResumableTraversal
from viewer.backends.interface import BackendInfo
from viewer.rays import HitBuffer, PassInfo, RayBatch


class GlslBackend(StatelessBackend):
    info = BackendInfo("glsl", "full BVH traversal from the root per ray (CHC+RT Table 2 'GLSL' baseline)",
                       counters=("draws", "resumed_rays"))

    def __init__(self, bc: BackendContext, params: None = None):
        self.bc = bc
        self.params = params
        self.work = WorkCounters(bc.ctx)
        self.traversal = ResumableTraversal(bc, self.work)

    @property
    def max_visits(self) -> int:
        return self.traversal.max_visits

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        self.traversal.bind_flags(hits.size)
        self.work.begin(hits.size)
        with self.bc.profiler.phase(f"trace:{pinfo.ray_type.label}"):
            stats = self.traversal.run(rays, pinfo, hits)
        return TraceResult(stats={**stats, **self.work.end()})

    def scene_changed(self, bc: BackendContext) -> None:
        """Nothing to build: the renderer rewrote the GpuScene's node and triangle buffers in place
        (the refitted BVH), and the traversal reads them from there."""
        self.bc = bc
        self.traversal.bc = bc

    def release(self) -> None:
        self.traversal.release()
        self.work.release()

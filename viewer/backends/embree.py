"""Reference backend: reads the rays back and traces them with Embree on the CPU.

Used as the independent reference for tests and for the error column of `rtwalk bench`.
"""

from __future__ import annotations

from viewer.backends.base import BackendContext, HitBuffer, RayBatch, TraceResult
from viewer.effects import RayType
from viewer.errors import RtwalkError


class EmbreeBackend:
    name = "embree"
    description = "CPU reference: Embree (embreex) on the same rays, hits uploaded back"

    def __init__(self, bc: BackendContext):
        from viewer.reference import EmbreeTracer

        if not EmbreeTracer.available():
            raise RtwalkError("backend 'embree' needs the embreex package (pip install embreex)")
        self.bc = bc
        self.tracer = EmbreeTracer(bc.scene.triangles)

    def begin_frame(self, frame_index: int) -> None:
        pass

    def trace(self, rays: RayBatch, ray_type: RayType, sample: int, hits: HitBuffer) -> TraceResult:
        with self.bc.profiler.phase(f"trace:{ray_type.label}"):
            r = rays.read()
            t, tri = self.tracer.trace(r.origins, r.directions, r.tmin, r.tmax, any_hit=ray_type.any_hit)
            hits.write(t, tri)
        return TraceResult(stats={"cpu_rays": int(r.active.sum())})

    def release(self) -> None:
        pass

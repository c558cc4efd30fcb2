"""Reference backend: reads the rays back and traces them with Embree on the CPU.

Used as the independent reference for tests and for the error column of `rtwalk bench`.
"""

from __future__ import annotations

import time

from viewer.backends.base import BackendContext, StatelessBackend, TraceResult
from viewer.backends.interface import BackendInfo
from viewer.errors import RtwalkError
from viewer.rays import HitBuffer, PassInfo, RayBatch


class EmbreeBackend(StatelessBackend):
    info = BackendInfo("embree", "CPU reference: Embree (embreex) on the same rays, hits uploaded back",
                       counters=("cpu_rays",), device="cpu")

    def __init__(self, bc: BackendContext, params: None = None):
        from viewer.reference import EmbreeTracer

        if not EmbreeTracer.available():
            raise RtwalkError("backend 'embree' needs the embreex package (pip install embreex)")
        self.bc = bc
        self.params = params
        self.tracer = EmbreeTracer(bc.scene.triangles)

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        with self.bc.profiler.phase(f"trace:{pinfo.ray_type.label}"):
            r = rays.read()
            t, tri = self.tracer.trace(r.origins, r.directions, r.tmin, r.tmax, any_hit=pinfo.any_hit)
            hits.write(t, tri)
        return TraceResult(stats={"cpu_rays": int(r.active.sum())})

    def scene_changed(self, bc: BackendContext) -> None:
        """A new Embree scene over the moved triangles (Embree builds its own BVH)."""
        from viewer.reference import EmbreeTracer

        self.bc = bc
        t0 = time.perf_counter()
        self.tracer = EmbreeTracer(bc.scene.triangles)
        ms = (time.perf_counter() - t0) * 1e3
        bc.profiler.record("build:embree", ms, ms)

    def release(self) -> None:
        pass

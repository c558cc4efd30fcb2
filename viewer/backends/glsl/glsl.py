"""The GLSL baseline: every ray traverses the whole BVH from the root, in a full-screen fragment
draw or a compute dispatch (`stage`).

The traversal itself (resumed in further draws when llvmpipe's loop limit would cut it short) is
viewer.backends.gl_traversal.ResumableTraversal, shared with chcrt.
"""

from __future__ import annotations

from dataclasses import dataclass

from viewer.backends.base import BackendContext, StatelessBackend, TraceResult, WorkCounters
from viewer.backends.gl_traversal import ResumableTraversal
from viewer.backends.interface import BackendInfo, param
from viewer.errors import RtwalkError
from viewer.gl.stages import STAGE_CHOICES, resolve_stage
from viewer.rays import HitBuffer, PassInfo, RayBatch


@dataclass
class GlslParams:
    stage: str = param("auto", "where the traversal runs: 'fragment' (a full-screen draw, hits through the "
                       "framebuffer), 'compute' (a dispatch of 8x8-pixel groups, hits through a buffer and one "
                       "full-screen copy; the same hits) or 'auto': fragment on a software rasterizer, else compute "
                       "where a probe finds compute shaders 2x faster (an NVIDIA H100/H200 runs fragment shaders "
                       "on a few of its processors; viewer/gl/stages.py)")

    def validate(self, source: str) -> None:
        if self.stage not in STAGE_CHOICES:
            raise RtwalkError(f"{source}: stage={self.stage!r}: choose from {', '.join(STAGE_CHOICES)}")


class GlslBackend(StatelessBackend):
    info = BackendInfo("glsl", "full BVH traversal from the root per ray (CHC+RT Table 2 'GLSL' baseline)",
                       params=GlslParams, counters=("draws", "resumed_rays"))

    def __init__(self, bc: BackendContext, params: GlslParams | None = None):
        self.bc = bc
        self.params = params or GlslParams()
        self.work = WorkCounters(bc.ctx)
        self.stage = resolve_stage(bc.ctx, self.params.stage)
        self.traversal = ResumableTraversal(bc, self.work, stage=self.stage)

    @property
    def max_visits(self) -> int:
        return self.traversal.max_visits

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        self.traversal.bind_flags(hits.size)
        self.work.begin(hits.size)
        with self.bc.profiler.phase(f"trace:{pinfo.ray_type.label}"):
            stats = self.traversal.run(rays, pinfo, hits)
        stats["compute_stage"] = int(self.stage == "compute")  # (stage=auto: what it chose here)
        return TraceResult(stats={**stats, **self.work.end()})

    def scene_changed(self, bc: BackendContext) -> None:
        """Nothing to build: the renderer rewrote the GpuScene's node and triangle buffers in place
        (the refitted BVH), and the traversal reads them from there."""
        self.bc = bc
        self.traversal.bc = bc

    def release(self) -> None:
        self.traversal.release()
        self.work.release()

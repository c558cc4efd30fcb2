"""The GLSL baseline: a full-screen fragment shader traverses the whole BVH for every ray."""

from __future__ import annotations

from viewer.backends.base import BackendContext, TraceResult, WorkCounters
from viewer.backends.interface import BackendInfo
from viewer.gpu import FullscreenQuad
from viewer.rays import HitBuffer, PassInfo, RayBatch


class GlslBackend:
    info = BackendInfo("glsl", "full BVH traversal from the root per ray (CHC+RT Table 2 'GLSL' baseline)",
                       counters=("draws",))

    def __init__(self, bc: BackendContext, params: None = None):
        self.bc = bc
        self.params = params
        self.overlays_enabled = False
        self.work = WorkCounters(bc.ctx)
        self.program = bc.programs.get("fullscreen.vert", "trace_glsl.frag",
                                       {"STACK_SIZE": bc.gpu_scene.stack_size, **self.work.defines})
        self.program["rayOrigin"] = 0
        self.program["rayDir"] = 1
        self.quad = FullscreenQuad(bc.ctx)

    def begin_frame(self, frame_index: int) -> None:
        pass

    def reset(self) -> None:
        pass

    def tile_level(self, size: tuple[int, int]) -> int:
        return -1

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        ctx = self.bc.ctx
        self.bc.gpu_scene.bind()
        rays.origin.use(0)
        rays.direction.use(1)
        self.program["anyHit"] = int(pinfo.any_hit)
        hits.fbo.use()
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        self.work.begin()
        with self.bc.profiler.phase(f"trace:{pinfo.ray_type.label}"):
            self.quad.render(self.program)
        return TraceResult(stats={"draws": 1, **self.work.end()})

    def release(self) -> None:
        self.work.release()

"""Ray generation: one ray per pixel per pass into a RayBatch, counting active rays on the GPU."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.effects import RayType, halton2
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_COUNTERS
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.passes.gbuffer import GBufferPass
from viewer.rays import RayBatch


class RayGenPass:
    MAX_COUNTERS = 8

    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 defines: dict[str, object] | None = None):
        """`defines`: the scene's fetch path (GpuScene.trace_defines)."""
        self.ctx = ctx
        self.program = programs.get("fullscreen.vert", "raygen.frag", defines)
        self.program["gId"] = 0
        self.quad = quad
        self.counters = ctx.buffer(reserve=4 * self.MAX_COUNTERS)
        self._zero = bytes(4 * self.MAX_COUNTERS)

    def generate(self, rays: RayBatch, gbuffer: GBufferPass, ray_type: RayType, sample: int,
                 light_index: int, ray_length: float, perturb_rad: float) -> None:
        p = self.program
        p["rayType"] = int(ray_type)
        p["lightIndex"] = int(light_index)
        p["sampleUV"] = halton2(sample)
        p["perturbAngle"] = float(perturb_rad)
        p["rayLength"] = float(ray_length)
        p["stream"] = int(ray_type) * 7919 + sample * 104729 + light_index * 15485863
        gbuffer.tri_id.use(0)
        self.counters.bind_to_storage_buffer(BIND_COUNTERS)
        rays.fbo.use()
        self.ctx.disable(self.ctx.BLEND | self.ctx.DEPTH_TEST)
        self.quad.render(p)

    def reset_count(self) -> None:
        glio.write(self.counters, self._zero)

    def read_counts(self) -> np.ndarray:
        return np.frombuffer(glio.read(self.counters), np.uint32).astype(np.int64)

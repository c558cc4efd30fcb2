"""Ray generation: one ray per pixel per pass into a RayBatch, counting active rays on the GPU."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.effects import RayType, halton2
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_COUNTERS
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.uniforms import apply
from viewer.rays import RayBatch


class RayGenPass:
    MAX_COUNTERS = 8

    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 defines: dict[str, object] | None = None):
        """`defines`: the scene's fetch path (GpuScene.trace_defines)."""
        self.ctx = ctx
        self.program_cache = programs
        self.defines = dict(defines or {})
        self._by_type: dict[RayType, moderngl.Program] = {}  # made on first use, one per ray type
        self.frame_uniforms: dict = {}  # camera and lights of the frame (set_frame_uniforms)
        self.quad = quad
        self.counters = ctx.buffer(reserve=4 * self.MAX_COUNTERS)
        self._zero = bytes(4 * self.MAX_COUNTERS)

    def program(self, ray_type: RayType) -> moderngl.Program:
        """The ray generation of `ray_type` (raygen.frag with RAY_TYPE: one program per type)."""
        prog = self._by_type.get(ray_type)
        if prog is None:
            prog = self.program_cache.get("fullscreen.vert", "raygen.frag", {**self.defines, "RAY_TYPE": int(ray_type)})
            prog["gId"] = 0
            self._by_type[ray_type] = prog
        return prog

    def set_frame_uniforms(self, values: dict) -> None:
        """The frame's camera and light uniforms, set on each program as it generates rays."""
        self.frame_uniforms = values

    def generate(self, rays: RayBatch, gbuffer: GBufferPass, ray_type: RayType, sample: int,
                 light_index: int, ray_length: float, perturb_rad: float) -> None:
        p = self.program(ray_type)
        apply(p, self.frame_uniforms)
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

"""Adds one traced pass to its effect's accumulator (float RGBA, additive blending)."""

from __future__ import annotations

import moderngl

from viewer.effects import RayType
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.textures import float_texture
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.targets import SizedTargets
from viewer.passes.uniforms import apply
from viewer.rays import HitBuffer, RayBatch

ACCUMULATED = (RayType.SHADOW, RayType.SOFT, RayType.AO, RayType.DIFFUSE, RayType.REFLECT)


class AccumulatePass(SizedTargets):
    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int], defines: dict[str, object] | None = None):
        """`defines`: the scene's fetch path (GpuScene.trace_defines)."""
        self.ctx = ctx
        self.quad = quad
        self.program_cache = programs
        self.defines = dict(defines or {})
        self._by_type: dict[RayType, moderngl.Program] = {}  # made on first use, one per effect
        self.frame_uniforms: dict = {}  # camera and lights of the frame (set_frame_uniforms)
        self.resize(size)

    def program(self, ray_type: RayType) -> moderngl.Program:
        """The accumulation of `ray_type`'s effect (accumulate.frag with ACC_EFFECT: one program per
        effect)."""
        prog = self._by_type.get(ray_type)
        if prog is None:
            defines = {**self.defines, "ACC_EFFECT": int(ray_type)}
            prog = self.program_cache.get("fullscreen.vert", "accumulate.frag", defines)
            for i, name in enumerate(["gPos", "gNormal", "rayOrigin", "rayDir", "hitT", "hitId"]):
                prog[name] = i
            self._by_type[ray_type] = prog
        return prog

    def set_frame_uniforms(self, values: dict) -> None:
        """The frame's camera and light uniforms, set on each program as it accumulates."""
        self.frame_uniforms = values

    def create_targets(self, size: tuple[int, int]) -> None:
        self.textures = {r: float_texture(self.ctx, size, 4) for r in ACCUMULATED}
        self.fbos = {r: self.ctx.framebuffer(color_attachments=[t]) for r, t in self.textures.items()}

    def clear(self) -> None:
        for fbo in self.fbos.values():
            fbo.clear(0.0, 0.0, 0.0, 0.0)

    def add(self, ray_type: RayType, rays: RayBatch, hits: HitBuffer, gbuffer: GBufferPass,
            light_index: int, weight: float) -> None:
        p = self.program(ray_type)
        apply(p, self.frame_uniforms)
        p["lightIndex"] = int(light_index)
        p["weight"] = float(weight)
        for i, tex in enumerate([gbuffer.position, gbuffer.normal, rays.origin, rays.direction, hits.t, hits.id]):
            tex.use(i)
        self.fbos[ray_type].use()
        ctx = self.ctx
        ctx.enable(ctx.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE
        ctx.blend_equation = moderngl.FUNC_ADD
        self.quad.render(p)
        ctx.disable(ctx.BLEND)

    def release_targets(self) -> None:
        for f in self.fbos.values():
            f.release()
        for t in self.textures.values():
            t.release()

    def release(self) -> None:
        self.release_targets()

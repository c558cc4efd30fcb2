"""Final composition (or one pass shown alone) into an RGBA8 image."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.effects import EffectSettings, RayType
from viewer.gl import io as glio
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.passes.accumulate import AccumulatePass
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.targets import SizedTargets

# Index = viewMode uniform in shade.frag.
SHADE_MODES = ["final", "albedo", "normal", "depth", "shadows", "soft", "ao", "diffuse", "reflections",
               "triangle_id"]


class ShadePass(SizedTargets):
    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int]):
        self.ctx = ctx
        self.quad = quad
        self.program = programs.get("fullscreen.vert", "shade.frag")
        names = ["gPos", "gNormal", "gAlbedo", "gId", "accShadow", "accSoft", "accAO", "accDiffuse", "accReflect"]
        for i, name in enumerate(names):
            self.program[name] = i
        self.resize(size)

    def create_targets(self, size: tuple[int, int]) -> None:
        self.color = self.ctx.texture(size, 4, dtype="f1")
        self.fbo = self.ctx.framebuffer(color_attachments=[self.color])

    def render(self, gbuffer: GBufferPass, acc: AccumulatePass, settings: EffectSettings, view: str,
               n_shadow_lights: int, depth_scale: float, acc_scale: tuple[float, ...] = (1.0,) * 5) -> None:
        """`acc_scale`: factor per accumulator (shadow, soft, ao, diffuse, reflect): requested over
        accumulated sample passes while progressive refinement is under way, else 1."""
        p = self.program
        for i, tex in enumerate([gbuffer.position, gbuffer.normal, gbuffer.albedo, gbuffer.tri_id]):
            tex.use(i)
        for i, r in enumerate([RayType.SHADOW, RayType.SOFT, RayType.AO, RayType.DIFFUSE, RayType.REFLECT]):
            acc.textures[r].use(4 + i)
        p["shadowOn"] = int(settings.shadows and n_shadow_lights > 0)
        p["softOn"] = int(settings.soft)
        p["aoOn"] = int(settings.ao)
        p["diffuseOn"] = int(settings.diffuse)
        p["reflectOn"] = int(settings.reflections)
        p["numShadowLights"] = int(n_shadow_lights)
        p["exposure"] = float(settings.exposure)
        p["viewMode"] = SHADE_MODES.index(view)
        p["depthScale"] = float(depth_scale)
        scale = p.get("accScale", None)
        if scale is not None:
            scale.value = tuple(float(v) for v in acc_scale)
        self.fbo.use()
        self.ctx.disable(self.ctx.BLEND | self.ctx.DEPTH_TEST)
        self.quad.render(p)

    def read_rgb(self) -> np.ndarray:
        """uint8 (H, W, 3), top row first (ready for PNG)."""
        data = np.frombuffer(glio.read(self.color), np.uint8).reshape(self.size[1], self.size[0], 4)
        return np.ascontiguousarray(data[::-1, :, :3])

    def release_targets(self) -> None:
        self.fbo.release()
        self.color.release()

    def release(self) -> None:
        self.release_targets()

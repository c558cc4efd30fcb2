"""Device denoiser for moving frames: an edge-aware a-trous wavelet filter (shaders/atrous.frag).

Runs on the shaded image already on the device, guided by the G-buffer (albedo demodulation,
normals, distances), in ITERATIONS + 1 full-screen draws per frame (prepare, then one 3x3 draw per
wavelet step with holes 1, 2, 4, ... pixels apart: two fetches per tap); no read-back. The result is a separate RGBA8
texture (`color`): the renderer's own image (Renderer.read_image, what agreement and image tests
compare) is never changed.
"""

from __future__ import annotations

import moderngl

from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.textures import float_texture
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.targets import SizedTargets

ITERATIONS = 4  # wavelet steps: a 3x3 kernel with holes 1, 2, 4, 8 covers 31x31 pixels
SIGMA_L = 4.0  # luminance edge-stop in local standard deviations (SVGF: 4)
NORMAL_SQUARINGS = 6  # normal edge-stop cos^(2^6) = cos^64 by squaring (Dammertz, SVGF: cos^128)
SIGMA_Z = 2.0  # distance edge-stop, in local distance gradients per pixel of offset (SVGF: 1)


class AtrousPass(SizedTargets):
    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int], iterations: int = ITERATIONS):
        self.ctx = ctx
        self.quad = quad
        self.iterations = max(int(iterations), 1)
        self.program = programs.get("fullscreen.vert", "atrous.frag", {"NORMAL_SQUARINGS": NORMAL_SQUARINGS})
        for i, name in enumerate(["src", "display", "guide", "gPos", "gNormal", "gAlbedo", "gId"]):
            self.program[name] = i
        self.resize(size)

    def _half(self, size: tuple[int, int]) -> moderngl.Texture:
        """Demodulated radiance and variance: half floats (10-bit mantissa) are plenty for a filter
        whose output is 8-bit, and halve the bytes every tap reads."""
        tex = self.ctx.texture(size, 4, dtype="f2")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    def create_targets(self, size: tuple[int, int]) -> None:
        self.ping = [self._half(size) for _ in range(2)]
        self.ping_fbos = [self.ctx.framebuffer(color_attachments=[t]) for t in self.ping]
        self.guide = float_texture(self.ctx, size, 4)  # octahedral normal, distance, its gradient
        self.prepare_fbo = self.ctx.framebuffer(color_attachments=[self.ping[0], self.guide])
        self.color = self.ctx.texture(size, 4, dtype="f1")
        self.fbo = self.ctx.framebuffer(color_attachments=[self.color])

    @property
    def draws(self) -> int:
        return self.iterations + 1

    def render(self, display: moderngl.Texture, gbuffer: GBufferPass) -> moderngl.Texture:
        """Filter `display` (the shade pass's image) into `self.color`, which is returned."""
        p = self.program
        p["sigmaL"] = SIGMA_L
        p["sigmaZ"] = SIGMA_Z
        display.use(1)
        self.guide.use(2)
        for i, tex in enumerate([gbuffer.position, gbuffer.normal, gbuffer.albedo, gbuffer.tri_id]):
            tex.use(3 + i)
        ctx = self.ctx
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        display.use(0)
        p["mode"] = 0
        p["stepPx"] = 1
        self.prepare_fbo.use()
        self.quad.render(p)
        for k in range(self.iterations):
            last = k == self.iterations - 1
            self.ping[k % 2].use(0)
            p["mode"] = 2 if last else 1
            p["stepPx"] = 1 << k
            (self.fbo if last else self.ping_fbos[(k + 1) % 2]).use()
            self.quad.render(p)
        return self.color  # the draws are counted by FullscreenQuad (viewer.gl.io)

    def release_targets(self) -> None:
        for obj in (self.prepare_fbo, *self.ping_fbos, *self.ping, self.guide, self.fbo, self.color):
            obj.release()

    def release(self) -> None:
        self.release_targets()

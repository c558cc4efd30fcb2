"""Device denoiser for moving frames: an edge-aware a-trous wavelet filter (shaders/atrous.frag).

Runs on the shaded image already on the device, guided by the G-buffer (albedo demodulation,
normals, positions), in ITERATIONS + 1 full-screen draws per frame (prepare, then one draw per
wavelet step with holes 1, 2, 4, ... pixels apart); no read-back. The result is a separate RGBA8
texture (`color`): the renderer's own image (Renderer.read_image, what agreement and image tests
compare) is never changed.
"""

from __future__ import annotations

import math

import moderngl

from viewer import iostats
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.textures import float_texture
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.targets import SizedTargets

ITERATIONS = 4  # wavelet steps: a 5x5 kernel with holes 1, 2, 4, 8 covers 61x61 pixels
SIGMA_L = 4.0  # luminance edge-stop in local standard deviations (SVGF: 4)
SIGMA_N = 64.0  # normal edge-stop exponent (Dammertz: 128; SVGF: 128)
SIGMA_P = 1.0  # tangent-plane distance edge-stop, in pixel footprints per pixel of offset


class AtrousPass(SizedTargets):
    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int], iterations: int = ITERATIONS):
        self.ctx = ctx
        self.quad = quad
        self.iterations = max(int(iterations), 1)
        self.program = programs.get("fullscreen.vert", "atrous.frag")
        for i, name in enumerate(["src", "display", "gPos", "gNormal", "gAlbedo", "gId"]):
            self.program[name] = i
        self.resize(size)

    def create_targets(self, size: tuple[int, int]) -> None:
        self.ping = [float_texture(self.ctx, size, 4) for _ in range(2)]
        self.ping_fbos = [self.ctx.framebuffer(color_attachments=[t]) for t in self.ping]
        self.color = self.ctx.texture(size, 4, dtype="f1")
        self.fbo = self.ctx.framebuffer(color_attachments=[self.color])

    @property
    def draws(self) -> int:
        return self.iterations + 1

    def render(self, display: moderngl.Texture, gbuffer: GBufferPass, fov_y_deg: float) -> moderngl.Texture:
        """Filter `display` (the shade pass's image) into `self.color`, which is returned."""
        p = self.program
        p["pixelAngle"] = 2.0 * math.tan(math.radians(fov_y_deg) / 2.0) / self.size[1]
        p["sigmaL"] = SIGMA_L
        p["sigmaN"] = SIGMA_N
        p["sigmaP"] = SIGMA_P
        display.use(1)
        for i, tex in enumerate([gbuffer.position, gbuffer.normal, gbuffer.albedo, gbuffer.tri_id]):
            tex.use(2 + i)
        ctx = self.ctx
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        display.use(0)
        p["mode"] = 0
        p["stepPx"] = 1
        self.ping_fbos[0].use()
        self.quad.render(p)
        for k in range(self.iterations):
            last = k == self.iterations - 1
            self.ping[k % 2].use(0)
            p["mode"] = 2 if last else 1
            p["stepPx"] = 1 << k
            (self.fbo if last else self.ping_fbos[(k + 1) % 2]).use()
            self.quad.render(p)
        iostats.gl_draw(self.draws)
        return self.color

    def release_targets(self) -> None:
        for obj in (*self.ping_fbos, *self.ping, self.fbo, self.color):
            obj.release()

    def release(self) -> None:
        self.release_targets()

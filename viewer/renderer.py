"""One frame: G-buffer -> for each effect and sample pass: ray generation -> backend trace ->
accumulate -> shade. Backend-agnostic; knows nothing about windows or files."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import moderngl
import numpy as np

from viewer.backends import create_backend
from viewer.backends.base import BackendContext, HitBuffer, RayArrays, RayBatch
from viewer.bvh import BVH
from viewer.camera import Camera
from viewer.effects import EffectSettings, RayType
from viewer.gpu import FullscreenQuad, GpuScene, ProgramCache
from viewer.passes.accumulate import AccumulatePass
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.raygen import RayGenPass
from viewer.passes.shade import ShadePass
from viewer.passes.uniforms import apply, camera_uniforms, light_uniforms
from viewer.profiler import GpuProfiler
from viewer.scene import Scene


@dataclass
class CapturedPass:
    """Rays and hits of one pass, read back for verification (row 0 = bottom, row-major)."""

    ray_type: RayType
    sample: int
    light: int
    rays: RayArrays
    t: np.ndarray  # float32 (R,), +inf on a miss
    tri: np.ndarray  # int32 (R,), -1 on a miss


@dataclass
class FrameReport:
    gpu_ms: dict[str, float]  # GPU time per phase
    cpu_ms: dict[str, float]  # CPU (submission) time per phase
    wall_ms: float  # whole frame, glFinish included
    rays: dict[str, int]  # active rays per ray type (effect name)
    trace_ms_by_ray: dict[str, float] = field(default_factory=dict)  # GPU time inside the backend
    backend_stats: dict[str, float] = field(default_factory=dict)
    captured: list[CapturedPass] = field(default_factory=list)

    @property
    def trace_ms(self) -> float:
        return sum(self.trace_ms_by_ray.values())


class Renderer:
    def __init__(self, ctx: moderngl.Context, scene: Scene, bvh: BVH, size: tuple[int, int],
                 backend: str = "glsl", settings: EffectSettings | None = None,
                 backend_options: dict[str, str] | None = None):
        """`scene` must already be in BVH leaf order (scene.reordered(bvh.tri_order)).
        `backend_options`: per backend name, its parameter text (e.g. {"chcrt": "t_q=0.4"})."""
        self.ctx = ctx
        self.scene = scene
        self.bvh = bvh
        self.settings = settings or EffectSettings()
        self.view = "final"
        self.size = size
        self.diagonal = max(scene.diagonal, 1e-30)
        self.depth_scale = self.diagonal
        self.programs = ProgramCache(ctx)
        self.profiler = GpuProfiler(ctx)
        self.quad = FullscreenQuad(ctx)
        self.gpu_scene = GpuScene.upload(ctx, scene, bvh)
        self.gbuffer = GBufferPass(ctx, self.programs, self.gpu_scene, size, self.depth_scale, self.diagonal)
        self.raygen = RayGenPass(ctx, self.programs, self.quad)
        self.accumulate = AccumulatePass(ctx, self.programs, self.quad, size)
        self.shade = ShadePass(ctx, self.programs, self.quad, size)
        self.rays = RayBatch(ctx, size)
        self.hits = HitBuffer(ctx, size)
        self.frame_index = 0
        self.backend_name = ""
        self.backend = None
        self._backends: dict[str, object] = {}
        self.backend_options = dict(backend_options or {})
        self.set_backend(backend)

    # -- configuration -------------------------------------------------------------------------
    def set_backend(self, name: str) -> None:
        """Switch backends live; each is created once and kept (its temporal state too)."""
        if name == self.backend_name:
            return
        backend = self._backends.get(name)
        if backend is None:
            bc = BackendContext(self.ctx, self.programs, self.profiler, self.gpu_scene, self.scene, self.bvh)
            backend = create_backend(name, bc, self.backend_options.get(name))
            self._backends[name] = backend
        self.backend, self.backend_name = backend, name

    def resize(self, size: tuple[int, int]) -> None:
        if size == self.size:
            return
        self.ctx.screen.use()  # never release a framebuffer that is still bound
        self.size = size
        self.gbuffer.resize(size)
        self.accumulate.resize(size)
        self.shade.resize(size)
        self.rays.release()
        self.hits.release()
        self.rays = RayBatch(self.ctx, size)
        self.hits = HitBuffer(self.ctx, size)

    @property
    def final_texture(self) -> moderngl.Texture:
        return self.shade.color

    def passes(self) -> list[tuple[RayType, int, int, float]]:
        """(ray type, sample, light index, accumulation weight) for every pass of a frame."""
        s, out = self.settings, []
        if s.primary:
            out.append((RayType.PRIMARY, 0, 0, 0.0))
        if s.shadows:
            out += [(RayType.SHADOW, 0, i, 1.0) for i in range(min(len(self.scene.point_lights), 8))]
        if s.soft:
            for li in range(min(len(self.scene.rect_lights), 4)):
                out += [(RayType.SOFT, k, li, 1.0 / s.soft_samples) for k in range(s.soft_samples)]
        if s.ao:
            out += [(RayType.AO, k, 0, 1.0 / s.ao_samples) for k in range(s.ao_samples)]
        if s.diffuse:
            out += [(RayType.DIFFUSE, k, 0, 1.0 / s.diffuse_samples) for k in range(s.diffuse_samples)]
        if s.reflections:
            out.append((RayType.REFLECT, 0, 0, 1.0))
        return out

    # -- one frame -----------------------------------------------------------------------------
    def render(self, camera: Camera, capture: bool = False) -> FrameReport:
        s = self.settings
        t0 = time.perf_counter()
        prof = self.profiler
        prof.begin_frame()
        cam_u = camera_uniforms(camera, self.size)
        light_u = light_uniforms(self.scene, s.ambient)
        for prog in (self.raygen.program, self.accumulate.program, self.shade.program):
            apply(prog, cam_u)
            apply(prog, light_u)
        with prof.phase("gbuffer"):
            self.gbuffer.render(camera)
        self.accumulate.clear()
        self.raygen.reset_count()
        self.backend.begin_frame(self.frame_index)
        lengths = {RayType.AO: s.ao_length * self.diagonal, RayType.DIFFUSE: self.diagonal}
        captured: list[CapturedPass] = []
        stats: dict[str, float] = {}
        for ray_type, sample, light, weight in self.passes():
            with prof.phase("raygen"):
                self.raygen.generate(self.rays, self.gbuffer, ray_type, sample, light,
                                     lengths.get(ray_type, 0.0), np.radians(s.perturb_deg))
            prof.label = ray_type.label
            result = self.backend.trace(self.rays, ray_type, sample, self.hits)
            prof.label = None
            for k, v in result.stats.items():
                stats[k] = stats.get(k, 0) + v
            if capture:
                t, tri = self.hits.read()
                captured.append(CapturedPass(ray_type, sample, light, self.rays.read(), t, tri))
            if ray_type != RayType.PRIMARY:
                with prof.phase("accumulate"):
                    self.accumulate.add(ray_type, self.rays, self.hits, self.gbuffer, light, weight)
        with prof.phase("shade"):
            self.shade.render(self.gbuffer, self.accumulate, s, self.view,
                              min(len(self.scene.point_lights), 8), self.depth_scale)
        gpu_ms = prof.end_frame()
        counts = self.raygen.read_counts()
        self.ctx.finish()
        wall = (time.perf_counter() - t0) * 1e3
        self.frame_index += 1
        rays = {RayType(i).label: int(counts[i]) for i in range(6) if counts[i] > 0}
        return FrameReport(gpu_ms, prof.cpu_ms(), wall, rays, dict(prof.by_label), stats, captured)

    def read_image(self) -> np.ndarray:
        return self.shade.read_rgb()

    def read_gbuffer_ids(self) -> np.ndarray:
        """int32 (H*W,) raster triangle id per pixel (row 0 = bottom), -1 = background."""
        from viewer.gpu import read_texture

        ids = read_texture(self.gbuffer.tri_id).reshape(-1)
        return np.where(ids < 0, -1, ids).astype(np.int32)

    def stats(self) -> dict:
        st = self.bvh.stats.to_dict()
        st["gpu_memory_bytes"] = self.gpu_scene.memory_bytes
        return st

    def release(self) -> None:
        for backend in self._backends.values():
            backend.release()
        for obj in (self.gbuffer, self.accumulate, self.shade, self.rays, self.hits, self.gpu_scene):
            obj.release()

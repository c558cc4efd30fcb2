"""One frame: G-buffer -> for each effect and sample pass: ray generation -> backend trace ->
accumulate -> shade. Backend-agnostic; knows nothing about windows or files.

Backend overlays (TraceResult.overlays, declared as OverlaySpecs in the backend's `info`) are
overwritten by every trace() call, so one pass is chosen (`overlay_pass`, default the frame's
first) and its overlays are copied on the GPU right after it is traced (passes/overlay.py); the
overlay views draw from that copy. Nothing is copied unless an overlay view is shown or
`capture_overlays` is set. Which views exist, and how they are drawn, comes from the backend's
`info` only: the renderer never names a backend.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import moderngl
import numpy as np

from viewer import iostats
from viewer.accel.bvh import BVH, refit_bvh
from viewer.backends import backend_names, create_backend, registered_infos
from viewer.backends.base import BackendContext
from viewer.backends.interface import OverlaySpec
from viewer.camera import Camera
from viewer.cl.frame import frame_path
from viewer.effects import EffectSettings, RayType
from viewer.errors import RtwalkError
from viewer.gl import io as glio
from viewer.gl.limits import allocation_guard, check_target_size
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.scene import GpuScene
from viewer.iostats import IoCounts
from viewer.passes.accumulate import ACCUMULATED, AccumulatePass
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.overlay import (
    CAPTURE_COUNTS,
    CAPTURE_FLAGS,
    CAPTURE_VALUE,
    FLAG_HIT,
    FLAG_RAY,
    OverlayPass,
    nice_ceil,
    overlay_spec,
    tile_counts,
    view_unavailable,
)
from viewer.passes.raygen import RayGenPass
from viewer.passes.shade import SHADE_MODES, ShadePass
from viewer.passes.uniforms import apply, camera_uniforms, light_uniforms
from viewer.profiler import GpuProfiler
from viewer.rays import HitBuffer, PassInfo, RayArrays, RayBatch
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
    overlay_source: tuple[RayType, int] | None = None  # the pass whose overlays were copied
    io: IoCounts = field(default_factory=IoCounts)  # bytes, syncs, launches, draws, queries (viewer.iostats)
    phase_io: dict[str, dict[str, int]] = field(default_factory=dict)  # per phase: cl_launches, host_syncs

    @property
    def trace_ms(self) -> float:
        return sum(self.trace_ms_by_ray.values())


class Renderer:
    def __init__(self, ctx: moderngl.Context, scene: Scene, bvh: BVH, size: tuple[int, int],
                 backend: str | None = None, settings: EffectSettings | None = None,
                 backend_options: dict[str, str] | None = None):
        """`scene` must already be in BVH leaf order (scene.reordered(bvh.tri_order)).
        `backend`: a registered name (None: the registry's first). `backend_options`: per backend
        name, its parameter text (--backend-params)."""
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
        check_target_size(ctx, size)  # one line, before anything frame-sized is allocated
        self.gpu_scene = GpuScene.upload(ctx, scene, bvh)
        with allocation_guard(size):
            self.gbuffer = GBufferPass(ctx, self.programs, self.gpu_scene, size, self.depth_scale, self.diagonal)
            self.gbuffer.set_bvh(bvh)
            fetch = self.gpu_scene.trace_defines()
            self.raygen = RayGenPass(ctx, self.programs, self.quad, fetch)
            self.accumulate = AccumulatePass(ctx, self.programs, self.quad, size, fetch)
            self.shade = ShadePass(ctx, self.programs, self.quad, size)
            self.rays = RayBatch(ctx, size)
            self.hits = HitBuffer(ctx, size)
        self.frame_index = 0
        self.samples_done: dict[RayType, set[int]] = {}  # sample indices accumulated since the last clear
        # overlays: the pass to copy them from ((ray type, sample), first occurrence in the frame;
        # None or a pass not in the frame: the frame's first pass), forced capture for tools that
        # save them, heat-map scale (fixed maximum, 0 = from the frame; log or linear), and strict
        # mode: an overlay view the backend cannot feed raises RtwalkError (the window sets it off
        # and shows `overlay_missing` instead, over the final image)
        self.overlay_pass: tuple[RayType, int] | None = None
        self.capture_overlays = False
        self.overlay_scale = 0
        self.overlay_log = True
        self.strict_overlays = True
        self.overlay_source: tuple[RayType, int] | None = None
        self.overlay_missing = ""
        self.backend_overlays: tuple[str, ...] | None = None  # textures the backend returned last (None: not traced)
        self._overlay: OverlayPass | None = None
        self._atrous = None  # viewer.passes.denoise.AtrousPass, created on first use
        # the window's moving frames: run the device filter inside render() (phase "denoise", in the
        # frame's time, so a render scale that follows the frame time pays for it too); the result
        # is `shown_texture`, read_image() stays raw
        self.denoise = False
        self.denoised = False
        self._idle_fbo: moderngl.Framebuffer | None = None  # bound during a headless resize
        self.backend_name = ""
        self.backend = None
        self._backends: dict[str, object] = {}
        self.backend_options = dict(backend_options or {})
        self.scene_time = float(scene.scene_time)  # wanted scene time; applied at the next render()
        self._stale: set[str] = set()  # created backends not yet told about the latest geometry
        self._device = None  # viewer.cl.frame.DeviceFrame, made on the first CL-resident frame
        self.gbuffer_drawn = 0  # G-buffer draws so far: a keep call reuses device copies of the same draw
        self.frame_path = "batch"  # the last frame's: "device" (CL-resident) or "batch" (RayBatch)
        # where the G-buffer comes from: "raster" (exact conservative raster, cost ~ triangles in
        # view), "preview" (plain raster, not exact at edges; moving frames only) or "trace" (the
        # backend's primary rays, cost ~ pixels); the progressive mode picks the cheaper of
        # preview and trace for its moving frames (viewer.progressive)
        self.gbuffer_source = "raster"
        self.set_backend(backend or backend_names()[0])

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
        elif name in self._stale:  # kept while another backend was active: catch up with the geometry
            backend.scene_changed(BackendContext(self.ctx, self.programs, self.profiler, self.gpu_scene,
                                                 self.scene, self.bvh))
        self._stale.discard(name)
        self.backend, self.backend_name = backend, name
        self.backend_overlays = None

    # -- animated scenes -----------------------------------------------------------------------
    def set_scene_time(self, t: float) -> None:
        """Show the scene at time `t` (seconds) from the next render() on; static scenes ignore it."""
        self.scene_time = float(t)

    def update_geometry(self) -> bool:
        """Bring every geometry-dependent structure to `scene_time` (called by render() inside the
        frame, so the builds are phases of that frame's report). False: nothing to do (a static
        scene, or the time shown already): nothing is rebuilt.

        The binary BVH is REFIT, not rebuilt: the animated scenes keep triangle count, order and
        materials, and a refit keeps the tree's topology and leaf order, so triangle ids (leaf
        slots) mean the same triangle in every frame and per-node temporal state (a backend's fronts)
        stays valid; it costs a few vectorised reductions instead of a SAH build. Phases:
        "build:animate" (evaluating the animation), "build:bvh" (refit), "build:upload" (GpuScene
        nodes, triangles and G-buffer vertices rewritten in place), then the active backend's own
        "build:*" phases (scene_changed); inactive backends catch up when selected."""
        scene = self.scene
        if not scene.animated or self.scene_time == scene.scene_time:
            return False
        prof = self.profiler
        t0 = time.perf_counter()
        tris = scene.triangles_at(self.scene_time)
        t1 = time.perf_counter()
        bvh = refit_bvh(self.bvh, tris)
        t2 = time.perf_counter()
        prof.record("build:animate", (t1 - t0) * 1e3, (t1 - t0) * 1e3)
        prof.record("build:bvh", (t2 - t1) * 1e3, (t2 - t1) * 1e3)
        scene = replace(scene, triangles=tris, scene_time=self.scene_time,
                        geometry_version=scene.geometry_version + 1)
        with prof.phase("build:upload"):
            self.gpu_scene.update(scene, bvh)
        self.scene, self.bvh = scene, bvh
        self.gbuffer.set_bvh(bvh)  # refit boxes cull the raster
        self._stale = set(self._backends)
        self._stale.discard(self.backend_name)
        self.backend.scene_changed(BackendContext(self.ctx, self.programs, self.profiler, self.gpu_scene,
                                                  scene, bvh))
        return True

    def resize(self, size: tuple[int, int]) -> None:
        if size == self.size:
            return
        check_target_size(self.ctx, size, "render size")
        # never release a framebuffer that is still bound: bind one that survives the resize
        if self.ctx.screen is not None:
            self.ctx.screen.use()
        else:  # headless (EGL): no default framebuffer
            if self._idle_fbo is None:
                self._idle_fbo = self.ctx.simple_framebuffer((1, 1))
            self._idle_fbo.use()
        self.size = size
        with allocation_guard(size, "render size"):
            self.gbuffer.resize(size)
            self.accumulate.resize(size)
            self.shade.resize(size)
            self.rays.release()
            self.hits.release()
            self.rays = RayBatch(self.ctx, size)
            self.hits = HitBuffer(self.ctx, size)
            if self._overlay is not None:
                self._overlay.resize(size)
            if self._atrous is not None:
                self._atrous.resize(size)

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
        if s.soft:  # sample-major: every light's sample k before sample k + 1, so a frame added up in
            # steps of samples (viewer.progressive) sums the shared accumulator in this same order
            lights = range(min(len(self.scene.rect_lights), 4))
            out += [(RayType.SOFT, k, li, 1.0 / s.soft_samples) for k in range(s.soft_samples) for li in lights]
        if s.ao:
            out += [(RayType.AO, k, 0, 1.0 / s.ao_samples) for k in range(s.ao_samples)]
        if s.diffuse:
            out += [(RayType.DIFFUSE, k, 0, 1.0 / s.diffuse_samples) for k in range(s.diffuse_samples)]
        if s.reflections:
            out.append((RayType.REFLECT, 0, 0, 1.0))
        return out

    # -- overlays ------------------------------------------------------------------------------
    @property
    def is_overlay_view(self) -> bool:
        """The view is not one of the shade pass's: a backend overlay view (or an unknown name)."""
        return self.view not in SHADE_MODES

    @property
    def view_spec(self) -> OverlaySpec | None:
        """The active backend's OverlaySpec of the current view (None: a shade view, or a view
        this backend does not produce)."""
        return overlay_spec(self.backend.info, self.view) if self.is_overlay_view else None

    @property
    def overlays_wanted(self) -> bool:
        """Copy overlays this frame: a tool saves them, or one of the backend's views is shown."""
        return self.capture_overlays or self.view_spec is not None

    @property
    def overlay(self) -> OverlayPass:
        """Created on first use: a renderer that never shows overlays never compiles its shaders."""
        if self._overlay is None:
            self._overlay = OverlayPass(self.ctx, self.programs, self.quad, self.size)
        return self._overlay

    def overlay_source_for(self, passes: list[tuple[RayType, int, int, float]]) -> tuple[RayType, int] | None:
        """The (ray type, sample) whose overlays are copied: `overlay_pass` if the frame has it,
        else the frame's first pass (None: no pass traces rays)."""
        keys = [(rt, k) for rt, k, _, _ in passes]
        if self.overlay_pass is not None and tuple(self.overlay_pass) in keys:
            rt, k = self.overlay_pass
            return RayType(rt), int(k)
        return keys[0] if keys else None

    def overlay_tile_level(self) -> int:
        """Quadtree level of the backend's finest tiles (outlines), -1 for a backend without tiles."""
        return int(self.backend.tile_level(self.size))

    def _overlay_unavailable(self, msg: str) -> None:
        self.overlay_missing = msg
        if self.strict_overlays:
            raise RtwalkError(msg)

    def _capture_overlays(self, overlays: dict) -> bool:
        """Copy the backend's overlays of the pass just traced (every view with
        `capture_overlays`, else the one shown); False when the shown view (if any) cannot be
        drawn from them."""
        specs = self.backend.info.overlays
        spec = self.view_spec
        if spec is not None and spec.texture not in overlays:
            self._overlay_unavailable(f"view '{self.view}': backend '{self.backend_name}' returned no "
                                      f"'{spec.texture}' texture for this pass")
            return False
        if not self.capture_overlays:  # the window: only the view shown
            specs = (spec,) if spec is not None else ()
        present = [s for s in specs if s.texture in overlays]
        if not present:
            return False
        if any(tuple(overlays[s.texture].size) != tuple(self.size) for s in present):
            self._overlay_unavailable(f"backend '{self.backend_name}' overlays are not at the render size")
            return False
        with self.profiler.phase("overlay"):
            self.overlay.capture(tuple(present), overlays, self.rays, self.hits)
        return True

    def overlay_scale_max(self, view: str | None = None) -> int:
        """The heat map's maximum this frame (the legend's) for a "heat" view (default: the
        current one): the fixed scale, else the frame's largest value rounded up to 1-2-5 steps
        (8 bytes read back)."""
        if self.overlay_scale > 0:
            return int(self.overlay_scale)
        view = view or self.view
        if self._overlay is None or view not in self._overlay.captured:
            return 1
        return nice_ceil(max(self._overlay.read_max(view)[0], 1))

    def read_overlays(self) -> dict[str, np.ndarray]:
        """The copied overlays of this frame's overlay pass, int32 (H*W,) each, row 0 = bottom,
        keyed by the backend's texture names (OverlaySpec.texture and .counts, those it returned),
        plus `ray` and `hit` (bool) for that pass. Empty when nothing was copied."""
        ov = self._overlay
        if ov is None or not ov.captured:
            return {}
        out: dict[str, np.ndarray] = {}
        for name, spec in ov.captured.items():
            data = ov.read(name).reshape(-1, 4)
            out[spec.texture] = np.ascontiguousarray(data[:, CAPTURE_VALUE])
            if spec.counts and (data[:, CAPTURE_COUNTS] >= 0).any():
                out[spec.counts] = np.ascontiguousarray(data[:, CAPTURE_COUNTS])
            flags = data[:, CAPTURE_FLAGS]
        out["ray"] = (flags & FLAG_RAY) != 0
        out["hit"] = (flags & FLAG_HIT) != 0
        return out

    def overlay_tiles(self, view: str | None = None) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """Per finest tile of this frame's overlay pass, for an "ids" view (default: the current
        one): (rects, counts, from_counts) (see passes.overlay.tile_counts); None without a
        capture of that view or without tiles. Reads the capture back."""
        view = view or self.view
        level = self.overlay_tile_level()
        ov = self._overlay
        if ov is None or view not in ov.captured or ov.captured[view].kind != "ids" or level < 0:
            return None
        return tile_counts(ov.read(view), level)

    # -- one frame -----------------------------------------------------------------------------
    def samples_requested(self) -> dict[RayType, int]:
        """Sample passes per accumulated effect that is on (1 for shadows and reflections)."""
        s = self.settings
        return {rt: s.samples(rt) for rt in ACCUMULATED if s.enabled(rt)}

    def acc_scale(self) -> tuple[float, ...]:
        """Per accumulator (passes.accumulate.ACCUMULATED order): requested / done sample passes,
        so that an image of k of N passes (weights 1/N each) is a complete estimate; exactly 1.0
        once all are done (the full-quality frame is unchanged)."""
        req = self.samples_requested()
        return tuple(float(req[rt]) / len(self.samples_done[rt]) if self.samples_done.get(rt) and rt in req else 1.0
                     for rt in ACCUMULATED)

    def render(self, camera: Camera, capture: bool = False, samples: tuple[int, ...] | None = None,
               keep: bool = False, shade: bool = True) -> FrameReport:
        """One frame. `samples`: trace only the sample passes with these indices (None: all: the
        full-quality frame); `keep`: add them to the accumulators of the previous call (same
        camera and size: the G-buffer is not redrawn), as progressive refinement does
        (viewer.progressive); `shade=False`: fill the accumulators only, no image (the steps of a
        stepped still frame before its last, which nothing shows)."""
        s = self.settings
        t0 = time.perf_counter()
        prof = self.profiler
        passes = self.passes()
        if samples is not None:
            passes = [p for p in passes if p[1] in samples and (p[0] != RayType.PRIMARY or not keep)]
        view_overlay = self.is_overlay_view
        source = self.overlay_source_for(passes) if self.overlays_wanted else None
        self.overlay_missing = ""
        self.overlay_source = None
        if self._overlay is not None:
            self._overlay.begin_frame()
        if view_overlay:
            missing = view_unavailable(self.view, self.backend.info, registered_infos())
            if missing:
                self._overlay_unavailable(missing)
            elif source is None:
                self._overlay_unavailable(f"view '{self.view}' shows a traced pass's overlays, but no pass "
                                          "traces rays (turn an effect on)")
        iostats.begin_frame()
        prof.begin_frame()
        self.update_geometry()
        cam_u = camera_uniforms(camera, self.size)
        light_u = light_uniforms(self.scene, s.ambient)
        frame_u = {**cam_u, **light_u}
        self.raygen.set_frame_uniforms(frame_u)
        self.accumulate.set_frame_uniforms(frame_u)
        apply(self.shade.program, cam_u)
        apply(self.shade.program, light_u)
        self.backend.overlays_enabled = self.overlays_wanted  # diagnostics cost time: only when shown or saved
        self.frame_path = frame_path(self.backend, overlays=self.overlays_wanted)
        # a device frame's per-frame builds (begin_frame) are timed by queue markers too: no waits
        prof.cl_deferred = self.frame_path == "device"
        try:
            self.backend.begin_frame(self.frame_index)
        finally:
            prof.cl_deferred = False
        if not keep:
            if self.gbuffer_source == "trace":
                self._traced_gbuffer(camera)
            else:
                with prof.phase("gbuffer:preview" if self.gbuffer_source == "preview" else "gbuffer"):
                    self.gbuffer.render(camera, preview=self.gbuffer_source == "preview")
            self.gbuffer_drawn += 1
            self.accumulate.clear()
            self.samples_done = {}
        lengths = {RayType.AO: s.ao_length * self.diagonal, RayType.DIFFUSE: self.diagonal}
        captured: list[CapturedPass] = []
        stats: dict[str, float] = {}
        if self.frame_path == "device":
            counts = self._device_passes(passes, lengths, cam_u, light_u, keep, capture, captured, stats, shade)
            overlay_done = False
        else:
            counts, overlay_done = self._batch_passes(passes, lengths, source, capture, captured, stats)
        if shade:
            with prof.phase("shade"):
                if view_overlay and overlay_done and self.view in self.overlay.captured:
                    self.overlay.render_view(self.shade.fbo, self.view, self.overlay_tile_level(),
                                             int(self.overlay_scale), self.overlay_log)
                else:  # an overlay view without overlays (window): the final image under the message
                    self.shade.render(self.gbuffer, self.accumulate, s, "final" if view_overlay else self.view,
                                      min(len(self.scene.point_lights), 8), self.depth_scale, self.acc_scale())
        self.denoised = False
        if shade and self.denoise and self.view == "final" and self.noisy:  # the picture shown; shade.color raw
            with prof.phase("denoise"):
                self.device_denoiser.render(self.shade.color, self.gbuffer)
            self.denoised = True
        self.overlay_source = source if overlay_done else None
        gpu_ms = prof.end_frame()
        if prof.saturated:  # timer results charged their CPU time instead (see profiler.py)
            stats["timer_saturated"] = float(prof.saturated)
        glio.finish(self.ctx)
        if self.frame_path != "device":  # counters a GL backend kept on the device: read after the finish, no wait
            end = getattr(self.backend, "end_frame", None)
            if callable(end):
                for k, v in end().items():
                    stats[k] = stats.get(k, 0) + v
        glio.check_errors(self.ctx, f"frame {self.frame_index}")
        wall = (time.perf_counter() - t0) * 1e3
        self.frame_index += 1
        rays = {RayType(i).label: int(counts[i]) for i in range(6) if counts[i] > 0}
        return FrameReport(gpu_ms, prof.cpu_ms(), wall, rays, dict(prof.by_label), stats, captured,
                           self.overlay_source, iostats.end_frame(),
                           {k: dict(v) for k, v in prof.io_by_phase.items()})

    def _batch_passes(self, passes, lengths, source, capture, captured, stats) -> tuple[np.ndarray, bool]:
        """Every pass through the RayBatch / HitBuffer textures (GL backends, overlay frames):
        (ray counts per type, whether the overlays were copied)."""
        s, prof = self.settings, self.profiler
        self.raygen.reset_count()
        overlay_done = False
        for ray_type, sample, light, weight in passes:
            with prof.phase("raygen"):
                count = self.raygen.generate(self.rays, self.gbuffer, ray_type, sample, light,
                                             lengths.get(ray_type, 0.0), np.radians(s.perturb_deg))
            prof.label = ray_type.label
            pinfo = PassInfo(ray_type, sample, light, weight, ray_count=count)
            result = self.backend.trace(self.rays, pinfo, self.hits)
            prof.label = None
            self.backend_overlays = tuple(result.overlays)
            if source is not None and not overlay_done and (ray_type, sample) == source:
                overlay_done = self._capture_overlays(result.overlays)
            for k, v in result.stats.items():
                stats[k] = stats.get(k, 0) + v
            if capture:
                t, tri = self.hits.read()
                captured.append(CapturedPass(ray_type, sample, light, self.rays.read(), t, tri))
            if ray_type != RayType.PRIMARY:
                with prof.phase("accumulate"):
                    self.accumulate.add(ray_type, self.rays, self.hits, self.gbuffer, light, weight)
                self.samples_done.setdefault(ray_type, set()).add(sample)
        return self.raygen.read_counts(), overlay_done

    def _device_passes(self, passes, lengths, cam_u, light_u, keep, capture, captured, stats,
                       shade: bool = True) -> np.ndarray:
        """Every pass on the CL device (viewer.cl.frame): the G-buffer ids in once, rays made,
        traced and accumulated there, the used accumulators out once, the ray counts read with
        them (without `shade` the accumulators stay on the device: a later call with `keep` takes
        them out). Phases are timed by queue markers (no host wait per phase or pass); the backend's
        `end_frame` (optional) reports counters kept on the device over the frame."""
        from viewer.cl.frame import DeviceFrame

        s, prof = self.settings, self.profiler
        if self._device is None:
            self._device = DeviceFrame()
        dev = self._device
        q = dev.ctx.queue
        dev.set_scene(self.scene)
        prof.cl_deferred = True  # every CL phase of the frame timed by markers: no wait per phase
        try:
            with prof.cl_phase("device:ids", q):
                dev.begin(self.size, self.gbuffer.tri_id, cam_u, light_u, keep, self.gbuffer_drawn)
            for ray_type, sample, light, weight in passes:
                with prof.cl_phase("raygen", q):
                    dev.generate(ray_type, sample, light, lengths.get(ray_type, 0.0), np.radians(s.perturb_deg))
                prof.label = ray_type.label
                result = self.backend.trace_device(dev.rays, PassInfo(ray_type, sample, light, weight), dev.hits)
                prof.label = None
                self.backend_overlays = tuple(result.overlays)
                for k, v in result.stats.items():
                    stats[k] = stats.get(k, 0) + v
                if capture:  # verification only: the pass's rays and hits read back
                    t, tri = dev.hits.read()
                    captured.append(CapturedPass(ray_type, sample, light, dev.rays.read(), t, tri))
                if ray_type != RayType.PRIMARY:
                    with prof.cl_phase("accumulate", q):
                        dev.accumulate(ray_type, light, weight)
                    self.samples_done.setdefault(ray_type, set()).add(sample)
            end = getattr(self.backend, "end_frame", None)
            if callable(end):
                for k, v in end().items():
                    stats[k] = stats.get(k, 0) + v
            dev.request_counts()  # arrives with the accumulators' reads (no wait of its own)
            if shade:
                with prof.cl_phase("device:accumulators", q):
                    dev.write_accumulators(self.accumulate.textures, sorted(self.samples_done, key=int))
        finally:
            prof.cl_deferred = False
        return dev.read_counts()

    def _traced_gbuffer(self, camera: Camera) -> None:
        """The G-buffer from the backend's nearest hits of primary rays (gbuffer_source "trace"):
        phases gbuffer:rays, the backend's trace:primary, gbuffer:fill. The rays are not counted
        (raygen's counters are reset after the G-buffer) and no overlay is taken from this pass."""
        prof = self.profiler
        with prof.phase("gbuffer:rays"):
            self.raygen.generate(self.rays, self.gbuffer, RayType.PRIMARY, 0, 0, 0.0, 0.0)
        self.backend.trace(self.rays, PassInfo(RayType.PRIMARY, 0, 0, 1.0, report=False), self.hits)
        with prof.phase("gbuffer:fill"):
            self.gbuffer.fill_from_hits(camera, self.hits, self.quad)

    def read_image(self) -> np.ndarray:
        """The raw frame (uint8 (H, W, 3), top row first): what tests and the bench compare."""
        return self.shade.read_rgb()

    # -- denoising of the picture shown or saved (viewer.denoise); read_image stays raw ----------
    @property
    def device_denoiser(self):
        """The a-trous pass (viewer.passes.denoise), created on first use."""
        if self._atrous is None:
            from viewer.passes.denoise import AtrousPass

            self._atrous = AtrousPass(self.ctx, self.programs, self.quad, self.size)
        self._atrous.resize(self.size)
        return self._atrous

    @property
    def noisy(self) -> bool:
        """The final image has sampled (Monte Carlo) effects: soft shadows, AO or diffuse. Point-light
        shadows and mirror reflections are one exact ray per pixel: nothing to denoise."""
        s = self.settings
        return bool(s.soft or s.ao or s.diffuse)

    @property
    def shown_texture(self) -> moderngl.Texture:
        """The picture of the last frame: device-filtered when `denoise` filtered it, else raw."""
        return self._atrous.color if self.denoised and self._atrous is not None else self.final_texture

    def denoise_on_device(self, camera: Camera | None = None) -> moderngl.Texture:
        """Filter the last frame on the device (a few draws, no read-back); the filtered texture.
        A shade view other than "final" (one effect alone, a diagnostic) is shown unfiltered."""
        if self.view != "final":
            return self.final_texture
        return self.device_denoiser.render(self.final_texture, self.gbuffer)

    def read_guides(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(albedo, normal) float32 (H, W, 3) and kept (H, W) bool (background or mirror pixels),
        top row first, from the G-buffer of the last frame."""
        from viewer.gl.textures import read_texture

        alb, nrm, ids = (read_texture(t)[::-1] for t in (self.gbuffer.albedo, self.gbuffer.normal, self.gbuffer.tri_id))
        nrm, ids = nrm[..., :3], ids[..., 0]
        kept = (ids < 0) | (alb[..., 3] > 0.5)
        return np.ascontiguousarray(alb[..., :3]), np.ascontiguousarray(nrm), kept

    def read_denoised(self, method: str = "library", camera: Camera | None = None,
                      image: np.ndarray | None = None) -> np.ndarray:
        """The last frame filtered, uint8 (H, W, 3), top row first. "library": Open Image Denoise
        on `image` (default read_image(); the device filter where pyoidn is missing); "device":
        the a-trous pass on the shaded texture. Views other than "final", and frames without
        sampled effects (`noisy`), come back raw."""
        from viewer.denoise import library_denoise, library_missing

        if self.view != "final" or not self.noisy:
            return self.read_image() if image is None else image
        if method == "library" and library_missing() is None:
            alb, nrm, kept = self.read_guides()
            return library_denoise(self.read_image() if image is None else image, alb, nrm, kept)
        tex = self.device_denoiser.render(self.final_texture, self.gbuffer)
        data = np.frombuffer(glio.read(tex), np.uint8).reshape(self.size[1], self.size[0], 4)
        return np.ascontiguousarray(data[::-1, :, :3])

    def read_gbuffer_ids(self) -> np.ndarray:
        """int32 (H*W,) raster triangle id per pixel (row 0 = bottom), -1 = background."""
        from viewer.gl.textures import read_texture

        ids = read_texture(self.gbuffer.tri_id).reshape(-1)
        return np.where(ids < 0, -1, ids).astype(np.int32)

    def stats(self) -> dict:
        st = self.bvh.stats.to_dict()
        st["gpu_memory_bytes"] = self.gpu_scene.memory_bytes
        return st

    def release(self) -> None:
        for backend in self._backends.values():
            backend.release()
        for obj in (self.gbuffer, self.raygen, self.accumulate, self.shade, self.rays, self.hits, self.gpu_scene):
            obj.release()
        if self._overlay is not None:
            self._overlay.release()
        if self._device is not None:
            self._device.release()
            self._device = None
        if self._atrous is not None:
            self._atrous.release()
            self._atrous = None
        if self._idle_fbo is not None:
            self._idle_fbo.release()
            self._overlay = None

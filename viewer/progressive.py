"""Progressive refinement: responsive while the camera moves, converging when it stops.

A `Progressive` drives a Renderer one call per displayed frame:
- the camera (or the settings, view, backend or size) changed since the last call: a new image
  with one sample pass per effect (sample 0 of each), at a render scale chosen to keep the frame
  time near `target_ms` (the window upscales the smaller image when it blits);
  its G-buffer from whichever source (Renderer.gbuffer_source: the plain "preview" raster, whose
  cost follows the triangles in view, or the backend's primary rays, whose cost follows the
  pixels) measured cheaper at that size (each is tried, and the other one again every PROBE_EVERY
  moving frames); a moving image is replaced as soon as the camera stops, so it does not need the
  exact raster's coverage;
- unchanged: at full scale, add the next sample pass of every effect that wants more into the
  accumulators (Renderer.render(samples=(k,), keep=True)) until the requested counts are reached;
- all done: idle (nothing is rendered; the last image stays).

The accumulators get the same passes with the same weights as the full-quality frame, and the
shade pass scales each by requested / done sample passes, so the converged image is the
full-quality frame (same sums in the same order) and every image on the way is a complete,
noisier estimate. Recordings and `rtwalk bench` render full-quality frames unless asked
(`rtwalk bench --progressive`, which measures this mode with viewer.bench.progressive).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from viewer.camera import Camera
from viewer.renderer import FrameReport, Renderer

SCALE_RUNGS_PER_OCTAVE = 4  # render scales step by 2^(1/4) (~19 %): each change reallocates the targets
MIN_SCALE = 1 / 16  # floor of the moving frames' scale (56x32 of an 896x504 window), reached only under load
DEFAULT_TARGET_MS = 60.0  # moving frames: 16.7 fps, a margin over 15 for the load's jitter
GBUFFER_SOURCES = ("preview", "trace")  # moving frames; still frames use the exact "raster"
PROBE_EVERY = 24  # moving frames between two tries of the G-buffer source not in use


@dataclass
class Step:
    """What one call did: `report` None when idle (the image is already converged)."""

    report: FrameReport | None
    moving: bool  # the camera (or anything else) changed: a one-pass-per-effect image
    scale: float  # render scale of the image now shown (1 = full)
    samples_done: int  # sample passes accumulated per effect (the largest count among effects)
    samples_requested: int
    converged: bool

    def line(self) -> str:
        state = "moving" if self.moving else ("converged" if self.converged else "refining")
        return f"samples {self.samples_done}/{self.samples_requested}, render scale {self.scale:.2f} ({state})"


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(1, int(round(size[0] * scale))), max(1, int(round(size[1] * scale)))


def _camera_key(camera: Camera) -> tuple:
    return (tuple(np.round(np.asarray(camera.position, np.float64), 12)),
            tuple(np.round(np.asarray(camera.orientation, np.float64), 12)), float(camera.fov_y))


class Progressive:
    def __init__(self, renderer: Renderer, full_size: tuple[int, int], target_ms: float = DEFAULT_TARGET_MS,
                 min_scale: float = MIN_SCALE, resize: Callable[[tuple[int, int]], None] | None = None):
        """`resize`: how to resize the renderer (the window binds its screen first)."""
        self.renderer = renderer
        self.resize = resize or renderer.resize
        self.full_size = tuple(full_size)
        self.target_ms = float(target_ms)
        self.min_scale = float(min_scale)
        self.scale = 1.0  # the scale used for moving frames (adapted)
        self.shown_scale = 1.0
        self._key: tuple | None = None
        self._next = 0  # next sample index to accumulate at full scale (0: start over)
        # per-frame time spent outside render() (the window's panel, blit and swap), measured by the
        # caller: the budget is for the whole frame, so the render gets what that leaves
        self.extra_ms = 0.0
        self._source_cost: dict[str, tuple[float, int]] = {}  # source -> (frame ms, pixels) last measured
        self._source_backend = ""
        self._moving_frames = 0

    def invalidate(self) -> None:
        """Something outside (a screenshot render) used the renderer: start over."""
        self._key = None

    def requested(self) -> int:
        req = self.renderer.samples_requested()
        return max(req.values()) if req else 1

    def _state_key(self, camera: Camera) -> tuple:
        r = self.renderer
        return (_camera_key(camera), tuple(sorted(r.settings.to_dict().items())), r.view, r.backend_name,
                self.full_size, r.scene_time)  # an animated scene's new time is a moving frame

    def _adapt(self, wall_ms: float) -> None:
        """Scale for the next moving frame from the measured frame time (the render's wall time plus
        `extra_ms`), so the budget holds when other work slows the machine: cost ~ pixels ~ scale^2,
        with a dead band against flicker."""
        if wall_ms <= 0:
            return
        ideal = self.scale * math.sqrt(self.target_ms / (wall_ms + max(self.extra_ms, 0.0)))
        ideal = min(1.0, max(self.min_scale, ideal))
        if ideal < self.scale * 0.95 or ideal > self.scale * 1.15:
            self.scale = self._rung(ideal)

    def _rung(self, ideal: float) -> float:
        """The largest scale of the ladder min_scale * 2^(k / SCALE_RUNGS_PER_OCTAVE) (and 1) not above
        `ideal`: steps relative to the scale, so a small scale can climb back one step at a time
        (fixed steps of 1/16 kept a 1/16 image there until the frame took a quarter of the budget)."""
        if ideal >= 1.0:
            return 1.0
        k = math.floor(SCALE_RUNGS_PER_OCTAVE * math.log2(ideal / self.min_scale) + 1e-9)
        return min(1.0, max(self.min_scale, self.min_scale * 2.0 ** (k / SCALE_RUNGS_PER_OCTAVE)))

    def _pick_source(self, pixels: int) -> str:
        """The G-buffer source expected cheaper for a moving frame of `pixels`: the raster's frame
        time taken as is (its cost follows the triangles in view), the traced one's scaled by the
        pixels (one primary ray each); each source is measured first, and the other one again every
        PROBE_EVERY moving frames (the view and the load change)."""
        r = self.renderer
        if r.backend_name != self._source_backend:
            self._source_cost, self._source_backend = {}, r.backend_name
        for src in GBUFFER_SOURCES:
            if src not in self._source_cost:
                return src
        self._moving_frames += 1
        (raster_ms, _), (trace_ms, trace_px) = self._source_cost["preview"], self._source_cost["trace"]
        best = "preview" if raster_ms <= trace_ms * pixels / max(trace_px, 1) else "trace"
        if self._moving_frames % PROBE_EVERY == 0:
            return "trace" if best == "preview" else "preview"
        return best

    def frame(self, camera: Camera) -> Step:
        r = self.renderer
        key = self._state_key(camera)
        requested = self.requested()
        if key != self._key:  # moving: one pass per effect at the adapted scale
            self._key = key
            size = scaled_size(self.full_size, self.scale)
            self.resize(size)
            r.gbuffer_source = source = self._pick_source(size[0] * size[1])
            try:
                report = r.render(camera, samples=(0,))
            finally:
                r.gbuffer_source = "raster"  # still frames and everyone else: the exact raster
            self._source_cost[source] = (report.wall_ms, size[0] * size[1])
            self.shown_scale = self.scale
            self._adapt(report.wall_ms)
            # a moving image is never part of the converged one: once the camera stops, start over at
            # full scale from the exact raster (the converged image is the full-quality frame exactly)
            self._next = 0
            return Step(report, True, self.shown_scale, 1, requested, requested <= 1 and self._next == 1)
        if self._next == 0:  # stopped after a reduced-scale image: start over at full scale
            self.resize(self.full_size)
            report = r.render(camera, samples=(0,))
            self.shown_scale, self._next = 1.0, 1
            return Step(report, False, 1.0, 1, requested, requested <= 1)
        if self._next < requested:
            report = r.render(camera, samples=(self._next,), keep=True)
            self._next += 1
            return Step(report, False, 1.0, self._next, requested, self._next >= requested)
        return Step(None, False, 1.0, requested, requested, True)


STEPPED_MIN_RAYS = 32_000_000  # a still frame with this many rays (17-20 s on 2 cores) is rendered in steps
MIN_SAMPLES_PER_STEP = 4  # a step's own cost (a finish, the ray counts' read) stays small beside its passes
MAX_STEPS = 16  # enough for a useful bar


def render_stepped(r: Renderer, camera: Camera, on_step: Callable[[int, int], None] | None = None
                   ) -> tuple[dict[str, float], dict[str, int]]:
    """The full-quality frame in steps of whole sample passes, so a long still render (`rtwalk
    render`) can show progress: sample 0 of every effect, then the later sample passes added in
    order, at least MIN_SAMPLES_PER_STEP a step (Renderer.render(samples=..., keep=True), the same
    sums in the same order: the same image as one call). One call where the frame is small (under
    STEPPED_MIN_RAYS rays), has too few sample passes, or shows a backend overlay (captured from one
    pass of one call).
    `on_step(done, steps)` after each step. Returns the GPU ms per phase and the rays per ray
    type, summed over the steps."""
    passes = r.passes()
    samples = sorted({p[1] for p in passes})
    pixels = r.size[0] * r.size[1]
    later = len(samples) - 1
    if later < MIN_SAMPLES_PER_STEP or pixels * len(passes) < STEPPED_MIN_RAYS or r.is_overlay_view:
        steps = [tuple(samples)]
    else:
        parts = min(MAX_STEPS - 1, later // MIN_SAMPLES_PER_STEP)
        steps = [(samples[0],)] + [tuple(int(k) for k in part) for part in np.array_split(samples[1:], parts)]
    gpu_ms: dict[str, float] = {}
    rays: dict[str, int] = {}
    for i, step in enumerate(steps):
        last = i == len(steps) - 1
        report = r.render(camera, samples=None if len(steps) == 1 else step, keep=i > 0, shade=last)
        for k, v in report.gpu_ms.items():
            gpu_ms[k] = gpu_ms.get(k, 0.0) + v
        for k, v in report.rays.items():
            rays[k] = rays.get(k, 0) + v
        if on_step is not None:
            on_step(i + 1, len(steps))
    return gpu_ms, rays

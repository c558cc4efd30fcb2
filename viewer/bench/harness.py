"""Backend-neutral timing harness shared by `rtwalk bench` and the studies (`rtwalk bench-chcrt`, ...).

It replays a recording deterministically (frames sampled at a fixed rate, never the wall clock),
runs configurations over consecutive frames (warm-up, reset of temporal state, timed frames: the
first is the cold frame, the mean of the rest the steady state), interleaves configurations frame
by frame so other jobs on a shared machine slow them alike, and shows progress. Backends are known
only through `viewer.backends` (their `info`): no backend is named here.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viewer.backends.interface import params_text
from viewer.errors import RtwalkError

# Warm-up of every run: the first frames of the run's path (at most two samples an effect), then a
# reset of the backend's temporal state. Three frames, because a backend with temporal state may
# reach its steady passes only in its third frame (a structure built on the host, then moved to the
# device, then used), and the driver compiles what those passes draw when they first draw it: with
# Mesa's shader cache cold (a fresh machine, a changed shader) one warm-up frame left 250-500 ms of
# llvmpipe compiles in the first timed frames (Table 2's city-near at 640x360 with
# MESA_SHADER_CACHE_DISABLE=true: chcrt's camera rays took 247 and 163 ms in timed frames 1 and 2
# against 50 ms steady, its AO 490 and 201 against 180). Two samples, because an effect's later
# sample passes may take other paths than its first.
WARMUP_FRAMES, WARMUP_SAMPLES = 3, 2
TRACE_PREFIX = "trace:"  # the renderer's per-ray-type tracing phases (backends without own phases)
PROTOCOL = (f"{WARMUP_FRAMES} warm-up frames (at most {WARMUP_SAMPLES} samples per effect), backend reset; then "
            "consecutive frames: the first is the cold "
            "frame, the mean of the rest the steady state; configurations compared in one table are interleaved "
            "frame by frame")


# ----------------------------------------------------------------------------------------- frames


def frame_numbers(rec, fps: float | None, max_frames: int | None, first_frame: int | None = None) -> list[int]:
    """Frames to replay: all, `max_frames` spread over the path, or consecutive from `first_frame`
    (what temporal-coherence methods need: spread frames are far apart in time)."""
    n = rec.frame_count(fps)
    if first_frame is not None:
        if not 0 <= first_frame < n:
            raise RtwalkError(f"--first-frame {first_frame} is outside the recording's 0..{n - 1}")
        return list(range(first_frame, min(n, first_frame + (max_frames or n))))
    if max_frames is not None and max_frames < n:
        # spread the frames over the whole path, still deterministic
        return sorted({int(round(i * (n - 1) / max(max_frames - 1, 1))) for i in range(max_frames)})
    return list(range(n))


def mrays(rep) -> dict[str, float]:
    """Mrays/s per ray type (and 'all') of a FrameReport: rays / tracing GPU time."""
    out = {}
    for ray, count in rep.rays.items():
        ms = rep.trace_ms_by_ray.get(ray, 0.0)
        out[ray] = count / (ms * 1e3) if ms > 0 else float("nan")
    total_ms = rep.trace_ms
    out["all"] = sum(rep.rays.values()) / (total_ms * 1e3) if total_ms > 0 else float("nan")
    return out


def frame_row(rep, rec, n: int, fps: float | None = None) -> dict:
    """One frame's numbers as stored in every report."""
    return {"frame": n, "time_s": float(rec.frame_times(fps)[n]),
            "scene_time_s": rec.scene_time_for_frame(n, fps), "wall_ms": rep.wall_ms,
            "build_ms": {k[len("build:"):]: v for k, v in rep.gpu_ms.items() if k.startswith("build:")},
            "gpu_ms": rep.gpu_ms, "cpu_ms": rep.cpu_ms, "trace_ms": rep.trace_ms,
            "trace_ms_by_ray": rep.trace_ms_by_ray, "rays": rep.rays,
            "mrays_per_s": mrays(rep), "backend_stats": rep.backend_stats, "io": rep.io.as_dict()}


def image_error(a: np.ndarray, b: np.ndarray) -> dict:
    """Mean/max absolute error (0..255), PSNR and the share of pixels off by more than 8."""
    diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
    mse = float((diff ** 2).mean())
    return {"mae": float(diff.mean()), "max": float(diff.max()),
            "psnr_db": float(10 * np.log10(255.0 ** 2 / mse)) if mse > 0 else float("inf"),
            "pixels_over_8": float((diff.max(axis=-1) > 8).mean())}


def is_trace_phase(name: str, backend_phases: tuple[str, ...] = ()) -> bool:
    """Tracing time: the renderer's trace:* phases and the phases a backend declares (info.phases)."""
    return name.startswith(TRACE_PREFIX) or name in backend_phases


def effect_settings(effect: str):
    """One run's effects: 'ao:20', or several joined with '+' (or ','); a suffix '@perturb=D' sets the
    per-pixel sample rotation in degrees (default 36, 0..180)."""
    from viewer.effects import parse_effects

    text, _, opt = effect.partition("@")
    s = parse_effects(text.replace("+", ","))
    if opt:
        key, _, val = opt.partition("=")
        try:
            deg = float(val)
        except ValueError:
            deg = -1.0
        if key.strip() != "perturb" or not 0 <= deg <= 180:
            raise RtwalkError(f"bad effect option '@{opt}': expected @perturb=D with D in 0..180 degrees")
        s.perturb_deg = deg
    return s


def warmup_settings(effect: str):
    """The warm-up frames' effects: `effect` with at most WARMUP_SAMPLES samples each."""
    s = effect_settings(effect)
    for name in ("soft_samples", "ao_samples", "diffuse_samples"):
        setattr(s, name, min(getattr(s, name), WARMUP_SAMPLES))
    return s


def load_average() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


# ----------------------------------------------------------------------------------------- runs


@dataclass
class FrameStats:
    """Means over a set of frames (cold: the first frame alone; steady: the rest)."""

    frames: int
    trace_ms: float  # GPU time of the tracing phases (trace:* and the backend's own phases)
    trace_cpu_ms: float  # CPU time inside those phases (Python, submission, waits for query results)
    wall_ms: float  # whole frame, glFinish included
    gpu_ms: float  # all GPU phases
    rays: float
    mrays_per_s: float  # rays / trace_ms
    counters: dict[str, float]

    @staticmethod
    def of(rows: list[dict]) -> FrameStats:
        def mean(vals) -> float:
            vals = [float(v) for v in vals]
            return float(np.mean(vals)) if vals else float("nan")

        keys = sorted({k for r in rows for k in r["backend_stats"]})
        trace = mean(r["trace_gpu_ms"] for r in rows)
        rays = mean(sum(r["rays"].values()) for r in rows)
        return FrameStats(len(rows), trace, mean(r["trace_cpu_ms"] for r in rows), mean(r["wall_ms"] for r in rows),
                          mean(sum(r["gpu_ms"].values()) for r in rows), rays,
                          rays / (trace * 1e3) if trace > 0 else float("nan"),
                          {k: mean(r["backend_stats"].get(k, 0.0) for r in rows) for k in keys})


@dataclass
class RunResult:
    """One configuration over consecutive frames: the raw per-frame rows and their summaries."""

    label: str
    recording: str
    scene: str
    size: tuple[int, int]
    effect: str
    backend: str
    params: str | None  # the backend's effective parameters (None for a backend without any)
    frame_numbers: list[int]
    frames: list[dict]
    cold: FrameStats
    steady: FrameStats

    @property
    def best(self) -> FrameStats:
        """Steady state where there is one (>= 2 frames), else the cold frame."""
        return self.steady if self.steady.frames else self.cold


ImageSink = Callable[[int, int, np.ndarray], None]


@dataclass
class RunSpec:
    """One configuration to time: label, effect, backend, its parameter text, image consumer."""

    label: str
    effect: str
    backend: str
    params: str | None = None
    sink: ImageSink | None = None


class Harness:
    """One GL context and a scene cache shared by all runs of a command."""

    def __init__(self, frames: int = 4, first_frame: int | None = None, quiet: bool = False, ctx=None):
        from viewer.gl.context import shared_context
        from viewer.profiler import choose_timing

        self.frames, self.first_frame, self.quiet = frames, first_frame, quiet
        self.interrupt = None  # a viewer.bench.partial.PartialRun: run_many stops between comparisons
        self.ctx = ctx if ctx is not None else shared_context()
        self.device = {"renderer": self.ctx.info.get("GL_RENDERER"), "version": self.ctx.info.get("GL_VERSION"),
                       "phase_timing": choose_timing(self.ctx)}
        self.device_text = f"{self.device['renderer']} (phase times: {self.device['phase_timing']})"
        self._scenes: dict[str, object] = {}
        self._recs: dict[Path, object] = {}
        self.load_at_start = load_average()
        self.bar = None

    def recording(self, path: Path):
        from viewer.recording import load_recording

        if path not in self._recs:
            self._recs[path] = load_recording(path)
        return self._recs[path]

    def scene(self, path: Path):
        """The recording's scene, prepared (BVH) once per command."""
        from viewer.recording import resolve_scene_spec
        from viewer.session import prepare_scene

        rec = self.recording(path)
        spec = resolve_scene_spec(rec, path)
        key = json.dumps([spec.spec, spec.size, spec.seed])
        if key not in self._scenes:
            if self.bar is not None:
                self.bar.set_postfix_str(f"loading {Path(spec.spec).name}")
            self._scenes[key] = prepare_scene(spec.spec, scene_size=spec.size, seed=spec.seed or 1, quiet=True)
        return self._scenes[key]

    def frames_for(self, path: Path, count: int) -> list[int]:
        """`count` consecutive frames: from `first_frame`, else from a third into the path."""
        rec = self.recording(path)
        n = rec.frame_count()
        first = self.first_frame
        if first is None:
            first = max(0, min(n // 3, n - count))
        return frame_numbers(rec, None, count, first)

    def run(self, label: str, path: Path, size: tuple[int, int], effect: str, backend: str,
            params: str | None = None, frames: list[int] | None = None, sink: ImageSink | None = None) -> RunResult:
        """One configuration (see run_many)."""
        return self.run_many(path, size, [RunSpec(label, effect, backend, params, sink)], frames)[0]

    def run_many(self, path: Path, size: tuple[int, int], specs: list[RunSpec],
                 frames: list[int] | None = None) -> list[RunResult]:
        """Configurations compared with each other, on the same consecutive frames, interleaved frame
        by frame (each keeps its own renderer and temporal state), so that other jobs on a shared
        machine slow them alike. Per configuration: warm-up, reset, timed frames (module docstring).
        A deferred Ctrl-C (`self.interrupt`, viewer.bench.partial) stops here, between comparisons."""
        from viewer.renderer import Renderer

        if self.interrupt is not None:
            self.interrupt.check()

        rec = self.recording(path)
        prep = self.scene(path)
        frames = frames if frames is not None else self.frames_for(path, self.frames)
        renderers: list = []
        rows: list[list[dict]] = [[] for _ in specs]
        try:
            for spec in specs:
                options = {spec.backend: spec.params} if spec.params else None
                r = Renderer(self.ctx, prep.scene, prep.bvh, size, spec.backend, warmup_settings(spec.effect), options)
                renderers.append(r)
                for n in frames[:WARMUP_FRAMES]:
                    r.set_scene_time(rec.scene_time_for_frame(n))
                    r.render(rec.camera_for_frame(n))
                r.settings = effect_settings(spec.effect)
                r.backend.reset()
            for k, n in enumerate(frames):
                cam = rec.camera_for_frame(n)
                scene_time = rec.scene_time_for_frame(n)
                for i, (spec, r) in enumerate(zip(specs, renderers, strict=True)):
                    r.set_scene_time(scene_time)
                    if self.bar is not None:
                        self.bar.set_postfix_str(f"{path.stem} {size[0]}x{size[1]} {spec.effect} {spec.label}")
                    rep = r.render(cam)
                    own = tuple(r.backend.info.phases)
                    row = frame_row(rep, rec, n)
                    row["cold"] = k == 0
                    row["trace_gpu_ms"] = sum(v for p, v in rep.gpu_ms.items() if is_trace_phase(p, own))
                    row["trace_cpu_ms"] = sum(v for p, v in rep.cpu_ms.items() if is_trace_phase(p, own))
                    rows[i].append(row)
                    if spec.sink is not None:
                        spec.sink(k, n, r.read_image())
                    if self.bar is not None:
                        self.bar.update(1)
            params = [params_text(r.backend.params) or None for r in renderers]
        finally:
            for r in renderers:
                r.release()
        return [RunResult(s.label, path.stem, prep.scene.name, size, s.effect, s.backend, params[i], list(frames),
                          rows[i], FrameStats.of(rows[i][:1]), FrameStats.of(rows[i][1:]))
                for i, s in enumerate(specs)]

    def progress(self, desc: str, total: int):
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc=desc, unit="frame", disable=self.quiet, file=sys.stderr)
        return self.bar

    def done(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

"""`rtwalk bench --progressive`: a recording replayed in the window's progressive mode
(viewer.progressive), reporting moving frame times, time to convergence and the converged image's
error against the full-quality frame."""

from __future__ import annotations

import sys
import time

import numpy as np

from viewer.progressive import DEFAULT_TARGET_MS, Progressive
from viewer.renderer import Renderer


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, np.float64), q)) if values else float("nan")


def replay_progressive(prepared, rec, settings, opts, ctx, target_ms: float = DEFAULT_TARGET_MS,
                       quiet: bool = False) -> dict:
    """Headless replay in progressive mode: every replayed frame is a moving frame; at the last
    camera the path stops and passes are added until converged. Reports frame times (median, p95)
    while moving, the render scales used, the time to convergence after the stop, and the converged
    image's error against the full-quality frame of the same camera (mean absolute, 0..255)."""
    from viewer.bench.harness import frame_numbers

    renderer = Renderer(ctx, prepared.scene, prepared.bvh, opts.size, opts.backend, settings, opts.backend_options)
    prog = Progressive(renderer, opts.size, target_ms)
    frames = frame_numbers(rec, opts.fps, opts.max_frames, opts.first_frame)
    cams = [rec.camera_for_frame(n, opts.fps) for n in frames]
    scene_times = [rec.scene_time_for_frame(n, opts.fps) for n in frames]
    renderer.set_scene_time(scene_times[0])
    renderer.render(cams[0])  # warm-up: compile every shader variant at full size
    for cam in cams[:2]:  # and the first adaptation steps
        prog.frame(cam)
    prog.invalidate()
    moving_ms, scales = [], []
    for cam, scene_time in zip(cams, scene_times, strict=True):
        renderer.set_scene_time(scene_time)
        t = time.perf_counter()
        step = prog.frame(cam)
        moving_ms.append((time.perf_counter() - t) * 1e3)
        scales.append(step.scale)
    stop = cams[-1]
    t = time.perf_counter()
    refine_ms = []
    while True:
        t1 = time.perf_counter()
        step = prog.frame(stop)
        if step.report is None:
            break
        refine_ms.append((time.perf_counter() - t1) * 1e3)
        if step.converged:
            break
    converge_s = time.perf_counter() - t
    image = renderer.read_image().astype(np.int16)
    renderer.render(stop)  # the full-quality frame of the same camera
    full = renderer.read_image().astype(np.int16)
    mae = float(np.abs(image - full).mean())
    renderer.release()
    out = {
        "format": "rtwalk-progressive", "version": 1, "backend": opts.backend, "size": list(opts.size),
        "effects": settings.to_dict(), "target_ms": target_ms, "frames": len(cams),
        "moving_ms": {"median": _percentile(moving_ms, 50), "p95": _percentile(moving_ms, 95),
                      "max": max(moving_ms), "all": moving_ms},
        "scale": {"median": _percentile(scales, 50), "min": min(scales), "max": max(scales)},
        "converge": {"seconds": converge_s, "frames": len(refine_ms), "frame_ms": refine_ms},
        "converged_vs_full_mae": mae,
    }
    if not quiet:
        print(f"progressive: {len(cams)} moving frames: median {out['moving_ms']['median']:.0f} ms, "
              f"p95 {out['moving_ms']['p95']:.0f} ms (target {target_ms:.0f} ms), render scale median "
              f"{out['scale']['median']:.2f}; converged {converge_s:.2f} s after the stop "
              f"({len(refine_ms)} frames), |converged - full| = {mae:.4f}/255 mean", file=sys.stderr)
    return out

"""`rtwalk view --frame-log FILE`: what each window frame cost, written when the window closes.

The window's own numbers (not a benchmark's): per loop iteration the wall time from one iteration
to the next (render, panel, blit and swap), the render's wall time, whether the camera moved, the
render scale and size, where the G-buffer came from, and the phases' times. The summary gives the
medians of moving, refining (still, not converged) and idle iterations, the fps they make, and the
load average at the end, since the window shares the machine.

JSON: {"summary": {...}, "frames": [{"n", "iteration_ms", "render_ms", "state", "scale", "size",
"gbuffer", "gpu_ms"}, ...]}; state is "moving", "refining" or "idle".
"""

from __future__ import annotations

import json
import os
import statistics
from pathlib import Path

from viewer.errors import RtwalkError


def gbuffer_source(gpu_ms: dict[str, float]) -> str:
    """The G-buffer source a frame used, from its phase names ("" when none ran)."""
    if "gbuffer:fill" in gpu_ms:
        return "trace"
    if "gbuffer:preview" in gpu_ms:
        return "preview"
    return "raster" if "gbuffer" in gpu_ms else ""


def check_frame_log(path: str, force: bool = False) -> None:
    """Before the window opens: a new file in a folder that can be written (a log already there is
    somebody's finished measurement: refused, not replaced, unless view --force)."""
    from viewer.cli_args import check_output_dir

    p = Path(path).expanduser()
    if p.exists() and not force:
        raise RtwalkError(f"--frame-log {path}: exists; pass --force to replace it, or choose another file")
    check_output_dir(str(p.parent), "--frame-log")


class FrameLog:
    def __init__(self, path: str):
        self.path = Path(path).expanduser()
        self.frames: list[dict] = []

    def add(self, n: int, iteration_ms: float, render_ms: float, step, report, size: tuple[int, int]) -> None:
        """One loop iteration; `step` is the progressive step (None without progressive mode)."""
        if report is None:
            state = "idle"
        elif step is None or step.moving:
            state = "moving"
        else:
            state = "refining"
        gpu = dict(report.gpu_ms) if report is not None else {}
        self.frames.append({"n": n, "iteration_ms": iteration_ms, "render_ms": render_ms, "state": state,
                            "scale": step.scale if step is not None else 1.0, "size": list(size),
                            "gbuffer": gbuffer_source(gpu), "gpu_ms": gpu})

    def summary(self) -> dict:
        out: dict = {"frames": len(self.frames)}
        for state in ("moving", "refining", "idle"):
            # the first iterations compile shaders and render the first full-size image
            ms = [f["iteration_ms"] for f in self.frames[2:] if f["state"] == state]
            med = statistics.median(ms) if ms else None
            out[state] = {"iterations": len(ms), "median_ms": med, "fps": 1000.0 / med if med else None}
        moving = [f for f in self.frames[2:] if f["state"] == "moving"]
        out["moving"]["scales"] = sorted({round(f["scale"], 4) for f in moving})
        out["moving"]["gbuffer"] = {s: sum(f["gbuffer"] == s for f in moving) for s in ("preview", "trace", "raster")}
        out["load_average"] = list(os.getloadavg())
        return out

    def line(self) -> str:
        s = self.summary()
        parts = []
        for state in ("moving", "refining"):
            if s[state]["iterations"]:
                parts.append(f"{state} {s[state]['fps']:.1f} fps (median {s[state]['median_ms']:.0f} ms over "
                             f"{s[state]['iterations']} frames)")
        if s["idle"]["iterations"]:
            parts.append(f"idle {s['idle']['iterations']} frames")
        if not parts:  # "no frames" was printed for a log of 20 (18 idle, 2 left out as warm-up)
            parts.append(f"{s['frames']} frames, all warm-up" if s["frames"] else "no frames")
        return "frame log: " + "; ".join(parts) + f"; load {s['load_average'][0]:.1f}"

    def write(self) -> Path:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.write_text(json.dumps({"summary": self.summary(), "frames": self.frames}, indent=1))
        except OSError as exc:
            raise RtwalkError(f"cannot write the frame log {self.path}: {exc.strerror or exc}") from None
        return self.path

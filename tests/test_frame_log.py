"""`rtwalk view --frame-log`: the closing line says what the log holds."""

from __future__ import annotations

from types import SimpleNamespace

from viewer.ui.frame_log import FrameLog


def _log(states: list[str]) -> FrameLog:
    log = FrameLog("unused.json")
    for n, state in enumerate(states):
        report = None if state == "idle" else SimpleNamespace(gpu_ms={"gbuffer": 1.0})
        step = SimpleNamespace(moving=state == "moving", scale=1.0)
        log.add(n, 10.0, 8.0, step, report, (32, 18))
    return log


def test_line_counts_idle_frames():
    """A window that converged at once and idled (the usual short `--max-frames` run) logged 20 frames;
    the line said "no frames"."""
    line = _log(["moving", "refining"] + ["idle"] * 18).line()
    assert "no frames" not in line and "idle 18 frames" in line
    assert "moving 100.0 fps" in _log(["moving"] * 4).line()
    assert "2 frames, all warm-up" in _log(["moving", "refining"]).line()
    assert "no frames" in _log([]).line()

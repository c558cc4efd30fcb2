"""The interactive window: camera controller maths, a real window under Xvfb, and the no-display error."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from viewer.camera import Camera
from viewer.ui.camera_controller import FAST_FACTOR, PITCH_LIMIT, FlyCamera


def _fly():
    return FlyCamera.from_camera(Camera.look_at([0, 1, 5], [0, 1, 0]), scene_diagonal=100.0)


def test_forward_moves_along_view_at_scene_scaled_speed():
    f = _fly()
    start = f.position.copy()
    f.update(0.5, ["forward"])
    np.testing.assert_allclose(f.position - start, [0, 0, -0.5 * f.speed], atol=1e-9)
    assert f.speed == pytest.approx(0.02 * 100.0)


def test_shift_is_faster_and_steps_are_frame_rate_independent():
    a, b, c = _fly(), _fly(), _fly()
    a.update(0.1, ["forward", "right"])
    b.update(0.05, ["forward", "right"])
    b.update(0.05, ["forward", "right"])
    np.testing.assert_allclose(a.position, b.position, atol=1e-12)
    c.update(0.1, ["forward"], fast=True)
    assert np.linalg.norm(c.position - _fly().position) == pytest.approx(FAST_FACTOR * 0.1 * c.speed)


def test_mouse_look_and_pitch_clamp():
    f = _fly()
    f.look(100, 0)  # drag right: turn right (yaw decreases about +Y)
    assert f.camera().forward[0] > 0
    f.look(0, -1e6)  # drag far up: pitch clamps
    assert f.pitch == pytest.approx(PITCH_LIMIT)
    assert math.isfinite(f.camera().forward[1])


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run not installed")
def test_window_runs_under_xvfb_and_shows_scene_and_panel(tmp_path):
    shot = tmp_path / "window.png"
    env = dict(os.environ, RTWALK_VIEW_FRAMES="3", RTWALK_VIEW_SCREENSHOT=str(shot))
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-m", "viewer.cli",
                           "view", "room", "--size", "480x270", "--quiet"], env=env, capture_output=True,
                          text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    img = np.asarray(Image.open(shot).convert("RGB")).astype(float)
    assert img.shape[:2] == (270, 480)
    assert img.std() > 10  # panel and scene, not a flat colour
    left, right = img[:, :120], img[:, 240:]
    assert abs(left.mean() - right.mean()) > 1  # the panel differs from the rendered scene


def test_view_without_display_is_one_line_error():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "viewer.cli", "view", "room"], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("rtwalk: error")]
    assert len(errors) == 1 and "display" in errors[0] and "Traceback" not in proc.stderr

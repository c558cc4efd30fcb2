"""The interactive window: camera controller (pure Python), panel helpers, and `rtwalk view` smoke
tests under xvfb-run (skipped where xvfb-run is missing)."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from viewer.camera import Camera, yaw_pitch_to_quat
from viewer.errors import RtwalkError
from viewer.progressive import MIN_SCALE, scaled_size
from viewer.ui.camera_controller import (
    FAST_FACTOR,
    PITCH_LIMIT,
    SPEED_FRACTION,
    WHEEL_FACTOR,
    FlyCamera,
    yaw_pitch_of,
)
from viewer.ui.panel import PANEL_WIDTH, FrameHistory, camera_argument, chart_phases, counter_rows, phase_label

REPO = Path(__file__).resolve().parents[1]
XVFB = shutil.which("xvfb-run")
# the window tests need a virtual display and the window packages (imgui-bundle, moderngl-window,
# pyglet): a machine that could not install one of them skips with the reason instead of failing
_UI_PACKAGES = {"imgui_bundle": "imgui-bundle", "moderngl_window": "moderngl-window", "pyglet": "pyglet"}
_MISSING_UI = [pip for mod, pip in _UI_PACKAGES.items() if importlib.util.find_spec(mod) is None]
needs_xvfb = pytest.mark.skipif(
    XVFB is None or bool(_MISSING_UI),
    reason="xvfb-run is not installed (apt-get install xvfb xauth)" if XVFB is None
    else f"window packages not installed: {', '.join(_MISSING_UI)} (pip install -e .)")


def fly(yaw=0.0, pitch=0.0, speed=2.0):
    return FlyCamera(np.zeros(3), yaw=yaw, pitch=pitch, base_speed=speed)


# --------------------------------------------------------------------------- camera controller


def test_w_moves_along_forward_by_speed_times_dt():
    f = fly(yaw=0.3, pitch=0.2, speed=2.0)
    cam = f.camera()
    f.update(0.1, ["forward"])
    np.testing.assert_allclose(f.position, cam.forward * 2.0 * 0.1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(f.position), 0.2, rtol=1e-12)


def test_axes_match_the_camera_and_other_keys():
    f = fly(yaw=-0.7, pitch=0.4)
    cam = f.camera()
    ax = f.axes()
    np.testing.assert_allclose(ax["forward"], cam.forward, atol=1e-12)
    np.testing.assert_allclose(ax["right"], cam.right, atol=1e-12)
    for action, expect in [("back", -cam.forward), ("right", cam.right), ("left", -cam.right),
                           ("up", [0, 1, 0]), ("down", [0, -1, 0])]:
        g = fly(yaw=-0.7, pitch=0.4, speed=1.0)
        g.update(1.0, [action])
        np.testing.assert_allclose(g.position, expect, atol=1e-12, err_msg=action)


def test_shift_multiplies_speed_and_diagonals_are_not_faster():
    a, b = fly(), fly()
    a.update(0.1, ["forward"])
    b.update(0.1, ["forward"], fast=True)
    np.testing.assert_allclose(b.position, a.position * FAST_FACTOR, atol=1e-12)
    c = fly(speed=2.0)
    c.update(0.5, ["forward", "right"])
    assert np.linalg.norm(c.position) == pytest.approx(1.0)
    d = fly()
    d.update(0.5, ["forward", "back"])  # opposite keys cancel
    np.testing.assert_allclose(d.position, 0.0)


def test_frame_rate_independence():
    a, b = fly(yaw=1.1, pitch=-0.3), fly(yaw=1.1, pitch=-0.3)
    a.update(0.05, ["forward", "up"], fast=True)
    a.update(0.05, ["forward", "up"], fast=True)
    b.update(0.1, ["forward", "up"], fast=True)
    np.testing.assert_allclose(a.position, b.position, atol=1e-12)
    c = fly()
    for _ in range(10):
        c.update(0.01, ["left"])
    d = fly()
    d.update(0.1, ["left"])
    np.testing.assert_allclose(c.position, d.position, atol=1e-12)
    e = fly()
    e.update(0.0, ["forward"])
    e.update(float("nan"), ["forward"])
    np.testing.assert_allclose(e.position, 0.0)


def test_mouse_look_changes_yaw_and_pitch():
    f = fly()
    f.look(10, 0)  # drag right: turn right (yaw about +Y decreases)
    assert f.yaw == pytest.approx(-10 * f.sensitivity)
    assert f.pitch == 0.0
    assert f.camera().forward[0] > 0  # now looking a little towards +X
    f.look(0, -20)  # drag up: look up
    assert f.pitch == pytest.approx(20 * f.sensitivity)
    assert f.camera().forward[1] > 0


def test_pitch_is_clamped():
    f = fly()
    f.look(0, -1e6)
    assert f.pitch == pytest.approx(PITCH_LIMIT)
    assert math.degrees(f.pitch) == pytest.approx(89.0)
    f.look(0, 1e6)
    assert f.pitch == pytest.approx(-PITCH_LIMIT)
    assert FlyCamera(np.zeros(3), pitch=3.0).pitch == pytest.approx(PITCH_LIMIT)


def test_wheel_scales_speed():
    f = fly(speed=2.0)
    f.scroll(1)
    assert f.speed == pytest.approx(2.0 * WHEEL_FACTOR)
    f.scroll(-3)
    assert f.speed == pytest.approx(2.0 / WHEEL_FACTOR**2)
    for _ in range(200):
        f.scroll(1)
    assert np.isfinite(f.speed) and f.speed < 2.0 * 1e4


def test_from_camera_round_trips_the_view_and_scales_speed_to_the_scene():
    cam = Camera.look_at([3.0, 2.0, 1.0], [-4.0, 1.0, -6.0], fov_y=50.0)
    f = FlyCamera.from_camera(cam, scene_diagonal=500.0)
    assert f.base_speed == pytest.approx(500.0 * SPEED_FRACTION)
    out = f.camera()
    np.testing.assert_allclose(out.position, cam.position)
    np.testing.assert_allclose(out.forward, cam.forward, atol=1e-9)
    np.testing.assert_allclose(out.up, cam.up, atol=1e-9)  # look_at has no roll
    assert out.fov_y == 50.0
    for yaw, pitch in [(0.0, 0.0), (2.5, -0.4), (-3.0, 1.2)]:
        y, p = yaw_pitch_of(Camera(np.zeros(3), yaw_pitch_to_quat(yaw, pitch)))
        assert y == pytest.approx(yaw) and p == pytest.approx(pitch)


# --------------------------------------------------------------------------- panel helpers


def test_camera_argument_reproduces_the_view():
    from viewer.cli_args import parse_camera

    cam = Camera.look_at([1.5, 2.25, -3.0], [10.0, 0.0, 4.0], fov_y=45.0)
    arg = camera_argument(cam, target_distance=5.0)
    back = parse_camera(arg)
    np.testing.assert_allclose(back.position, cam.position, atol=1e-4)
    np.testing.assert_allclose(back.forward, cam.forward, atol=1e-4)
    assert back.fov_y == 45.0
    assert " " not in arg and len(arg.split(",")) == 7


def test_frame_history_keeps_the_last_frames():
    h = FrameHistory(n=120)
    assert h.fps == 0.0 and h.array().shape == (1,)
    for i in range(300):
        h.add(10.0 + (i % 2), 5.0)
    assert len(h.frame_ms) == 120
    assert h.mean_ms == pytest.approx(10.5)
    assert h.array().dtype == np.float32


def test_phase_chart_data():
    declared = ("chc:1-intersect-visible", "chc:2-queries", "chc:3-traversal", "chc:4-final-intersect")
    gpu = {"gbuffer": 5.0, "chc:2-queries": 2.0, "chc:1-intersect-visible": 1.0, "shade": 1.0,
           "chc:4-final-intersect": 4.0, "chc:3-traversal": 3.0, "trace:ao": 9.0}
    assert list(chart_phases(gpu, declared)) == list(declared)  # the backend's phases, in its order
    assert list(chart_phases(gpu, declared[::-1])) == list(declared[::-1])
    assert chart_phases(gpu) == {"trace:ao": 9.0}  # nothing declared: the per-ray-type trace phases
    assert chart_phases({"gbuffer": 1.0, "trace:shadows": 2.0, "trace:ao": 3.0}, declared) == {"trace:shadows": 2.0,
                                                                                               "trace:ao": 3.0}
    h = FrameHistory(n=5)
    assert h.phase_table()[0] == [] and h.phase_table()[1].shape == (0, 0)
    h.add(10, 10, chart_phases(gpu, declared), {"queries": 4})
    h.add(10, 10, {"trace:ao": 7.0}, {"queries": 6})  # backend switched: other phases are 0 there
    names, table = h.phase_table()
    assert names[-1] == "trace:ao" and table.shape == (5, 2)
    np.testing.assert_array_equal(table[:, 0], [1, 2, 3, 4, 0])
    np.testing.assert_array_equal(table[:, 1], [0, 0, 0, 0, 7])
    assert h.counter_mean("queries") == 5.0 and h.counter_mean("draws") == 0.0
    for _ in range(10):
        h.add(1, 1)
    assert len(h.phases) == 5 and h.phase_table(last=3)[1].shape == (0, 3)


def test_phase_labels_and_counter_rows():
    assert phase_label("chc:2-queries") == "queries"
    assert phase_label("chc:1-intersect-visible") == "intersect visible"
    assert phase_label("trace:ao") == "ao" and phase_label("gbuffer") == "gbuffer"
    assert phase_label("x:10_final_step") == "final step" and phase_label("x:3") == "3"
    rows, others = counter_rows({"b": 1, "z": 2, "a": 3}, ("a", "b", "c"))
    assert rows == ["a", "b"] and others == ["z"]
    assert counter_rows({"b": 1}, ()) == ([], ["b"])


def test_initial_view(monkeypatch):
    from argparse import Namespace

    from viewer.ui.app import initial_view

    monkeypatch.delenv("RTWALK_VIEW_MODE", raising=False)
    assert initial_view(Namespace()) == "final"
    monkeypatch.setenv("RTWALK_VIEW_MODE", "query_overdraw")
    assert initial_view(Namespace()) == "query_overdraw"
    assert initial_view(Namespace(view="subtree_batches")) == "subtree_batches"
    monkeypatch.setenv("RTWALK_VIEW_MODE", "xray")
    with pytest.raises(RtwalkError, match="xray"):
        initial_view(Namespace())


def test_frame_limit(monkeypatch):
    from argparse import Namespace

    from viewer.ui.app import frame_limit

    monkeypatch.delenv("RTWALK_VIEW_FRAMES", raising=False)
    assert frame_limit(Namespace(max_frames=None)) is None
    assert frame_limit(Namespace()) is None
    assert frame_limit(Namespace(max_frames=3)) == 3
    monkeypatch.setenv("RTWALK_VIEW_FRAMES", "7")
    assert frame_limit(Namespace(max_frames=None)) == 7
    assert frame_limit(Namespace(max_frames=2)) == 2
    monkeypatch.setenv("RTWALK_VIEW_FRAMES", "x")
    with pytest.raises(RtwalkError):
        frame_limit(Namespace(max_frames=None))
    with pytest.raises(RtwalkError):
        frame_limit(Namespace(max_frames=0))


def test_render_scale_from_env(monkeypatch):
    from viewer.ui.app import DEFAULT_RENDER_SCALE, render_scale_from_env

    monkeypatch.delenv("RTWALK_VIEW_SCALE", raising=False)
    assert render_scale_from_env() == DEFAULT_RENDER_SCALE == 1.0  # progressive refinement keeps it responsive
    monkeypatch.setenv("RTWALK_VIEW_SCALE", "1")
    assert render_scale_from_env() == 1.0
    for bad in ("0.1", "2", "nan", "x"):
        monkeypatch.setenv("RTWALK_VIEW_SCALE", bad)
        with pytest.raises(RtwalkError):
            render_scale_from_env()


# --------------------------------------------------------------------------- the window


def _env(**extra) -> dict:
    """The environment of a window run: this checkout's `viewer` first (the runs start in a
    temporary folder, where an installed copy would be imported instead), no RTWALK_VIEW_*."""
    env = dict(os.environ)
    for key in ("RTWALK_VIEW_FRAMES", "RTWALK_VIEW_SCREENSHOT", "RTWALK_VIEW_SCALE", "RTWALK_VIEW_MODE"):
        env.pop(key, None)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env.update(extra)
    return env


def _xvfb(cmd: list[str], cwd: Path, env: dict, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([XVFB, "-a", "-s", "-screen 0 1280x800x24", *cmd], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


@needs_xvfb
def test_view_smoke_under_xvfb(tmp_path):
    from PIL import Image

    shot = tmp_path / "tmp.png"
    flog = tmp_path / "frames.json"
    cmd = [sys.executable, "-m", "viewer.cli", "view", "room", "--size", "320x180", "--frame-log", str(flog)]
    res = _xvfb(cmd, tmp_path, _env(RTWALK_VIEW_FRAMES="5", RTWALK_VIEW_SCREENSHOT=str(shot)))
    assert res.returncode == 0, res.stderr[-3000:]
    assert shot.is_file(), res.stderr[-3000:]
    # --frame-log: every iteration, with the window's own times, written on close
    log = json.loads(flog.read_text())
    assert [f["n"] for f in log["frames"]] == list(range(5))
    assert all(f["iteration_ms"] >= f["render_ms"] >= 0 for f in log["frames"])
    assert log["frames"][0]["gbuffer"] == "preview" and log["frames"][0]["gpu_ms"]  # the first image: moving
    assert any(f["gbuffer"] == "raster" for f in log["frames"][1:])  # then refined from the exact raster
    assert log["summary"]["frames"] == 5 and "frame log:" in res.stderr
    again = subprocess.run(cmd, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and again.stderr.count("\n") == 1 and "exists" in again.stderr
    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape == (180, 320 + PANEL_WIDTH, 3)  # the panel is beside the image
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # panel text + rendered scene, not a flat colour
    left, right = img[:, :100], img[:, 200:]
    assert left.std() > 5 and right.std() > 5
    assert not (tmp_path / "imgui.ini").exists()


@pytest.mark.parametrize("display", [None, ":4093"], ids=["unset", "unreachable"])
def test_view_without_display_fails_with_one_line(tmp_path, display):
    env = _env()
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    if display is not None:
        env["DISPLAY"] = display
    res = subprocess.run([sys.executable, "-m", "viewer.cli", "view", "room"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr  # one line, and no scene loading before it
    assert lines[0].startswith("rtwalk: error: no display")
    assert "xvfb-run" in lines[0] and "rtwalk render" in lines[0]


_DRIVER = textwrap.dedent('''
    """Drives the real window through pyglet's event handlers, frame by frame.
    (pyglet coordinates: y = 0 is the bottom row; the panel covers x < 340, the image is right of it.)"""
    import json
    import sys

    import moderngl_window  # noqa: F401  (before pyglet, so its options apply)
    import pyglet.window.key as K
    import pyglet.window.mouse as M

    from viewer import cli
    from viewer.ui import app as ui_app

    script, log = {}, {}

    def at(n):
        def deco(f):
            script.setdefault(n, []).append(f)
            return f
        return deco

    orig_frame = ui_app.ViewerApp.frame

    def frame(self, now, dt, frame_ms):
        for f in script.get(self.frames, []):
            f(self, self.wnd)
        orig_frame(self, now, dt, frame_ms)
        err = self.ctx.error
        if err != "GL_NO_ERROR":
            log.setdefault("gl_errors", []).append([self.frames, err])

    ui_app.ViewerApp.frame = frame

    def press(w, key):
        w.on_key_press(key, 0)
        w.on_key_release(key, 0)

    @at(1)
    def f1(app, w):
        log["p0"] = app.fly.position.tolist()
        w.on_key_press(K.W, 0)

    @at(4)
    def f4(app, w):
        w.on_key_release(K.W, 0)
        log["p1"] = app.fly.position.tolist()
        log["forward"] = app.camera.forward.tolist()
        log["yaw0"] = app.fly.yaw
        w.on_mouse_motion(600, 200, 0, 0)

    @at(5)
    def f5(app, w):  # drag in the scene: looks around
        w.on_mouse_press(600, 200, M.LEFT, 0)
        w.on_mouse_drag(650, 200, 50, 0, M.LEFT, 0)
        w.on_mouse_release(650, 200, M.LEFT, 0)
        w.on_mouse_motion(60, 150, 0, 0)

    @at(6)
    def f6(app, w):  # drag that starts on the panel: no camera change
        log["yaw1"] = app.fly.yaw
        w.on_mouse_press(60, 150, M.LEFT, 0)
        w.on_mouse_drag(160, 150, 100, 0, M.LEFT, 0)
        w.on_mouse_release(160, 150, M.LEFT, 0)
        w.on_mouse_motion(600, 200, 0, 0)

    @at(7)
    def f7(app, w):
        log["yaw2"] = app.fly.yaw
        press(w, K.F12)
        press(w, K.R)
        w.on_key_press(K.D, 0)

    @at(10)
    def f10(app, w):
        w.on_key_release(K.D, 0)
        log["recording"] = app.recorder.recording
        press(w, K.R)

    @at(11)
    def f11(app, w):
        log["saved"] = app.session_recording is not None and not app.recorder.recording
        press(w, K.P)

    @at(12)
    def f12(app, w):
        log["playing"] = app.playing is not None
        press(w, K.P)

    @at(13)
    def f13(app, w):
        log["stopped"] = app.playing is None
        app.switch_backend("no-such-backend")

    @at(14)
    def f14(app, w):
        log["backend"] = app.renderer.backend_name
        log["backend_error"] = app.backend_error
        app.renderer.view = "normal"
        app.render_scale = 1.0

    @at(16)
    def f16(app, w):
        log["render_size"] = list(app.renderer.size)
        w.on_key_press(K.ESCAPE, 0)

    args = cli.build_parser().parse_args(["view", "room", "--size", "400x240", "--quiet"])
    log["rc"] = ui_app.run_viewer(args)
    print("LOG " + json.dumps(log))
''')


@needs_xvfb
def test_view_keys_and_mouse_under_xvfb(tmp_path):
    """W moves, drags look (not when they start on the panel), F12/R/P save and play, Esc quits."""
    (tmp_path / "driver.py").write_text(_DRIVER)
    res = _xvfb([sys.executable, "driver.py"], tmp_path, _env())
    assert res.returncode == 0, res.stderr[-3000:]
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("LOG ")]
    assert line, res.stdout[-2000:] + res.stderr[-2000:]
    log = json.loads(line[-1][4:])
    assert log["rc"] == 0
    assert "gl_errors" not in log
    moved = np.subtract(log["p1"], log["p0"])
    assert np.linalg.norm(moved) > 0 and np.dot(moved, log["forward"]) > 0.99 * np.linalg.norm(moved)
    assert log["yaw1"] < log["yaw0"]  # dragged right in the scene: turned right
    assert log["yaw2"] == log["yaw1"]  # the drag on the panel did not move the camera
    assert log["recording"] and log["saved"] and log["playing"] and log["stopped"]
    assert log["backend"] == "glsl" and "no-such-backend" in log["backend_error"]
    assert log["render_size"] == [400, 240]
    from PIL import Image

    shots = list((tmp_path / "screenshots").glob("rtwalk-*.png"))
    assert len(shots) == 1
    assert Image.open(shots[0]).size == (400, 240)  # F12 saves the full-size render, not the 0.5 scale
    recs = list((tmp_path / "recordings").glob("room-*.json"))
    assert len(recs) == 1
    from viewer.recording import load_recording

    rec = load_recording(recs[0])
    assert rec.scene["builtin"] == "room" and len(rec.keyframes) >= 2


_OVERLAY_DRIVER = textwrap.dedent('''
    """chcrt window in the query_overdraw view: O and V keys, glsl (no overlays) and back; the
    window screenshot is taken at the last frame (query_overdraw again)."""
    import json

    import moderngl_window  # noqa: F401
    import pyglet.window.key as K

    from viewer import cli
    from viewer.ui import app as ui_app

    log = {"frames": []}
    orig_frame = ui_app.ViewerApp.frame

    def press(w, key):
        w.on_key_press(key, 0)
        w.on_key_release(key, 0)

    def frame(self, now, dt, frame_ms):
        r, n, w = self.renderer, self.frames, self.wnd
        if n == 1:
            press(w, K.O)  # overlay pass: first pass -> primary sample 0 -> ...
            press(w, K.O)
        elif n == 2:
            press(w, K.V)  # query_overdraw -> subtree_batches
        elif n == 4:
            press(w, K.V)  # -> final
        elif n == 5:
            press(w, K.V)  # -> query_overdraw
            self.switch_backend("glsl")
            press(w, K.F12)  # glsl has no such overlay: the screenshot is refused with the reason
        elif n == 6:
            self.switch_backend("chcrt")
        orig_frame(self, now, dt, frame_ms)
        src = r.overlay_source
        log["frames"].append({"view": r.view, "backend": r.backend_name, "missing": r.overlay_missing,
                              "source": None if src is None else [src[0].label, src[1]],
                              "pass": None if r.overlay_pass is None else [r.overlay_pass[0].label, r.overlay_pass[1]],
                              "phases": len(self.history.phases[-1]), "error": self.ctx.error,
                              "status": self.status})

    ui_app.ViewerApp.frame = frame
    args = cli.build_parser().parse_args(["view", "city", "--scene-size", "20000", "--backend", "chcrt",
                                          "--effects", "primary,shadows", "--size", "480x300", "--quiet"])
    log["rc"] = ui_app.run_viewer(args)
    print("LOG " + json.dumps(log))
''')


@needs_xvfb
def test_view_overlays_under_xvfb(tmp_path):
    """chcrt in the window: overlay views (RTWALK_VIEW_MODE, V), source pass (O), the panel line
    for a backend without overlays, and the legend drawn over the heat map (window screenshot)."""
    from PIL import Image

    from viewer.passes.overlay import heat_lut

    shot = tmp_path / "overlays.png"
    (tmp_path / "driver.py").write_text(_OVERLAY_DRIVER)
    res = _xvfb([sys.executable, "driver.py"], tmp_path,
                _env(RTWALK_VIEW_FRAMES="9", RTWALK_VIEW_MODE="query_overdraw", RTWALK_VIEW_SCREENSHOT=str(shot)))
    assert res.returncode == 0, res.stderr[-3000:]
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("LOG ")]
    assert line, res.stdout[-2000:] + res.stderr[-2000:]
    log = json.loads(line[-1][4:])
    fr = log["frames"]
    assert log["rc"] == 0 and len(fr) == 9
    assert all(f["error"] == "GL_NO_ERROR" for f in fr), fr
    # the cold pass's four phases, and chc:0-setup: the steady passes' programs compiled (chcrt prewarm)
    assert fr[0]["view"] == "query_overdraw" and fr[0]["source"] == ["primary", 0] and fr[0]["phases"] == 5
    assert fr[1]["pass"] == ["shadows", 0] and fr[1]["source"] == ["shadows", 0]  # O twice
    assert fr[2]["view"] == "subtree_batches" and fr[2]["source"] == ["shadows", 0]
    assert fr[4]["view"] == "final" and fr[4]["source"] is None  # nothing copied in the final view
    glsl = fr[5]  # switch_backend applies at the start of the next frame(); here: the same one
    assert glsl["backend"] == "glsl" and glsl["view"] == "query_overdraw" and glsl["source"] is None
    assert "glsl" in glsl["missing"] and glsl["phases"] == 2  # trace:primary, trace:shadows
    assert glsl["status"] == ("screenshot not saved: view 'query_overdraw': not produced by this backend; "
                              "final image shown")
    assert not (tmp_path / "screenshots").exists()
    assert fr[-1]["backend"] == "chcrt" and fr[-1]["source"] == ["shadows", 0] and not fr[-1]["missing"]

    img = np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)
    lut = heat_lut().astype(np.int32)

    def near(region, colour, tol=12):
        return (np.abs(region - colour).max(axis=2) <= tol).any()

    assert img.shape == (300, 480 + PANEL_WIDTH, 3)  # 480x300: the legend (330 px wide) fits, few pixels
    img = img[:, PANEL_WIDTH:]  # the image, right of the panel
    legend = img[190:, 140:]  # bottom right
    assert near(legend, lut[0]) and near(legend, lut[255]) and near(legend, lut[128])  # the colour bar
    assert near(legend, (210, 210, 210), 3) and near(legend, (255, 255, 255), 3)  # ticks and text
    heat = img[10:180, 15:470].reshape(-1, 3)
    exact = (heat[:, None, :] == lut[None]).all(axis=2).any(axis=1)
    no_ray = (heat == 46).all(axis=1)  # overlay.glsl's OVERLAY_NO_DATA: pixels without a shadow ray (sky)
    assert exact.mean() > 0.3 and no_ray.mean() < 0.5  # the heat map is there, not only "no ray"
    # the image is the heat map: LUT colours or no-ray grey (constant per tile; edges filtered by the blit)
    assert (exact | no_ray).mean() > 0.8


_PROGRESSIVE_DRIVER = textwrap.dedent('''
    """W held for frames 1-3 (moving), then still until converged; every imgui.text line is checked
    against the room left in the panel; at the end the window and the renderer's image are saved."""
    import json

    import moderngl_window  # noqa: F401
    import numpy as np
    import pyglet.window.key as K
    from imgui_bundle import imgui

    from viewer import cli
    from viewer.ui import app as ui_app

    log = {"steps": [], "cut": []}
    orig_text = imgui.text

    def text(s, *a):
        avail, width = imgui.get_content_region_avail().x, imgui.calc_text_size(s).x
        if width > avail + 0.5:
            log["cut"].append([s, width, avail])
        return orig_text(s, *a)

    imgui.text = text
    orig_frame = ui_app.ViewerApp.frame

    def frame(self, now, dt, frame_ms):
        n, w = self.frames, self.wnd
        if n == 1:
            w.on_key_press(K.W, 0)
        elif n == 4:
            w.on_key_release(K.W, 0)
        orig_frame(self, now, dt, frame_ms)
        st = self.step
        log["steps"].append({"moving": st.moving, "scale": st.scale, "done": st.samples_done,
                             "requested": st.samples_requested, "idle": st.report is None,
                             "size": list(self.renderer.size), "line": st.line()})
        if n == 13:  # the picture shown: the converged frame through Open Image Denoise (--denoise on)
            tex = self.denoiser.shown
            shown = np.frombuffer(tex.read(), np.uint8).reshape(tex.height, tex.width, tex.components)
            np.save("final.npy", shown[::-1, :, :3])
            np.save("raw.npy", self.renderer.read_image())
            log["method"] = self.denoiser.method

    ui_app.ViewerApp.frame = frame
    args = cli.build_parser().parse_args(["view", "room", "--size", "400x240", "--effects", "shadows,ao:4",
                                          "--frame-target-ms", "1", "--quiet"])
    log["rc"] = ui_app.run_viewer(args)
    print("LOG " + json.dumps(log))
''')


@needs_xvfb
def test_view_progressive_panel_beside_the_image(tmp_path):
    """The window refines progressively: reduced scale while W is held (the frame-time target is
    1 ms), then 4 AO passes at full size, then idle; the panel is beside the image (the window's
    image area is exactly the renderer's full-size image) and no panel text line is cut off."""
    from PIL import Image

    shot = tmp_path / "window.png"
    (tmp_path / "driver.py").write_text(_PROGRESSIVE_DRIVER)
    res = _xvfb([sys.executable, "driver.py"], tmp_path,
                _env(RTWALK_VIEW_FRAMES="14", RTWALK_VIEW_SCREENSHOT=str(shot)))
    assert res.returncode == 0, res.stderr[-3000:]
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("LOG ")]
    assert line, res.stdout[-2000:] + res.stderr[-2000:]
    log = json.loads(line[-1][4:])
    steps = log["steps"]
    assert log["rc"] == 0 and len(steps) == 14 and not log["cut"], log["cut"]
    moving = steps[1:4]  # W held (pressed before frame 1, released before frame 4): the camera moves
    assert all(s["moving"] and s["done"] == 1 and s["scale"] == MIN_SCALE for s in moving), moving
    assert all(s["size"] == list(scaled_size((400, 240), MIN_SCALE)) for s in moving)
    still = steps[4:]
    assert not any(s["moving"] for s in still)
    assert [s["done"] for s in still[:4]] == [1, 2, 3, 4] and all(s["size"] == [400, 240] for s in still)
    assert still[3]["line"] == "samples 4/4, render scale 1.00 (converged)"
    assert all(s["idle"] for s in still[4:])  # converged: nothing more is rendered
    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape == (240, 400 + PANEL_WIDTH, 3)
    final = np.load(tmp_path / "final.npy")
    np.testing.assert_array_equal(img[:, PANEL_WIDTH:], final)  # the whole image, nothing under the panel
    from viewer.denoise import library_missing

    assert log["method"] == ("library" if library_missing() is None else "device")
    assert (final != np.load(tmp_path / "raw.npy")).any()  # denoised: not the raw frame


# --------------------------------------------------------------------------- issue 23: the panel fits


def test_fps_line_is_the_last_rendered_frame_or_idle():
    from types import SimpleNamespace

    from viewer.ui.panel import fps_line

    hist = FrameHistory()
    for ms in (100.0, 300.0, 1900.0):
        hist.add(ms, ms)
    assert "1.9 s" not in fps_line(SimpleNamespace(history=hist, last_frame_ms=1900.0, idle=False))
    assert fps_line(SimpleNamespace(history=hist, last_frame_ms=1900.0, idle=False)).split()[0] == "0.5"
    idle = fps_line(SimpleNamespace(history=hist, last_frame_ms=1900.0, idle=True))
    assert idle.startswith("idle") and "fps" not in idle and "1,900 ms" in idle
    assert fps_line(SimpleNamespace(history=FrameHistory(), last_frame_ms=0.0, idle=False)) == "- fps"


def test_top_phases_fold_the_rest():
    from viewer.ui.panel import TOP_PHASES, top_phases

    few = {"gbuffer": 3.0, "shade": 1.0}
    assert top_phases(few) == list(few.items())
    many = {f"p{i}": float(i) for i in range(12)}
    rows = top_phases(many)
    assert len(rows) == TOP_PHASES + 1 and rows[-1][0] == f"other ({12 - TOP_PHASES} phases)"
    assert sum(v for _, v in rows) == pytest.approx(sum(many.values()))
    assert [k for k, _ in rows[:-1]] == [f"p{i}" for i in range(12 - TOP_PHASES, 12)]  # costliest, in order


@pytest.mark.parametrize("backend", ["glsl", "pgrid"])
def test_panel_fits_a_504_px_window(gl_ctx, backend, monkeypatch):
    """The panel as it opens (sections folded but the timings) holds in the 504-px window with
    this backend's phases and counters: nothing to scroll to, nothing below the edge."""
    from imgui_bundle import imgui

    from tests.conftest import opencl_missing, prepared_scene
    from tests.view_helpers import draw_views

    if backend == "pgrid" and opencl_missing():
        pytest.skip(opencl_missing())
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer
    from viewer.ui import panel

    room = prepared_scene("room")
    cam = room.scene.default_camera
    r = Renderer(gl_ctx, room.scene, room.bvh, (64, 36), backend, parse_effects("shadows,ao:2,reflections"))
    seen = []
    real_end = imgui.end

    def end():
        if imgui.get_window_size().x == 340:  # the panel window (not implot's)
            seen.append((imgui.get_cursor_pos_y(), imgui.get_scroll_max_y(), imgui.get_window_size().y))
        real_end()

    monkeypatch.setattr(imgui, "end", end)
    real_draw = panel.draw_panel
    monkeypatch.setattr(panel, "draw_panel", lambda host, w, h: real_draw(host, w, 504))
    try:
        draw_views(r, cam, ("final", "final", "final"))  # the scroll range settles after a frame
    finally:
        r.release()
    bottom, scroll_max, height = seen[-1]
    assert height == 504 and scroll_max == 0 and bottom <= 504, seen


def test_window_screenshot_and_frame_log_are_not_replaced(tmp_path, monkeypatch):
    """RTWALK_VIEW_SCREENSHOT naming an existing file (a second run of the same command) replaced
    it silently: refused in one line before the window opens, as render -o is, unless view --force;
    --frame-log the same way. (An unreachable display stops the forced run right after the checks.)"""
    from tests.cli_runner import run_cli

    shot, flog = tmp_path / "s.png", tmp_path / "f.json"
    shot.write_bytes(b"earlier")
    monkeypatch.setenv("RTWALK_VIEW_SCREENSHOT", str(shot))
    monkeypatch.setenv("DISPLAY", ":4093")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    res = run_cli("view", "room")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "RTWALK_VIEW_SCREENSHOT" in res.stderr and "exists" in res.stderr and "--force" in res.stderr
    forced = run_cli("view", "room", "--force")
    assert forced.returncode == 2 and "no display" in forced.stderr, forced.stderr
    monkeypatch.delenv("RTWALK_VIEW_SCREENSHOT")
    flog.write_text("{}")
    res = run_cli("view", "room", "--frame-log", str(flog))
    assert res.returncode == 2 and "--frame-log" in res.stderr and "--force" in res.stderr, res.stderr
    assert "no display" in run_cli("view", "room", "--frame-log", str(flog), "--force").stderr
    assert shot.read_bytes() == b"earlier" and flog.read_text() == "{}"
    monkeypatch.setenv("RTWALK_VIEW_SCREENSHOT", str(shot))  # the windowed main job has no --force of its own
    res = run_cli("room")
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "`rtwalk view --force`" in res.stderr, res.stderr


def test_f12_screenshot_names_are_new(tmp_path):
    """F12 saves into screenshots/ under a name no file had: created exclusively (stem, stem-1, ...)."""
    from viewer.ui.app import _new_file

    (tmp_path / "a.png").write_bytes(b"x")
    (tmp_path / "a-1.png").write_bytes(b"y")
    assert _new_file(tmp_path, "a", ".png") == tmp_path / "a-2.png"
    assert _new_file(tmp_path, "a", ".png") == tmp_path / "a-3.png"
    assert (tmp_path / "a.png").read_bytes() == b"x" and (tmp_path / "a-1.png").read_bytes() == b"y"


def test_fit_to_screen_keeps_the_aspect_ratio():
    from viewer.ui.app import fit_to_screen

    assert fit_to_screen((896, 504), (1400, 900)) == (896, 504)  # fits: unchanged
    assert fit_to_screen((896, 504), None) == (896, 504)  # no screen size known: the driver decides
    assert fit_to_screen((10000, 10000), (1400, 900)) == (900, 900)
    room = 1280 - PANEL_WIDTH
    assert fit_to_screen((2000, 1000), (1280, 800), panel=PANEL_WIDTH) == (room, room // 2)


@needs_xvfb
def test_view_size_larger_than_the_display_is_fitted(tmp_path):
    """`view --size 10000x10000` under a 1400x900 virtual display was accepted and took minutes per
    frame: the window is fitted to the display (aspect kept) with one warning line."""
    from PIL import Image

    shot = tmp_path / "big.png"
    cmd = [sys.executable, "-m", "viewer.cli", "view", "room", "--size", "2000x1000", "--quiet"]
    res = _xvfb(cmd, tmp_path, _env(RTWALK_VIEW_FRAMES="1", RTWALK_VIEW_SCREENSHOT=str(shot)))
    assert res.returncode == 0, res.stderr[-3000:]
    warnings = [ln for ln in res.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "1280x800 display" in warnings[0] and "940x470" in warnings[0], res.stderr
    assert Image.open(shot).size == (1280, 470)

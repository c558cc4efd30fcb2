"""Progressive refinement (viewer.progressive): one pass per effect while moving, at a reduced
scale when over the frame-time target; when the camera stops, passes are added until the
requested counts, and the converged image is the full-quality frame (a separate renderer)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from viewer.camera import Camera
from viewer.effects import parse_effects
from viewer.progressive import MIN_SCALE, Progressive, scaled_size
from viewer.renderer import Renderer

SIZE = (96, 54)
EFFECTS = "primary,shadows,soft:3,ao:4"


@pytest.fixture(scope="module")
def room():
    return prepared_scene("room")


def _cams():
    return (Camera.look_at([-1.5, 1.2, 2.0], [0.5, 0.8, -1.0]), Camera.look_at([1.0, 1.4, 2.2], [-0.5, 0.6, -1.0]))


def _full_image(gl_ctx, room, cam) -> np.ndarray:
    r = Renderer(gl_ctx, room.scene, room.bvh, SIZE, "glsl", parse_effects(EFFECTS))
    try:
        r.render(cam)
        return r.read_image().astype(np.int16)
    finally:
        r.release()


@pytest.mark.parametrize("target_ms", [1e6, 1e-3], ids=["full-scale", "reduced-scale"])
def test_converges_to_the_full_quality_frame(gl_ctx, room, target_ms):
    a, b = _cams()
    full = _full_image(gl_ctx, room, b)
    r = Renderer(gl_ctx, room.scene, room.bvh, SIZE, "glsl", parse_effects(EFFECTS))
    try:
        prog = Progressive(r, SIZE, target_ms=target_ms)
        s1 = prog.frame(a)
        s2 = prog.frame(b)  # moved
        assert s1.moving and s2.moving and s2.samples_done == 1 and s2.samples_requested == 4
        # one pass per effect while moving: 1 shadow pass per light, 1 soft pass per rect light, 1 AO pass
        assert s2.report.rays["ao"] > 0 and s2.report.rays["soft"] > 0
        if target_ms < 1:  # over the target: the moving image is smaller (upscaled when shown)
            assert s2.scale == pytest.approx(MIN_SCALE) and tuple(r.size) == scaled_size(SIZE, MIN_SCALE)
        else:
            assert s2.scale == 1.0 and tuple(r.size) == SIZE
        steps = []
        for _ in range(10):
            st = prog.frame(b)  # stopped
            steps.append(st)
            if st.report is None:
                break
        assert steps[-1].report is None and steps[-1].converged  # idle once converged
        assert tuple(r.size) == SIZE
        assert [s.samples_done for s in steps[:-1]][-1] == 4
        first_static = steps[0]
        assert not first_static.moving
        img = r.read_image().astype(np.int16)
        assert np.abs(img - full).mean() <= 1.0  # <= 1/255 mean
    finally:
        r.release()


def test_partial_images_are_complete_estimates(gl_ctx, room):
    """After 1 of 4 AO passes the image is as bright as the full one on average (scaled by
    requested / done), not a quarter of the AO term."""
    _, b = _cams()
    full = _full_image(gl_ctx, room, b)
    r = Renderer(gl_ctx, room.scene, room.bvh, SIZE, "glsl", parse_effects(EFFECTS))
    try:
        prog = Progressive(r, SIZE, target_ms=1e6)
        prog.frame(b)
        partial = r.read_image().astype(np.int16)
        assert np.abs(partial - full).mean() > 0.2  # noisier: fewer samples
        assert abs(partial.mean() - full.mean()) < 2.0
    finally:
        r.release()


def test_settings_change_restarts(gl_ctx, room):
    _, b = _cams()
    r = Renderer(gl_ctx, room.scene, room.bvh, SIZE, "glsl", parse_effects(EFFECTS))
    try:
        prog = Progressive(r, SIZE, target_ms=1e6)
        for _ in range(6):
            prog.frame(b)
        assert prog.frame(b).report is None
        r.settings = parse_effects("shadows,ao:2")
        st = prog.frame(b)
        assert st.report is not None and st.samples_requested == 2 and st.samples_done == 1
    finally:
        r.release()


def test_bench_progressive_report(tmp_path):
    """`rtwalk bench --progressive`: moving frame times (median, p95), time to convergence, and the
    converged image equal to the full-quality frame."""
    import json
    import subprocess
    import sys

    from viewer.recording import Keyframe, Recording, save_recording

    a, b = _cams()
    keys = [Keyframe.from_camera(0.0, a), Keyframe.from_camera(1.0, b)]
    path = save_recording(Recording({"builtin": "room"}, (64, 36), 6.0, keys), tmp_path / "room-path.json")
    proc = subprocess.run([sys.executable, "-m", "viewer.cli", "bench", "--recording", str(path), "--progressive",
                           "--effects", "primary,shadows,ao:3", "--size", "64x36", "--out", str(tmp_path / "out"),
                           "--name", "p", "--frame-target-ms", "1000"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "progressive: 7 moving frames" in proc.stderr, proc.stderr
    rep = json.loads((tmp_path / "out" / "p-progressive.json").read_text())
    assert rep["frames"] == 7 and len(rep["moving_ms"]["all"]) == 7
    assert rep["moving_ms"]["median"] <= rep["moving_ms"]["p95"] <= rep["moving_ms"]["max"]
    assert rep["converge"]["frames"] == 3 and rep["converge"]["seconds"] > 0  # samples 0..2 at full size
    assert rep["scale"]["max"] == 1.0 and rep["converged_vs_full_mae"] <= 1.0


def test_moving_frames_pick_the_cheaper_gbuffer_source(gl_ctx, room):
    """Each G-buffer source is measured on a moving frame; then the cheaper one (the traced one's
    time scaled by the pixels) is used, the other tried again every PROBE_EVERY moving frames; still
    frames always use the exact raster."""
    from viewer.progressive import GBUFFER_SOURCES, PROBE_EVERY

    a, b = _cams()
    r = Renderer(gl_ctx, room.scene, room.bvh, SIZE, "glsl", parse_effects(EFFECTS))
    try:
        prog = Progressive(r, SIZE, target_ms=1e6)
        prog.frame(a)
        prog.frame(b)
        assert set(prog._source_cost) == set(GBUFFER_SOURCES) and r.gbuffer_source == "raster"
        prog._source_cost = {"preview": (50.0, 100), "trace": (40.0, 100)}
        picks = [prog._pick_source(200) for _ in range(PROBE_EVERY)]  # trace: 80 ms at 200 px
        assert picks[:-1] == ["preview"] * (PROBE_EVERY - 1) and picks[-1] == "trace"
        assert prog._pick_source(100) == "trace"  # 40 ms < 50 ms
    finally:
        r.release()


def _accumulators(r: Renderer) -> dict:
    return {k: np.frombuffer(t.read(), np.float32).copy() for k, t in r.accumulate.textures.items()}


@pytest.mark.parametrize("backend", ["glsl", "clbvh"])
def test_stepped_still_frame_is_the_one_call_frame(gl_ctx, room, backend, monkeypatch):
    """`rtwalk render` renders a large still frame in steps of sample passes (for its progress bar):
    the same passes, weights and sums in the same order, so the same accumulators bit for bit (two
    area lights share the soft accumulator: their passes are sample-major), the same image and rays;
    small frames stay one call."""
    from dataclasses import replace

    import viewer.progressive as progressive

    _, cam = _cams()
    light = room.scene.rect_lights[0]
    second = replace(light, corner=light.corner + np.float32(0.5) * light.edge_u,
                     radiance=light.radiance * np.float32(0.7))
    scene = replace(room.scene, rect_lights=[light, second])
    effects = parse_effects("primary,shadows,soft:5,ao:5,diffuse:4,reflections")
    r = Renderer(gl_ctx, scene, room.bvh, SIZE, backend, effects)
    try:
        one = r.render(cam)
        whole, sums = r.read_image().copy(), _accumulators(r)
        calls: list[tuple[int, int]] = []
        progressive.render_stepped(r, cam, lambda done, steps: calls.append((done, steps)))
        assert calls == [(1, 1)]  # under STEPPED_MIN_RAYS: one call
        monkeypatch.setattr(progressive, "STEPPED_MIN_RAYS", 1)
        monkeypatch.setattr(progressive, "MIN_SAMPLES_PER_STEP", 2)
        calls.clear()
        _, rays = progressive.render_stepped(r, cam, lambda done, steps: calls.append((done, steps)))
        assert calls == [(1, 3), (2, 3), (3, 3)]  # sample 0, then samples 1-4 in two steps
        assert rays == one.rays
        stepped = _accumulators(r)
        assert sums.keys() == stepped.keys()
        assert all(np.array_equal(sums[k], stepped[k]) for k in sums)
        assert np.array_equal(r.read_image(), whole)
    finally:
        r.release()

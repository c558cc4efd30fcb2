"""Recordings: interpolation against formulas written here, deterministic sampling, shipped paths,
and one-line errors for malformed files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from viewer.camera import Camera, quat_to_matrix
from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS, SHARED_SCENES
from viewer.recording import Keyframe, Recording, load_recording, resolve_scene_spec, save_recording


def _rec(times, positions, yaw_deg):
    keys = []
    for t, p, y in zip(times, positions, yaw_deg, strict=True):
        a = np.radians(y) / 2
        keys.append(Keyframe(t, p, [np.cos(a), 0.0, np.sin(a), 0.0], 60.0))
    return Recording({"builtin": "room"}, (64, 36), 10.0, keys)


def test_catmull_rom_hits_keyframes_and_matches_formula():
    pts = [np.array(p, float) for p in ([0, 0, 0], [1, 2, 0], [3, 2, 1], [4, 0, 2])]
    rec = _rec([0.0, 1.0, 2.0, 3.0], pts, [0, 0, 0, 0])
    for i, p in enumerate(pts):
        np.testing.assert_allclose(rec.camera_at(float(i)).position, p, atol=1e-12)
    u = 0.3  # segment 1 -> 2, uniform Catmull-Rom written out independently
    p0, p1, p2, p3 = pts
    expect = 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                    + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)
    np.testing.assert_allclose(rec.camera_at(1.3).position, expect, atol=1e-9)


def test_slerp_midpoint_of_90_degrees_is_45():
    rec = _rec([0.0, 2.0], [np.zeros(3), np.zeros(3)], [0, 90])
    m = quat_to_matrix(rec.camera_at(1.0).orientation)
    fwd = -m[:, 2]
    np.testing.assert_allclose(fwd, [-np.sin(np.radians(45)), 0, -np.cos(np.radians(45))], atol=1e-9)


def test_frames_are_sampled_at_fixed_rate():
    rec = _rec([0.0, 1.0], [np.zeros(3), np.ones(3)], [0, 0])
    np.testing.assert_array_equal(rec.frame_times(4.0), [0.0, 0.25, 0.5, 0.75, 1.0])
    assert rec.frame_count() == 11


def test_round_trip(tmp_path):
    rec = _rec([0.0, 1.5], [np.zeros(3), np.array([1.0, 2.0, 3.0])], [10, 20])
    back = load_recording(save_recording(rec, tmp_path / "r.json"))
    for t in (0.0, 0.7, 1.5):
        np.testing.assert_allclose(back.camera_at(t).position, rec.camera_at(t).position)


@pytest.mark.parametrize("name", ["city-near", "city-far", "sponza-walk", "sibenik-walk", "conference-walk"])
def test_shipped_recordings_load(name):
    rec = load_recording(RECORDINGS / f"{name}.json")
    assert rec.duration >= 8 and rec.frame_count() > 100
    spec = resolve_scene_spec(rec)
    if "file" in rec.scene and SHARED_SCENES.exists():
        assert (SHARED_SCENES / rec.scene["file"]).exists() and spec.spec.endswith(rec.scene["file"].split("/")[-1])


GOOD = {"format": "rtwalk-recording", "version": 1, "scene": {"builtin": "city"}, "resolution": [64, 36],
        "fps": 30, "keyframes": [{"time": 0, "position": [0, 1, 0], "orientation": [1, 0, 0, 0], "fov_y": 60},
                                 {"time": 1, "position": [0, 1, 1], "orientation": [1, 0, 0, 0], "fov_y": 60}]}


def _bad(**change):
    d = json.loads(json.dumps(GOOD))
    for k, v in change.items():
        if k == "key1":
            d["keyframes"][1].update(v)
        else:
            d[k] = v
    return json.dumps(d)


@pytest.mark.parametrize("text", [
    "{truncated", "[]", _bad(format="other"), _bad(version=7), _bad(keyframes=[]), _bad(resolution=[0, 5]),
    _bad(key1={"time": 0}), _bad(key1={"position": [0, "nan", 0]}), _bad(key1={"orientation": [0, 0, 0, 0]}),
    _bad(key1={"fov_y": 200}), _bad(fps=-1),
])
def test_malformed_recordings_fail_with_one_line(tmp_path, text):
    p = tmp_path / "broken.json"
    p.write_text(text.replace('"nan"', "NaN"))
    with pytest.raises(RtwalkError) as exc:
        load_recording(p)
    msg = str(exc.value)
    assert "broken.json" in msg and "\n" not in msg


def test_missing_recording(tmp_path):
    with pytest.raises(RtwalkError, match="gone.json"):
        load_recording(tmp_path / "gone.json")


def test_camera_roundtrip_through_keyframe():
    cam = Camera.look_at([1, 2, 3], [0, 0, 0], fov_y=45)
    back = Keyframe.from_camera(0.0, cam).camera()
    np.testing.assert_allclose(back.forward, cam.forward, atol=1e-12)

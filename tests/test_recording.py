"""viewer.recording: spline/slerp maths checked against formulas written here, fixed-rate frame
sampling, the shipped camera paths, one-line errors for every kind of malformed file, and the
interactive Recorder's save/load round trip."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from viewer.camera import Camera, quat_to_matrix
from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS, SHARED_SCENES
from viewer.recording import (
    Keyframe,
    Recorder,
    Recording,
    load_recording,
    resolve_scene_spec,
    save_recording,
)

# Bounding boxes from ../shared/scenes/README.md (min, max), used without loading the meshes.
SCENE_BOUNDS = {
    "sponza-dabrovic/sponza.obj": ((-17.403, -0.907, -7.799), (17.417, 15.653, 7.802)),
    "sibenik/sibenik.obj": ((-20.141, -15.312, -8.497), (20.141, 15.300, 8.497)),
    "conference/conference.ply": ((-1020.13, -2.792, -1055.66), (1685.81, 650.293, 668.489)),
}
SHIPPED = ["city-near", "city-far", "sponza-walk", "sibenik-walk", "conference-walk"]


def yaw_q(deg: float) -> np.ndarray:
    """Rotation about +Y by `deg` degrees as (w, x, y, z)."""
    a = math.radians(deg) / 2
    return np.array([math.cos(a), 0.0, math.sin(a), 0.0])


def make_rec(times, positions, yaws=None, fovs=None, fps=10.0) -> Recording:
    n = len(times)
    yaws = [0.0] * n if yaws is None else yaws
    fovs = [60.0] * n if fovs is None else fovs
    keys = [Keyframe(t, p, yaw_q(y), f) for t, p, y, f in zip(times, positions, yaws, fovs, strict=True)]
    return Recording({"builtin": "room"}, (64, 36), fps, keys)


def catmull_rom_reference(p0, p1, p2, p3, u):
    """Uniform Catmull-Rom in matrix form: 0.5 * [u^3 u^2 u 1] M [p0 p1 p2 p3]^T."""
    m = np.array([[-1, 3, -3, 1], [2, -5, 4, -1], [-1, 0, 1, 0], [0, 2, 0, 0]], float)
    return 0.5 * np.array([u ** 3, u ** 2, u, 1.0]) @ m @ np.array([p0, p1, p2, p3], float)


def rotation_angle_deg(qa, qb) -> float:
    d = abs(float(np.dot(qa, qb))) / (np.linalg.norm(qa) * np.linalg.norm(qb))
    return math.degrees(2 * math.acos(min(1.0, d)))


PTS = [np.array(p, float) for p in ([0, 0, 0], [2, 1, 0], [3, 3, 1], [5, 3, 4], [6, 0, 4])]
TIMES = [0.5, 1.5, 2.0, 3.25, 4.0]  # non-uniform, first not zero


# --------------------------------------------------------------------------- interpolation


def test_spline_passes_through_keyframes_exactly():
    rec = make_rec(TIMES, PTS)
    for t, p in zip(TIMES, PTS, strict=True):
        np.testing.assert_array_equal(rec.camera_at(t).position, p)


def test_spline_matches_hand_written_catmull_rom():
    rec = make_rec(TIMES, PTS)
    for seg in range(len(PTS) - 1):
        t0, t1 = TIMES[seg], TIMES[seg + 1]
        p0 = PTS[seg - 1] if seg > 0 else PTS[0]  # end keyframes duplicated
        p3 = PTS[seg + 2] if seg + 2 < len(PTS) else PTS[-1]
        for u in (0.25, 0.5, 0.8):
            expect = catmull_rom_reference(p0, PTS[seg], PTS[seg + 1], p3, u)
            np.testing.assert_allclose(rec.camera_at(t0 + u * (t1 - t0)).position, expect, atol=1e-12)
    # a value worked out by hand: middle of segment 1 -> 2 of (0,0,0),(2,1,0),(3,3,1),(5,3,4)
    # at u = 1/2 uniform Catmull-Rom is (-p0 + 9 p1 + 9 p2 - p3) / 16 = (40, 33, 5) / 16
    np.testing.assert_allclose(rec.camera_at(1.75).position, [2.5, 2.0625, 0.3125], atol=1e-12)


def test_time_is_clamped_and_fov_is_linear():
    rec = make_rec([0.0, 2.0], [np.zeros(3), np.ones(3)], fovs=[40.0, 80.0])
    np.testing.assert_array_equal(rec.camera_at(-5.0).position, np.zeros(3))
    np.testing.assert_array_equal(rec.camera_at(99.0).position, np.ones(3))
    assert rec.camera_at(0.5).fov_y == pytest.approx(50.0)
    assert rec.camera_at(99.0).fov_y == 80.0
    with pytest.raises(RtwalkError):
        rec.camera_at(float("nan"))


def test_slerp_unit_length_and_half_of_90_degrees_is_45():
    rec = make_rec([0.0, 1.0], [np.zeros(3), np.zeros(3)], yaws=[0.0, 90.0])
    for t in np.linspace(0, 1, 17):
        assert np.linalg.norm(rec.camera_at(t).orientation) == pytest.approx(1.0, abs=1e-12)
    q = rec.camera_at(0.5).orientation
    q = q if q[0] >= 0 else -q
    np.testing.assert_allclose(q, yaw_q(45.0), atol=1e-12)
    fwd = -quat_to_matrix(q)[:, 2]  # camera looks down -Z; 45 deg about +Y turns it towards -X
    np.testing.assert_allclose(fwd, [-math.sqrt(0.5), 0.0, -math.sqrt(0.5)], atol=1e-12)
    for t in np.linspace(0, 1, 9):  # constant angular speed
        angle = rotation_angle_deg(rec.camera_at(t).orientation, yaw_q(0.0))
        assert angle == pytest.approx(90.0 * t, abs=1e-9)


def test_slerp_takes_the_shortest_arc():
    # q and -q are the same rotation: a keyframe written as -q must not make the camera spin round
    keys = [Keyframe(0.0, np.zeros(3), yaw_q(10.0), 60.0), Keyframe(1.0, np.zeros(3), -yaw_q(70.0), 60.0)]
    rec = Recording({"builtin": "room"}, (64, 36), 10.0, keys)
    mid = rec.camera_at(0.5).orientation
    assert rotation_angle_deg(mid, yaw_q(40.0)) == pytest.approx(0.0, abs=1e-6)
    # and 350 deg apart the short way round is 10 deg, through 355 deg
    rec = make_rec([0.0, 1.0], [np.zeros(3)] * 2, yaws=[0.0, 350.0])
    assert rotation_angle_deg(rec.camera_at(0.5).orientation, yaw_q(-5.0)) == pytest.approx(0.0, abs=1e-6)


# --------------------------------------------------------------------------- sampling


def test_frame_sampling_is_exact_and_deterministic():
    rec = make_rec([1.0, 3.5], [np.zeros(3), np.ones(3)], fps=4.0)
    assert rec.duration == 2.5
    assert rec.frame_count() == 11  # floor(2.5 * 4) + 1
    expect = 1.0 + np.arange(11) / 4.0
    np.testing.assert_array_equal(rec.frame_times(), expect)
    np.testing.assert_array_equal(rec.frame_times(), rec.frame_times())
    assert rec.frame_count(30) == 76  # floor(2.5 * 30) + 1
    np.testing.assert_array_equal(rec.frame_times(30), 1.0 + np.arange(76) / 30.0)
    for n in (0, 5, 10):
        a, b = rec.camera_for_frame(n), rec.camera_at(expect[n])
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.orientation, b.orientation)
    for bad in (-1, 11, 100):
        with pytest.raises(RtwalkError, match="frame"):
            rec.camera_for_frame(bad)


def test_frame_count_absorbs_float_rounding():
    rec = make_rec([0.0, 0.3], [np.zeros(3), np.ones(3)])  # 0.3 * 10 = 2.9999999999999996
    assert rec.frame_count(10) == 4


def test_single_keyframe_is_a_still():
    rec = make_rec([2.0], [np.array([1.0, 2.0, 3.0])])
    assert rec.duration == 0.0 and rec.frame_count() == 1
    np.testing.assert_array_equal(rec.camera_for_frame(0).position, [1, 2, 3])
    np.testing.assert_array_equal(rec.camera_at(10.0).position, [1, 2, 3])


# --------------------------------------------------------------------------- shipped recordings


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_recording_is_a_smooth_path_in_its_scene(name):
    path = RECORDINGS / f"{name}.json"
    rec = load_recording(path)
    assert rec.resolution == (1280, 720) and rec.fps == 30
    assert 8.0 <= rec.duration <= 15.0 and 8 <= len(rec.keyframes) <= 12
    pos = np.array([rec.camera_at(t).position for t in rec.frame_times()])
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert steps.max() < 0.1 * np.ptp(pos, axis=0).max()  # no jumps between frames
    spec = resolve_scene_spec(rec, path)
    if "builtin" in rec.scene:
        assert spec.spec == "city" and spec.size == rec.scene["size"] and spec.seed == rec.scene["seed"]
        return
    lo, hi = SCENE_BOUNDS[rec.scene["file"]]
    assert np.all(pos > lo) and np.all(pos < hi), "camera leaves the scene's bounding box"
    if not SHARED_SCENES.exists():
        pytest.skip(f"{SHARED_SCENES} not present")
    assert Path(spec.spec).is_file() and Path(spec.spec) == (SHARED_SCENES / rec.scene["file"]).resolve()


def test_every_file_in_recordings_loads():
    files = sorted(RECORDINGS.glob("*.json"))
    assert {f.stem for f in files} >= set(SHIPPED)
    for f in files:
        load_recording(f)


def test_resolve_scene_spec_search_order(tmp_path):
    rec = load_recording(RECORDINGS / "sponza-walk.json")
    # 1) next to the recording wins
    local = tmp_path / "sponza-dabrovic" / "sponza.obj"
    local.parent.mkdir()
    local.write_text("# stub\n")
    assert resolve_scene_spec(rec, tmp_path / "r.json").spec == str(local.resolve())
    # 2) ../shared/scenes, 3) as given when found nowhere
    elsewhere = tmp_path / "sub" / "r.json"
    expect = SHARED_SCENES / "sponza-dabrovic" / "sponza.obj"
    got = resolve_scene_spec(rec, elsewhere).spec
    assert got == (str(expect.resolve()) if expect.exists() else "sponza-dabrovic/sponza.obj")
    rec.scene = {"file": "no/such/scene.obj"}
    assert resolve_scene_spec(rec, elsewhere).spec == "no/such/scene.obj"
    rec.scene = {"builtin": "city"}
    assert tuple(resolve_scene_spec(rec, elsewhere)) == ("city", None, None)


# --------------------------------------------------------------------------- malformed files

GOOD = {"format": "rtwalk-recording", "version": 1, "scene": {"builtin": "city", "size": 1000, "seed": 2},
        "resolution": [64, 36], "fps": 30,
        "keyframes": [{"time": 0.0, "position": [0, 1, 0], "orientation": [1, 0, 0, 0], "fov_y": 60},
                      {"time": 1.0, "position": [0, 1, 1], "orientation": [1, 0, 0, 0], "fov_y": 60},
                      {"time": 2.0, "position": [1, 1, 1], "orientation": [1, 0, 0, 0], "fov_y": 60}]}


def variant(top=None, key=None, drop=None, drop_key=None) -> str:
    d = json.loads(json.dumps(GOOD))
    d.update(top or {})
    if key:
        d["keyframes"][2].update(key)
    if drop:
        del d[drop]
    if drop_key:
        del d["keyframes"][1][drop_key]
    return json.dumps(d)


GOOD_TEXT = json.dumps(GOOD)
MALFORMED = {
    "invalid-json": "{format: rtwalk}",
    "truncated": GOOD_TEXT[: len(GOOD_TEXT) // 2],
    "empty": "",
    "top-level-list": "[1, 2]",
    "wrong-format": variant({"format": "blender-path"}),
    "no-format": variant(drop="format"),
    "future-version": variant({"version": 3}),
    "scene-time-partial": variant({"version": 2}, key={"scene_time": 1.0}),
    "scene-time-nan": variant({"version": 2, "keyframes": [dict(k, scene_time="NAN") for k in GOOD["keyframes"]]})
    .replace('"NAN"', "NaN"),
    "scene-time-string": variant({"version": 2, "keyframes": [dict(k, scene_time="x") for k in GOOD["keyframes"]]}),
    "version-string": variant({"version": "1"}),
    "missing-keyframes": variant(drop="keyframes"),
    "empty-keyframes": variant({"keyframes": []}),
    "keyframes-not-list": variant({"keyframes": {"time": 0}}),
    "missing-scene": variant(drop="scene"),
    "scene-both": variant({"scene": {"builtin": "city", "file": "x.obj"}}),
    "scene-size-negative": variant({"scene": {"builtin": "city", "size": -5}}),
    "missing-time": variant(drop_key="time"),
    "missing-orientation": variant(drop_key="orientation"),
    "nan-position": variant(key={"position": [0, "NAN", 0]}).replace('"NAN"', "NaN"),
    "inf-position": variant(key={"position": [0, "INF", 0]}).replace('"INF"', "Infinity"),
    "huge-position": variant(key={"position": [0, "BIG", 0]}).replace('"BIG"', "1e999"),
    "short-position": variant(key={"position": [0, 1]}),
    "string-position": variant(key={"position": "0,1,0"}),
    "equal-time": variant(key={"time": 1.0}),
    "decreasing-time": variant(key={"time": 0.5}),
    "nan-time": variant(key={"time": "NAN"}).replace('"NAN"', "NaN"),
    "zero-quaternion": variant(key={"orientation": [0, 0, 0, 0]}),
    "bool-in-quaternion": variant(key={"orientation": [True, 0, 0, 0]}),
    "fov-zero": variant(key={"fov_y": 0}),
    "fov-179": variant(key={"fov_y": 179}),
    "fov-200": variant(key={"fov_y": 200}),
    "fov-string": variant(key={"fov_y": "wide"}),
    "resolution-zero": variant({"resolution": [0, 720]}),
    "resolution-one": variant({"resolution": [1280]}),
    "resolution-float": variant({"resolution": [1280.5, 720]}),
    "resolution-string": variant({"resolution": "1280x720"}),
    "resolution-huge": variant({"resolution": [100000, 720]}),
    "fps-negative": variant({"fps": -30}),
    "fps-zero": variant({"fps": 0}),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_file_gives_one_line_error_naming_the_file(tmp_path, case):
    path = tmp_path / f"bad-{case}.json"
    path.write_text(MALFORMED[case], encoding="utf-8")
    with pytest.raises(RtwalkError) as exc:
        load_recording(path)
    msg = str(exc.value)
    assert f"bad-{case}.json" in msg and "\n" not in msg and "\r" not in msg, msg
    assert exc.value.__cause__ is None or isinstance(exc.value.__cause__, RtwalkError), msg


def test_error_names_the_keyframe(tmp_path):
    path = tmp_path / "x.json"
    path.write_text(variant(key={"time": 1.0}))
    with pytest.raises(RtwalkError, match=r"x\.json: keyframe 2: time must increase"):
        load_recording(path)


def test_missing_file_non_utf8_and_directory(tmp_path):
    with pytest.raises(RtwalkError, match=r"gone\.json.*not found"):
        load_recording(tmp_path / "gone.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00garbage\x81")
    with pytest.raises(RtwalkError, match=r"bin\.json"):
        load_recording(tmp_path / "bin.json")
    (tmp_path / "adir.json").mkdir()
    with pytest.raises(RtwalkError, match=r"adir\.json"):
        load_recording(tmp_path / "adir.json")


def test_good_variant_loads_and_normalises(tmp_path):
    d = json.loads(GOOD_TEXT)
    d["keyframes"][0]["orientation"] = [2, 0, 0, 0]
    d["unknown_future_key"] = {"ignored": True}
    path = tmp_path / "ok.json"
    path.write_text(json.dumps(d))
    rec = load_recording(path)
    np.testing.assert_array_equal(rec.keyframes[0].orientation, [1, 0, 0, 0])
    assert rec.scene == {"builtin": "city", "size": 1000, "seed": 2} and rec.source == path


def test_save_refuses_an_invalid_recording(tmp_path):
    rec = make_rec([0.0, 1.0], [np.zeros(3), np.ones(3)], fovs=[60.0, 0.5])
    with pytest.raises(RtwalkError, match="out.json"):
        save_recording(rec, tmp_path / "out.json")
    assert not (tmp_path / "out.json").exists()


def test_save_load_round_trip_is_exact(tmp_path):
    rec = make_rec(TIMES, PTS, yaws=[0, 30, 60, 100, 170], fovs=[60, 55, 50, 45, 70])
    back = load_recording(save_recording(rec, tmp_path / "deep" / "r.json"))
    assert back == rec
    for t in np.linspace(0.5, 4.0, 15):
        np.testing.assert_array_equal(back.camera_at(t).position, rec.camera_at(t).position)


# --------------------------------------------------------------------------- recorder


def test_recorder_thins_and_round_trips(tmp_path):
    r = Recorder()
    r.start({"builtin": "city", "size": 150_000, "seed": 1}, (320, 180), fps=24)
    cams = {}
    for i, t in enumerate([100.0, 100.03, 100.06, 100.2, 100.25, 100.4, 100.45]):
        cams[t] = Camera.look_at([i, 1.7, -i], [i + 1, 1.7, -i - 5], fov_y=50 + i)
        r.add(t, cams[t])
    assert not r.add(100.3, cams[100.2])  # earlier than the last kept keyframe: ignored
    rec = r.stop()
    # kept: 100.0, 100.2 (0.2 after), 100.4; 100.45 is pending and kept by stop() as the end pose
    np.testing.assert_allclose([k.time for k in rec.keyframes], [0.0, 0.2, 0.4, 0.45], atol=1e-9)
    np.testing.assert_allclose(rec.keyframes[-1].position, cams[100.45].position)
    out = r.save(tmp_path / "recordings")
    assert out.parent == tmp_path / "recordings"
    assert re.fullmatch(r"city-\d{8}-\d{6}(-\d+)?\.json", out.name), out.name
    back = load_recording(out)
    assert back == rec and back.resolution == (320, 180) and back.fps == 24
    assert back.scene == {"builtin": "city", "size": 150_000, "seed": 1}
    cam = back.camera_at(0.2)
    np.testing.assert_allclose(cam.forward, cams[100.2].forward, atol=1e-12)
    assert cam.fov_y == pytest.approx(cams[100.2].fov_y)
    assert r.save(tmp_path / "recordings") != out  # same second: a new name, never overwritten


def test_recorder_file_scene_and_empty_recording(tmp_path):
    r = Recorder()
    r.start("sibenik/sibenik.obj", (64, 36))
    with pytest.raises(RtwalkError, match="nothing was recorded"):
        r.stop()
    r.start(Path("sibenik/sibenik.obj"), (64, 36))
    r.add(0.0, Camera.look_at([0, 0, 0], [1, 0, 0]))
    rec = r.stop()  # one pose: a still
    assert rec.scene == {"file": "sibenik/sibenik.obj"} and rec.frame_count() == 1
    assert r.save(tmp_path).name.startswith("sibenik-")

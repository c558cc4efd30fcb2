"""Animated scenes (issue 9, "Animated scenes"): the built-in `room-anim`, the BVH refit and the
per-frame rebuild of every backend's geometry-dependent structures.

Every registered exact backend (tests.conftest.backend_params) renders two frames of `room-anim`
at different scene times; each frame's rays are checked against an Embree scene built from THAT
frame's triangles (an independent reference: a stale structure anywhere in a backend shows up as
disagreement on the moving objects). A static scene must not rebuild anything.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import backend_params, checked_backend, prepared_scene
from viewer.effects import RayType, parse_effects
from viewer.reference import EmbreeTracer, compare_hits
from viewer.renderer import Renderer

SIZE = (160, 96)
EFFECTS = "primary,shadows,ao:1,reflections"
TIMES = (0.55, 1.35)  # cubes in the air, then one resting, one bouncing; the spheres have moved


def _reference_moves(scene) -> None:
    """The scene really animates between the two times (else the test proves nothing)."""
    a, b = scene.triangles_at(TIMES[0]), scene.triangles_at(TIMES[1])
    moved = np.abs(a - b).max(axis=(1, 2)) > 1e-3
    assert moved.sum() > 100, int(moved.sum())
    assert (~moved).sum() > 1000  # the room itself stays put


def test_room_anim_is_deterministic_and_rigid():
    from viewer.scene_io import load_scene

    s1, s2 = load_scene("room-anim"), load_scene("room-anim")
    for t in (0.0, 0.7, 3.9):
        a, b = s1.triangles_at(t), s2.triangles_at(t)
        assert a.shape == s1.triangles.shape and np.array_equal(a, b)
        # rigid motion: every triangle keeps its edge lengths (float32 rounding only)
        e0 = np.linalg.norm(s1.triangles[:, 1] - s1.triangles[:, 0], axis=1)
        e1 = np.linalg.norm(a[:, 1] - a[:, 0], axis=1)
        assert np.allclose(e0, e1, rtol=1e-5, atol=1e-5)
        # everything stays inside the room (x, z in [-5, 5], y in [-0.2, 5.1])
        flat = a.reshape(-1, 3)
        assert flat[:, [0, 2]].min() >= -5.1 and flat[:, [0, 2]].max() <= 5.1
        assert flat[:, 1].min() >= -0.2 and flat[:, 1].max() <= 5.1
    _reference_moves(s1)


def test_refit_matches_vertex_bounds():
    """Refit boxes against float64 NumPy: each node's box is exactly its triangles' min/max."""
    from viewer.accel.bvh import refit_bvh

    prep = prepared_scene("room-anim", 1)
    tris = prep.scene.triangles_at(1.1)
    bvh = refit_bvh(prep.bvh, tris)
    assert np.array_equal(bvh.tri_order, prep.bvh.tri_order)
    flat_min, flat_max = tris.min(axis=1).astype(np.float64), tris.max(axis=1).astype(np.float64)
    for node in np.random.default_rng(3).choice(len(bvh.node_min), 200, replace=False):
        f, c = int(bvh.node_first[node]), int(bvh.node_count[node])
        assert np.array_equal(bvh.node_min[node], flat_min[f:f + c].min(axis=0).astype(np.float32)), node
        assert np.array_equal(bvh.node_max[node], flat_max[f:f + c].max(axis=0).astype(np.float32)), node


@pytest.mark.parametrize("backend", backend_params(reference=False))
def test_animated_frames_agree_with_embree(backend, gl_ctx):
    backend = checked_backend(backend)
    prep = prepared_scene("room-anim", 1)
    _reference_moves(prep.scene)
    camera = prep.scene.default_camera
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, backend, parse_effects(EFFECTS))
    try:
        for t in TIMES:
            r.set_scene_time(t)
            rep = r.render(camera, capture=True)
            assert "build:bvh" in rep.gpu_ms and "build:upload" in rep.gpu_ms, rep.gpu_ms
            tris = r.scene.triangles
            assert np.array_equal(tris, prep.scene.triangles_at(t))  # the frame's geometry, leaf order
            raster = r.read_gbuffer_ids()
            embree = EmbreeTracer(tris)
            seen = set()
            for cp in rep.captured:
                act = cp.rays.active
                if act.sum() == 0:
                    continue
                seen.add(cp.ray_type)
                o, d = cp.rays.origins[act], cp.rays.directions[act]
                t_ref, id_ref = embree.trace(o, d, cp.rays.tmin[act], cp.rays.tmax[act], any_hit=cp.ray_type.any_hit)
                st = compare_hits(cp.t[act], cp.tri[act], t_ref, id_ref, tris)
                label = f"{backend} t={t} {cp.ray_type.label}"
                assert st["hitmiss_agree"] >= 0.999, (label, st)
                if not cp.ray_type.any_hit:
                    assert st["id_agree"] >= (0.9999 if cp.ray_type == RayType.PRIMARY else 0.999), (label, st)
                if cp.ray_type == RayType.PRIMARY:  # the G-buffer's vertices moved too
                    assert (raster[act] == id_ref).mean() >= 0.999, (label, "raster")
            assert {RayType.PRIMARY, RayType.SHADOW, RayType.AO} <= seen
    finally:
        r.release()


@pytest.mark.parametrize("backend", ["glsl"])
def test_static_scene_rebuilds_nothing(backend, gl_ctx):
    """A static scene: set_scene_time changes nothing, no build phase runs, buffers are untouched."""
    prep = prepared_scene("room", 1)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, backend, parse_effects("primary"))
    try:
        r.render(prep.scene.default_camera)
        scene, bvh = r.scene, r.bvh
        r.set_scene_time(2.0)
        rep = r.render(prep.scene.default_camera)
        assert not [k for k in rep.gpu_ms if k.startswith("build:")], rep.gpu_ms
        assert r.scene is scene and r.bvh is bvh and r.scene.geometry_version == 0
        assert r.update_geometry() is False
    finally:
        r.release()


def test_animated_scene_same_time_rebuilds_nothing(gl_ctx):
    prep = prepared_scene("room-anim", 1)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, "glsl", parse_effects("primary"))
    try:
        r.set_scene_time(0.8)
        rep = r.render(prep.scene.default_camera)
        assert "build:bvh" in rep.gpu_ms
        rep = r.render(prep.scene.default_camera)  # same time: nothing moves, nothing is rebuilt
        assert not [k for k in rep.gpu_ms if k.startswith("build:")], rep.gpu_ms
    finally:
        r.release()


def test_recording_scene_time_round_trip_and_old_files(tmp_path):
    """Scene time per keyframe: saved as version 2, loaded back equal, interpolated linearly (against
    np.interp on the keyframe values); a file without it (version 1) uses the camera clock."""
    from viewer.camera import Camera
    from viewer.recording import Keyframe, Recording, load_recording, save_recording

    cam = Camera.look_at((0, 2, 4), (0, 1, 0))
    keys = [Keyframe.from_camera(t, cam) for t in (0.0, 1.0, 3.0)]
    for k, st in zip(keys, (5.0, 5.0, 9.0), strict=True):  # stands still, then runs at 2x
        k.scene_time = st
    rec = Recording({"builtin": "room-anim", "size": 1, "seed": 1}, (64, 36), 10.0, keys)
    path = save_recording(rec, tmp_path / "anim.json")
    import json

    assert json.loads(path.read_text())["version"] == 2
    back = load_recording(path)
    assert [k.scene_time for k in back.keyframes] == [5.0, 5.0, 9.0]
    for n in range(back.frame_count()):
        t = n / 10.0
        assert back.scene_time_for_frame(n) == pytest.approx(float(np.interp(t, [0, 1, 3], [5, 5, 9])))
    for k in keys:
        k.scene_time = None
    path1 = save_recording(rec, tmp_path / "static.json")
    assert json.loads(path1.read_text())["version"] == 1
    old = load_recording(path1)
    assert not old.has_scene_time and old.scene_time_for_frame(7) == pytest.approx(0.7)


def test_shipped_anim_recording_moves_objects():
    from viewer.paths import RECORDINGS
    from viewer.recording import load_recording

    rec = load_recording(RECORDINGS / "room-anim-walk.json")
    assert rec.scene["builtin"] == "room-anim" and rec.has_scene_time
    times = [rec.scene_time_for_frame(n) for n in range(rec.frame_count())]
    assert times[0] < times[-1]


def test_every_registered_backend_implements_scene_changed():
    """The contract method is implemented by every registered backend class (no silent fallback)."""
    from tests.conftest import opencl_missing
    from viewer.backends import backend_class, backend_names

    for name in backend_names():
        try:
            cls = backend_class(name)
        except ImportError:
            assert opencl_missing() is not None, name
            continue
        assert callable(getattr(cls, "scene_changed", None)), name


def test_inactive_backend_catches_up_when_selected(gl_ctx):
    """A backend created earlier and inactive while the scene moved is told when selected again: its
    hits match Embree on the current frame's triangles."""
    from tests.conftest import opencl_missing

    other = "clbvh" if opencl_missing() is None else "chcrt"
    prep = prepared_scene("room-anim", 1)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, other, parse_effects("primary,shadows"))
    try:
        r.render(prep.scene.default_camera)  # built at t = 0
        r.set_backend("glsl")
        r.set_scene_time(1.35)
        r.render(prep.scene.default_camera)  # the geometry moves while `other` is inactive
        r.set_backend(other)
        rep = r.render(prep.scene.default_camera, capture=True)
        embree = EmbreeTracer(r.scene.triangles)
        for cp in rep.captured:
            act = cp.rays.active
            t_ref, id_ref = embree.trace(cp.rays.origins[act], cp.rays.directions[act], cp.rays.tmin[act],
                                         cp.rays.tmax[act], any_hit=cp.ray_type.any_hit)
            st = compare_hits(cp.t[act], cp.tri[act], t_ref, id_ref, r.scene.triangles)
            assert st["hitmiss_agree"] >= 0.999, (other, cp.ray_type.label, st)
    finally:
        r.release()


def test_chcrt_keeps_fronts_across_a_refit(gl_ctx):
    """A refit keeps the tree's topology, so chcrt keeps its per-pass fronts (same objects) and
    still agrees with Embree on the moved frame (checked in test_animated_frames_agree_with_embree)."""
    prep = prepared_scene("room-anim", 1)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, "chcrt", parse_effects("primary"))
    try:
        r.render(prep.scene.default_camera)
        fronts = dict(r.backend.fronts)
        assert fronts
        r.set_scene_time(0.9)
        rep = r.render(prep.scene.default_camera)
        assert "build:chcrt" in rep.gpu_ms
        assert all(r.backend.fronts.get(k) is f for k, f in fronts.items())
        assert np.array_equal(r.backend.nt.box_min, r.bvh.node_min)  # the query boxes were refitted
    finally:
        r.release()


def test_chcrt_without_temporal_coherence_starts_every_frame_cold(gl_ctx):
    """temporal=false (what temporal coherence buys is measured against it): fronts are dropped
    at every frame, so each front has traced exactly one frame; the default keeps them."""
    prep = prepared_scene("room-anim", 1)
    for temporal, want in (("false", 1), ("true", 2)):
        r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, "chcrt", parse_effects("primary"),
                     backend_options={"chcrt": f"temporal={temporal}"})
        try:
            r.render(prep.scene.default_camera)
            r.set_scene_time(0.9)
            r.render(prep.scene.default_camera)
            assert r.backend.fronts and all(f.frames == want for f in r.backend.fronts.values())
        finally:
            r.release()


def test_bench_judges_each_animated_frame_by_its_own_geometry(gl_ctx):
    """`rtwalk bench` on an animated path: the Embree reference of the error column is built on each
    checked frame's triangles (a reference of the first frame reports moved objects as errors)."""
    from viewer.bench.replay import BenchOptions, run_bench
    from viewer.paths import RECORDINGS
    from viewer.recording import load_recording

    rec = load_recording(RECORDINGS / "room-anim-walk.json")
    prep = prepared_scene("room-anim")
    opts = BenchOptions(backend="glsl", size=(96, 54), reference="embree", reference_every=1, warmup=0,
                        first_frame=40, max_frames=3)
    report = run_bench(prep, rec, parse_effects("primary,shadows,reflections"), opts, gl_ctx, quiet=True)
    times = [row["scene_time_s"] for row in report["frames"]]
    assert len(set(times)) == 3  # the objects moved between the checked frames
    for row in report["frames"]:
        for ray, err in row["error"].items():
            assert err["hit_agreement"] >= 0.999 and err["id_agreement"] >= 0.999, (row["frame"], ray, err)

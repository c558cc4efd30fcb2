"""Every ray type of every registered backend, and the rasterized G-buffer, against Embree on the
same rays.

The backends come from the registry (tests.conftest.backend_params): each one (the Embree reference
itself excepted) meets the same bars, without test code of its own. The rays are the ones the
pipeline generated (read back from the ray textures), so this checks tracing, not sampling. Embree
(embreex) is an independent implementation. Two consecutive frames are rendered and the second is
checked, so backends with temporal state (reuse of the previous frame) are checked warm.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import backend_params, checked_backend, prepared_scene, shared_scene
from viewer.effects import RayType, parse_effects
from viewer.paths import RECORDINGS
from viewer.reference import EmbreeTracer, compare_hits
from viewer.renderer import Renderer

SIZE = (320, 180)
# every ray type once (one sample each: this checks tracing, not sampling); two frames are rendered,
# so the cost per backend stays near that of one frame with two samples of each
EFFECTS = "primary,shadows,soft:1,ao:1,diffuse:1,reflections"

SCENES = {
    "city": lambda: ("city", 60_000, "city-near.json"),
    "sponza": lambda: (shared_scene("sponza-dabrovic/sponza.obj"), None, "sponza-walk.json"),
    "sibenik": lambda: (shared_scene("sibenik/sibenik.obj"), None, "sibenik-walk.json"),
    "conference": lambda: (shared_scene("conference/conference.ply"), None, "conference-walk.json"),
    "bunny": lambda: (shared_scene("bunny/bun_zipper.ply"), None, None),
    # the room moved to x = 1e6 (float32 step 1/16): secondary rays start within rounding of surfaces
    "room-at-1e6": lambda: ("room-at-1e6", None, None),
}

_embree: dict = {}  # scene key -> EmbreeTracer, shared by the backends
_far: dict = {}  # the far room, prepared once


def _far_room():
    """The built-in room moved by 1e6 along x (lights and camera too), prepared like a loaded scene."""
    from dataclasses import replace

    from tests.test_reference import FAR_SHIFT
    from viewer.accel.bvh import build_bvh
    from viewer.camera import Camera
    from viewer.procedural import make_room
    from viewer.session import PreparedScene

    if not _far:
        room = make_room()
        shift = FAR_SHIFT

        def moved(p):
            return (np.asarray(p, np.float64) + shift).astype(np.float32)

        cam = room.default_camera
        scene = replace(room, triangles=moved(room.triangles),
                        point_lights=[replace(p, position=moved(p.position)) for p in room.point_lights],
                        rect_lights=[replace(r, corner=moved(r.corner)) for r in room.rect_lights],
                        default_camera=Camera(cam.position + shift, cam.orientation, cam.fov_y))
        bvh = build_bvh(scene.triangles)
        _far["room"] = PreparedScene(scene.reordered(bvh.tri_order), bvh)
    return _far["room"]


def _cameras(scene, recording: str | None):
    """Two consecutive cameras (the frame before the checked one, then the checked one); a scene
    without a recording uses its default camera twice (a still camera)."""
    from viewer.recording import load_recording

    path = RECORDINGS / recording if recording else None
    if path is not None and path.exists():
        rec = load_recording(path)
        n = rec.frame_count() // 3
        return rec.camera_for_frame(n - 1), rec.camera_for_frame(n)
    return scene.default_camera, scene.default_camera


@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.parametrize("backend", backend_params(reference=False))
def test_all_ray_types_agree_with_embree(backend, name, gl_ctx):
    backend = checked_backend(backend)
    spec, size, recording = SCENES[name]()
    prep = _far_room() if spec == "room-at-1e6" else prepared_scene(spec, size)
    settings = parse_effects(EFFECTS)
    before, camera = _cameras(prep.scene, recording)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, backend, settings)
    try:
        r.render(before)
        rep = r.render(camera, capture=True)
        raster_ids = r.read_gbuffer_ids()
    finally:
        r.release()
    key = (spec, size)
    if key not in _embree:
        _embree[key] = EmbreeTracer(prep.scene.triangles)
    embree = _embree[key]
    tris = prep.scene.triangles
    seen = set()
    for cp in rep.captured:
        act = cp.rays.active
        if act.sum() == 0:
            continue
        seen.add(cp.ray_type)
        o, d, lo, hi = cp.rays.origins[act], cp.rays.directions[act], cp.rays.tmin[act], cp.rays.tmax[act]
        t_ref, id_ref = embree.trace(o, d, lo, hi, any_hit=cp.ray_type.any_hit)
        st = compare_hits(cp.t[act], cp.tri[act], t_ref, id_ref, tris)
        label = f"{backend} {name} {cp.ray_type.label} sample {cp.sample}"
        if cp.ray_type.any_hit:
            assert st["hitmiss_agree"] >= 0.999, (label, st)
        else:
            assert st["hitmiss_agree"] >= 0.999, (label, st)
            need = 0.9999 if cp.ray_type == RayType.PRIMARY else 0.999
            assert st["id_agree"] >= need, (label, st)
            # distances: 1e-5 relative where both found the same triangle, plus a few float32 ulps of the
            # coordinates: a float32 origin/vertex difference is only that exact, which dominates for
            # hits very close to the ray origin (t -> 0), for Embree as for us
            both = (cp.tri[act] >= 0) & (cp.tri[act] == id_ref)
            err = np.abs(cp.t[act][both].astype(np.float64) - t_ref[both])
            tol = 1e-5 * t_ref[both] + 4 * _ulp_scale(tris, o[both])
            assert err.size == 0 or (err <= tol).all(), (label, float((err / np.maximum(t_ref[both], 1e-30)).max()))
        if cp.ray_type == RayType.PRIMARY:
            # rasterization (G-buffer ids) against Embree on the same primary rays
            # ids may differ only where the two triangles are met at the same distance (ties)
            same = raster_ids[act] == id_ref
            diff = ~same
            if diff.any():
                tie = _same_distance(tris, o[diff], d[diff], raster_ids[act][diff], t_ref[diff])
                agree = (same.sum() + tie.sum()) / len(same)
            else:
                agree = 1.0
            assert agree >= 0.9999, (f"{name} raster vs embree", agree, int(diff.sum()))
    expected = {RayType.PRIMARY, RayType.SHADOW, RayType.AO, RayType.DIFFUSE}
    assert expected <= seen, seen


def _ulp_scale(tris, o):
    """float32 ulp of the largest coordinate magnitude involved, per ray (directions are unit)."""
    mag = max(float(np.abs(tris).max()), 1e-30)
    return np.spacing(np.float32(mag)).astype(np.float64) + np.spacing(np.abs(o).max(1).astype(np.float32))


def _same_distance(tris, o, d, ids, t_ref, rel=1e-6):
    """True where triangle `ids` is hit by the ray at (relatively) the reference distance."""
    from viewer.reference import trace_float64

    ok = np.zeros(len(ids), bool)
    for k in range(len(ids)):  # only the few disagreeing pixels
        if ids[k] < 0 or not np.isfinite(t_ref[k]):
            continue
        t, hit = trace_float64(tris[ids[k]][None], o[k][None], d[k][None], np.zeros(1), np.full(1, np.inf))
        ok[k] = hit[0] >= 0 and abs(t[0] - t_ref[k]) <= rel * max(t_ref[k], 1e-30)
    return ok


def test_backend_params_marks(monkeypatch):
    """The registry-driven parameters: the reference left out where asked, an OpenCL backend skipped
    (with the reason) only when no OpenCL device exists, an inexact backend skipped with the reason."""
    import sys
    import types

    import tests.conftest as conftest
    import viewer.backends as registry
    from viewer.backends.interface import BackendInfo

    fake = types.ModuleType("fake_backends")
    fake.Cl = type("Cl", (), {"info": BackendInfo("fakecl", "an OpenCL backend", device="cl")})
    fake.Approx = type("Approx", (), {"info": BackendInfo("fakeapprox", "approximate by design", exact=False)})
    monkeypatch.setitem(sys.modules, "fake_backends", fake)
    monkeypatch.setitem(registry.BACKENDS, "fakecl", "fake_backends:Cl")
    monkeypatch.setitem(registry.BACKENDS, "fakeapprox", "fake_backends:Approx")
    monkeypatch.setattr(conftest, "_opencl_reason", ["no OpenCL device (test)"])
    params = {p.id: p for p in backend_params(reference=False)}
    assert "embree" not in params and {"glsl", "fakecl", "fakeapprox"} <= set(params)
    assert not params["glsl"].marks
    (mark,) = params["fakecl"].marks
    assert mark.name == "skip" and "no OpenCL device (test)" in mark.kwargs["reason"]
    (mark,) = params["fakeapprox"].marks
    assert mark.name == "skip" and "exact" in mark.kwargs["reason"]
    assert "embree" in {p.id for p in backend_params(reference=True)}
    monkeypatch.setattr(conftest, "_opencl_reason", [None])      # an OpenCL device exists: it runs
    assert not {p.id: p for p in backend_params(reference=False)}["fakecl"].marks

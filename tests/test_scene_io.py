"""Scene loading: counts, materials, cleaning, sidecars, built-ins (against numbers computed here
or stated in ../shared/scenes/README.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import shared_scene
from viewer.errors import RtwalkError
from viewer.scene_io import load_scene, vertical_hits


def test_conference_drops_zero_area_triangles():
    s = load_scene(shared_scene("conference/conference.ply"), progress=False)
    assert s.triangle_count == 331_179 - 53_627  # README: 53,627 exactly-zero-area triangles
    assert any("53627 zero-area" in n for n in s.notes)


def test_sponza_materials_from_mtl():
    s = load_scene(shared_scene("sponza-dabrovic/sponza.obj"), progress=False)
    assert s.triangle_count == 66_445
    assert len(s.materials) == 19
    albedos = np.array([m.albedo for m in s.materials])
    assert len(np.unique(albedos.round(3), axis=0)) > 3  # Kd values differ
    used = np.bincount(s.material_ids, minlength=len(s.materials))
    assert (used > 0).all()


def test_mirror_patterns_and_sidecar(tmp_path):
    obj = tmp_path / "quad.obj"
    obj.write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nusemtl shiny\nf 1 2 3\nusemtl dull\nf 1 3 4\n")
    (tmp_path / "quad.mtl").write_text("newmtl shiny\nKd 0.9 0.9 0.9\nnewmtl dull\nKd 0.2 0.5 0.1\n")
    s = load_scene(str(obj), mirror_patterns=["SHI*"], progress=False)
    assert {m.name: m.mirror for m in s.materials} == {"shiny": True, "dull": False}
    dull = next(m for m in s.materials if m.name == "dull")
    np.testing.assert_allclose(dull.albedo, [0.2, 0.5, 0.1], atol=1.5 / 255)  # trimesh stores Kd as 8 bit
    (tmp_path / "quad.obj.rtwalk.json").write_text(json.dumps({
        "mirrors": ["dull"], "point_lights": [{"position": [0, 0, 3], "intensity": [5, 5, 5]}],
        "camera": {"position": [0.5, 0.5, 4], "target": [0.5, 0.5, 0], "fov_y": 40}}))
    s = load_scene(str(obj), progress=False)
    assert all(m.mirror for m in s.materials if m.name == "dull")
    assert len(s.point_lights) == 1 and s.point_lights[0].position[2] == 3
    assert s.default_camera.fov_y == 40
    np.testing.assert_allclose(s.default_camera.forward, [0, 0, -1], atol=1e-9)


def test_bad_sidecar_is_one_line(tmp_path):
    obj = tmp_path / "t.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "t.obj.rtwalk.json").write_text('{"point_lights": [{"position": [1, 2]}]}')
    with pytest.raises(RtwalkError) as exc:
        load_scene(str(obj), progress=False)
    assert "t.obj.rtwalk.json" in str(exc.value) and "\n" not in str(exc.value)


def test_nan_and_degenerate_triangles_dropped(tmp_path):
    obj = tmp_path / "mixed.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 0\nv 2 0 0\n"
                   "f 1 2 3\nf 1 2 4\nf 1 2 5\n")  # good, NaN, collinear
    s = load_scene(str(obj), progress=False)
    assert s.triangle_count == 1
    assert any("NaN" in n for n in s.notes) and any("zero-area" in n for n in s.notes)


def test_city_size_and_determinism():
    a = load_scene("city", scene_size=50_000, seed=3, progress=False)
    b = load_scene("city", scene_size=50_000, seed=3, progress=False)
    c = load_scene("city", scene_size=50_000, seed=4, progress=False)
    assert abs(a.triangle_count - 50_000) <= 0.15 * 50_000
    assert a.triangles.tobytes() == b.triangles.tobytes()
    assert a.triangles.tobytes() != c.triangles.tobytes()
    assert any(m.mirror for m in a.materials)
    with pytest.raises(RtwalkError):
        load_scene("city", scene_size=10, progress=False)


def test_room_is_closed_and_lit_inside():
    s = load_scene("room", progress=False)
    lo, hi = s.bounds
    for light in s.point_lights:
        assert (light.position > lo).all() and (light.position < hi).all()
    # every vertical line through the room crosses floor and ceiling
    for x, z in [(0.0, 0.0), (1.0, -1.0), (-1.5, 1.5)]:
        ys, _ = vertical_hits(s.triangles, x, z)
        ext = hi[1] - lo[1]
        assert len(ys) >= 2 and ys[0] <= lo[1] + 0.1 * ext and ys[-1] >= hi[1] - 0.1 * ext


def test_indoor_default_light_is_under_the_ceiling():
    s = load_scene(shared_scene("sibenik/sibenik.obj"), progress=False)
    p = s.point_lights[0].position
    ys, _ = vertical_hits(s.triangles, float(p[0]), float(p[2]))
    above = ys[ys > p[1]]
    below = ys[ys < p[1]]
    assert len(above) and len(below), "light must have a floor below and a ceiling above"


def test_bvh_progress_fraction_gives_a_sane_eta():
    """The BVH bar's fraction (viewer.session.BuildWork) grows with the work done, so the ETA it
    implies (elapsed / fraction) is near the real build time once a third is done (the bar used to
    count triangles placed in leaves: 0% for most of the build, an ETA minutes off)."""
    import time

    from viewer.accel.bvh import build_bvh
    from viewer.procedural import make_city
    from viewer.session import BuildWork

    scene = make_city(300_000, 1)
    work = BuildWork(scene.triangle_count)
    seen: list[tuple[float, float]] = []
    t0 = time.perf_counter()
    build_bvh(scene.triangles, progress=lambda placed, total: seen.append((time.perf_counter() - t0,
                                                                          work.level_done(placed))))
    total = time.perf_counter() - t0
    fracs = [f for _, f in seen]
    assert fracs == sorted(fracs) and fracs[-1] == 1.0 and fracs[0] < 0.2
    mid = [(t, f) for t, f in seen if 0.33 <= f <= 0.9]
    assert mid
    for t, f in mid:
        assert 0.4 < (t / f) / total < 2.5, (t, f, total)

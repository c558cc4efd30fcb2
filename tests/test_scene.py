"""Procedural scenes (city, room) and scene loading (shared benchmark scenes, sidecars, errors).

Numbers for the shared scenes come from ../shared/scenes/README.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from viewer.errors import RtwalkError
from viewer.procedural import (
    BUILTIN_SCENES,
    PITCH,
    PLINTH_TOP,
    STREET_WIDTH,
    city_layout,
    make_city,
    make_room,
)
from viewer.scene_io import load_scene

SCENES_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


def _areas(tris: np.ndarray) -> np.ndarray:
    t = tris.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _first_hits(tris: np.ndarray, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brute force float64 Moller-Trumbore: (nearest distance or inf, hit triangle or -1) per ray."""
    t = tris.astype(np.float64)
    v0, e1, e2 = t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    s = origin - v0
    q = np.cross(s, e1)  # (T, 3), independent of the ray direction
    best = np.full(len(dirs), np.inf)
    which = np.full(len(dirs), -1)
    for i, d in enumerate(dirs):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = np.einsum("ij,ij->i", s, p) * inv
            v = (q @ d) * inv
            dist = np.einsum("ij,ij->i", e2, q) * inv
        ok = (np.abs(det) > 1e-14) & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 1e-9)
        if ok.any():
            k = np.argmin(np.where(ok, dist, np.inf))
            best[i], which[i] = dist[k], k
    return best, which


# ---------------------------------------------------------------------------------------------- city


@pytest.mark.parametrize("target", [50_000, 400_000])
def test_city_triangle_count_near_target(target):
    s = make_city(target, seed=1)
    assert abs(s.triangle_count - target) <= 0.15 * target
    assert s.triangles.dtype == np.float32 and s.triangles.shape == (s.triangle_count, 3, 3)
    assert s.material_ids.dtype == np.int32 and s.material_ids.shape == (s.triangle_count,)
    assert 0 <= s.material_ids.min() and s.material_ids.max() < len(s.materials)


def test_city_is_deterministic_per_seed():
    a, b, c = make_city(50_000, 5), make_city(50_000, 5), make_city(50_000, 6)
    assert a.triangles.tobytes() == b.triangles.tobytes()
    assert a.material_ids.tobytes() == b.material_ids.tobytes()
    assert a.triangles.shape != c.triangles.shape or a.triangles.tobytes() != c.triangles.tobytes()


def test_city_geometry_is_clean_and_bounded():
    s = make_city(150_000, 1)
    assert np.isfinite(s.triangles).all()
    assert _areas(s.triangles).min() > 1e-4  # no degenerate triangles
    lay = city_layout(150_000, 1)
    lo, hi = s.bounds
    g = lay["ground_half_extent"]
    np.testing.assert_allclose([lo[0], lo[2], hi[0], hi[2]], [-g, -g, g, g])
    assert -1.0 <= lo[1] <= 0.0 and 60.0 <= hi[1] <= 200.0
    assert hi[1] == pytest.approx(lay["max_height"])
    # mostly ordinary heights, a few towers
    assert 10.0 < lay["max_building_height"] <= 120.0
    # mirrors: glass_mirror exists and is used
    mirrors = [i for i, m in enumerate(s.materials) if m.mirror]
    assert [s.materials[i].name for i in mirrors] == ["glass_mirror"]
    assert np.isin(s.material_ids, mirrors).any()
    assert s.identity == {"builtin": "city", "size": 150_000, "seed": 1}


def test_city_layout_streets_are_free():
    lay = city_layout(150_000, 1)
    assert lay["blocks_per_side"] == 8 and lay["pitch"] == PITCH and lay["street_width"] == STREET_WIDTH
    assert lay["street_centres"] == [-160.0 + 40.0 * k for k in range(9)]
    s = make_city(150_000, 1)
    tmin, tmax = s.triangles.min(axis=1), s.triangles.max(axis=1)
    raised = tmax[:, 1] > PLINTH_TOP + 1e-3  # anything above the sidewalks (not ground, not plinth top)
    half_w = lay["street_width"] / 2
    for sc in lay["street_centres"]:
        for axis in (0, 2):  # streets along z (fixed x) and along x (fixed z)
            inside = (tmax[:, axis] > sc - half_w + 1e-3) & (tmin[:, axis] < sc + half_w - 1e-3)
            assert not (raised & inside).any(), f"geometry in the street at {'xz'[axis // 2]} = {sc}"
    cam = s.default_camera
    assert cam.position[1] == pytest.approx(1.7) and cam.position[0] in lay["street_centres"]
    np.testing.assert_allclose(cam.position, lay["default_camera"]["position"])


def test_city_lights():
    s = make_city(50_000, 1)
    lo, hi = s.bounds
    (p,) = s.point_lights
    (r,) = s.rect_lights
    assert p.position[1] >= 2.9 * city_layout(50_000, 1)["max_building_height"]
    d2 = float(np.sum(p.position.astype(np.float64) ** 2))
    e_ground = float(p.intensity.mean()) * (p.position[1] / np.sqrt(d2)) / d2  # at the city centre
    assert 1.0 < e_ground < 2.0
    assert r.center[1] > hi[1] and r.normal[1] < -0.99


# ---------------------------------------------------------------------------------------------- room


def test_room_is_closed_and_faces_inwards():
    s = make_room(seed=1, detail=1)
    assert 1_000 <= s.triangle_count <= 10_000
    assert _areas(s.triangles).min() > 1e-6
    lo, hi = (b.astype(np.float64) for b in s.bounds)
    centre = (lo + hi) / 2
    dirs = np.random.default_rng(0).normal(size=(1000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist, tri = _first_hits(s.triangles, centre, dirs)
    assert np.isfinite(dist).all(), f"{int(np.isinf(dist).sum())} of 1000 rays escape the room"
    t = s.triangles[tri].astype(np.float64)
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    assert (np.einsum("ij,ij->i", n, dirs) < 0).all(), "every surface seen from inside is front-facing"


def test_room_contents():
    s = make_room()
    names = {m.name: m for m in s.materials}
    assert names["mirror"].mirror and np.isin(s.material_ids, [s.materials.index(names["mirror"])]).any()
    assert not names["red_wall"].mirror
    lo, hi = s.bounds
    for light in s.point_lights:
        assert (light.position > lo).all() and (light.position < hi).all()
    (r,) = s.rect_lights
    assert r.normal[1] < -0.99 and lo[1] < r.center[1] < hi[1]
    cam = s.default_camera
    assert (cam.position > lo).all() and (cam.position < hi).all()
    assert make_room(1).triangles.tobytes() == make_room(1).triangles.tobytes()
    assert make_room(1, detail=2).triangle_count > 2 * s.triangle_count


def test_builtins_through_load_scene():
    assert set(BUILTIN_SCENES) >= {"city", "room"}
    d = load_scene(None, scene_size=20_000, progress=False)
    assert d.identity == {"builtin": "city", "size": 20_000, "seed": 1}
    s = load_scene("city:20k", seed=2, progress=False)
    assert s.identity == {"builtin": "city", "size": 20_000, "seed": 2}
    assert abs(s.triangle_count - 20_000) <= 0.15 * 20_000
    m = load_scene("room", mirror_patterns=["RED_*"], progress=False)
    assert {x.name for x in m.materials if x.mirror} == {"mirror", "red_wall"}


# ---------------------------------------------------------------------------------------------- files


@pytest.mark.scenes
@pytest.mark.skipif(not SCENES_DIR.is_dir(), reason="shared scenes not present")
@pytest.mark.parametrize("rel, count", [("sponza-dabrovic/sponza.obj", 66_445), ("bunny/bun_zipper.ply", 69_451)])
def test_shared_scene_counts(rel, count):
    s = load_scene(str(SCENES_DIR / rel), progress=False)
    assert s.triangle_count == count and s.notes == []
    assert s.identity == {"file": str(SCENES_DIR / rel), "name": Path(rel).name}


@pytest.mark.scenes
@pytest.mark.skipif(not SCENES_DIR.is_dir(), reason="shared scenes not present")
def test_conference_drops_zero_area():
    s = load_scene("conference/conference.ply", progress=False)  # resolved against ../shared/scenes
    assert s.triangle_count == 331_179 - 53_627
    assert any("dropped 53627 zero-area triangles" in n for n in s.notes)
    assert s.name == "conference" and s.identity["file"] == "conference/conference.ply"
    assert _areas(s.triangles).min() > 0


@pytest.mark.scenes
@pytest.mark.skipif(not SCENES_DIR.is_dir(), reason="shared scenes not present")
def test_sibenik_counts_add_up():
    s = load_scene("sibenik/sibenik.obj", progress=False)
    dropped = sum(int(n.split()[1]) for n in s.notes if "zero-area" in n)
    assert 0 < dropped <= 11 and s.triangle_count + dropped == 73_564
    assert len(s.materials) == 14


@pytest.mark.scenes
@pytest.mark.skipif(not SCENES_DIR.is_dir(), reason="shared scenes not present")
def test_sponza_materials_lights_camera():
    s = load_scene("sponza-dabrovic/sponza.obj", mirror_patterns=["SP_00_PROZOR"], progress=False)
    assert len(s.materials) == 19
    by_name = {m.name: m for m in s.materials}
    np.testing.assert_allclose(by_name["sp_00_svod"].albedo, [0.941177, 0.866667, 0.737255], atol=1e-6)  # Kd
    assert len(np.unique(np.array([m.albedo for m in s.materials]).round(4), axis=0)) >= 8
    assert [m.name for m in s.materials if m.mirror] == ["sp_00_prozor"]
    lo, hi = s.bounds
    (p,) = s.point_lights
    assert (p.position > lo).all() and (p.position < hi).all()  # lights the interior
    (r,) = s.rect_lights
    assert r.normal[1] < -0.99
    cam = s.default_camera  # an interior: the camera is inside
    assert (cam.position > lo).all() and (cam.position < hi).all()


@pytest.mark.scenes
@pytest.mark.skipif(not SCENES_DIR.is_dir(), reason="shared scenes not present")
def test_object_scan_camera_is_outside_and_sees_it():
    s = load_scene("bunny/bun_zipper.ply", progress=False)
    lo, hi = (b.astype(np.float64) for b in s.bounds)
    cam = s.default_camera
    assert ((cam.position < lo) | (cam.position > hi)).any()
    dist, _ = _first_hits(s.triangles, cam.position, cam.forward[None])
    assert np.isfinite(dist).all()


def _quad_obj(tmp_path: Path) -> Path:
    obj = tmp_path / "quad.obj"
    obj.write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                   "usemtl Glass_Pane\nf 1 2 3\nusemtl wall\nf 1 3 4\n")
    (tmp_path / "quad.mtl").write_text("newmtl Glass_Pane\nKd 0.9 0.91 0.92\nnewmtl wall\nKd 0.123 0.456 0.789\n")
    return obj


def test_obj_materials_and_mirror_patterns(tmp_path):
    obj = _quad_obj(tmp_path)
    s = load_scene(str(obj), mirror_patterns=["glass*"], progress=False)
    mats = {m.name: m for m in s.materials}
    assert set(mats) == {"Glass_Pane", "wall"}
    assert mats["Glass_Pane"].mirror and not mats["wall"].mirror
    np.testing.assert_allclose(mats["wall"].albedo, [0.123, 0.456, 0.789], atol=1e-6)
    assert s.triangle_count == 2 and s.identity == {"file": str(obj), "name": "quad.obj"}
    assert len(s.point_lights) == 1 and len(s.rect_lights) == 1 and s.default_camera is not None


def test_sidecar_lights_camera_sky(tmp_path):
    obj = _quad_obj(tmp_path)
    (tmp_path / "quad.obj.rtwalk.json").write_text(json.dumps({
        "mirrors": ["WALL"],
        "point_lights": [{"position": [0, 0, 3], "intensity": [5, 6, 7]}],
        "rect_lights": [{"corner": [0, 2, 0], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1], "radiance": [2, 2, 2]}],
        "camera": {"position": [0.5, 0.5, 4], "target": [0.5, 0.5, 0], "fov_y": 40},
        "sky_color": [0.1, 0.2, 0.3]}))
    s = load_scene(str(obj), progress=False)
    assert {m.name for m in s.materials if m.mirror} == {"wall"}
    (p,) = s.point_lights
    np.testing.assert_allclose(p.position, [0, 0, 3])
    np.testing.assert_allclose(p.intensity, [5, 6, 7])
    (r,) = s.rect_lights
    np.testing.assert_allclose(r.normal, [0, -1, 0])
    np.testing.assert_allclose(s.sky_color, [0.1, 0.2, 0.3], rtol=1e-6)
    assert s.default_camera.fov_y == 40
    np.testing.assert_allclose(s.default_camera.position, [0.5, 0.5, 4])
    np.testing.assert_allclose(s.default_camera.forward, [0, 0, -1], atol=1e-9)
    # orientation instead of a target
    (tmp_path / "quad.obj.rtwalk.json").write_text(json.dumps(
        {"camera": {"position": [1, 2, 3], "orientation": [1, 0, 0, 0]}}))
    s = load_scene(str(obj), progress=False)
    np.testing.assert_allclose(s.default_camera.forward, [0, 0, -1], atol=1e-12)


def test_glb_scene_graph_transforms_and_pbr(tmp_path):
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    red = trimesh.creation.box((1, 1, 1))
    red.visual = TextureVisuals(material=PBRMaterial(name="red_paint", baseColorFactor=[0.8, 0.1, 0.1, 1.0]))
    chrome = trimesh.creation.box((1, 1, 1))
    chrome.visual = TextureVisuals(material=PBRMaterial(name="chrome", baseColorFactor=[0.9, 0.9, 0.9, 1.0]))
    sc = trimesh.Scene()
    sc.add_geometry(red, node_name="a", geom_name="a")
    move = trimesh.transformations.translation_matrix
    sc.add_geometry(chrome, node_name="b", geom_name="b", transform=move([10, 0, 0]))
    sc.add_geometry(chrome, node_name="b2", geom_name="b", transform=move([0, 5, 0]))  # an instance
    path = tmp_path / "two.glb"
    sc.export(str(path))
    s = load_scene(str(path), mirror_patterns=["chrome"], progress=False)
    assert s.triangle_count == 36
    lo, hi = s.bounds
    np.testing.assert_allclose(lo, [-0.5, -0.5, -0.5])
    np.testing.assert_allclose(hi, [10.5, 5.5, 0.5])
    mats = {m.name: m for m in s.materials}
    assert set(mats) == {"red_paint", "chrome"} and mats["chrome"].mirror
    np.testing.assert_allclose(mats["red_paint"].albedo, [0.8, 0.1, 0.1], atol=1.5 / 255)


def test_face_colours_become_materials(tmp_path):
    import trimesh

    m = trimesh.creation.box((1, 1, 1))
    m.visual.face_colors = np.tile([[255, 0, 0, 255], [0, 255, 0, 255]], (6, 1))
    path = tmp_path / "coloured.ply"
    m.export(str(path))
    s = load_scene(str(path), progress=False)
    albedos = sorted(tuple(float(c) for c in x.albedo) for x in s.materials)
    assert albedos == [(0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]
    assert np.bincount(s.material_ids).tolist() == [6, 6]


# ---------------------------------------------------------------------------------------------- errors


def _error(spec: str, **kw) -> str:
    with pytest.raises(RtwalkError) as exc:
        load_scene(spec, progress=False, **kw)
    msg = str(exc.value)
    assert "\n" not in msg and msg.strip(), repr(msg)
    return msg


def test_missing_file():
    assert "no_such_scene.obj" in _error("no_such_scene.obj")
    assert "deep/none.ply" in _error("/tmp/deep/none.ply")


def test_corrupt_and_empty_files(tmp_path):
    garbage = tmp_path / "garbage.obj"
    garbage.write_bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    assert "garbage.obj" in _error(str(garbage))
    garbage_ply = tmp_path / "garbage.ply"
    garbage_ply.write_bytes(garbage.read_bytes())
    assert "garbage.ply" in _error(str(garbage_ply))
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    assert "empty.ply" in _error(str(empty))
    points = tmp_path / "points.ply"
    points.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                      "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    assert "points.ply" in _error(str(points))
    bad_index = tmp_path / "bad_index.obj"
    bad_index.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    assert "bad_index.obj" in _error(str(bad_index))


def test_no_valid_triangles(tmp_path):
    nan = tmp_path / "nan_only.obj"
    nan.write_text("v nan nan nan\nv nan 1 2\nv 1 nan 3\nv 0 0 inf\nf 1 2 3\nf 2 3 4\n")
    msg = _error(str(nan))
    assert "nan_only.obj" in msg and "no valid triangles" in msg
    flat = tmp_path / "collinear.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    assert "collinear.obj" in _error(str(flat))


@pytest.mark.parametrize("content", [
    "{not json",
    '["a list"]',
    '{"point_lights": [{"position": [1, 2]}]}',
    '{"point_lights": [{"position": [1, 2, 3]}]}',
    '{"rect_lights": [{"corner": [0, 0, 0], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1], "radiance": "bright"}]}',
    '{"camera": {"position": [0, 0, 0], "target": [0, "x", 1]}}',
    '{"mirrors": "glass"}',
    '{"sky_color": [0.1, 0.2]}',
])
def test_bad_sidecar(tmp_path, content):
    obj = _quad_obj(tmp_path)
    (tmp_path / "quad.obj.rtwalk.json").write_text(content)
    assert "quad.obj.rtwalk.json" in _error(str(obj))


def test_unknown_builtin_and_bad_size():
    assert "nosuchcity" in _error("nosuchcity")
    assert "city" in _error("city", scene_size=10)
    assert "room" in _error("room", scene_size=10_000)

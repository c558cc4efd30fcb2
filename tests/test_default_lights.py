"""Default lights of scene files without lights: in free space, lighting what the camera sees.

Checked with Embree (viewer.reference.EmbreeTracer), independent of the NumPy ray caster that
places them: primary rays on a grid from the default camera give the visible samples, shadow rays
to the point light (and to the rect light's centre) say which are lit.
"""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import shared_scene
from viewer.reference import EmbreeTracer

pytestmark = pytest.mark.skipif(not EmbreeTracer.available(), reason="embreex not installed")


def _mesh_file(tmp_path, kind: str) -> str:
    import trimesh

    mesh = trimesh.creation.box() if kind == "box" else trimesh.creation.icosphere(subdivisions=4)
    path = tmp_path / f"{kind}.ply"
    mesh.export(path)
    return str(path)


def _lit_share(scene, light: np.ndarray, grid=(48, 27)) -> tuple[float, int]:
    """(share of the camera's visible samples lit by a point at `light`, number of samples)."""
    emb = EmbreeTracer(scene.triangles)
    o, d = scene.default_camera.primary_rays(*grid)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    r = len(o)
    t, ids = emb.trace(o, d, np.zeros(r), np.full(r, np.inf))
    hit = ids >= 0
    p = o[hit] + t[hit, None].astype(np.float64) * d[hit]
    tri = scene.triangles[ids[hit]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[np.einsum("ij,ij->i", n, d[hit]) > 0] *= -1  # face the viewer, as the shaders do
    to_l = light - p
    facing = np.einsum("ij,ij->i", to_l, n) > 0
    eps = 1e-4 * scene.diagonal
    _, occ = emb.trace(p + eps * n, to_l, np.zeros(len(p)), np.full(len(p), 1.0 - 1e-6), any_hit=True)
    return float((facing & (occ < 0)).mean()), int(hit.sum())


def _inside_closed(mesh_kind: str, x: np.ndarray) -> bool:
    if mesh_kind == "box":  # trimesh box: unit cube centred at the origin
        return bool((np.abs(x) <= 0.5).all())
    return bool(np.linalg.norm(x) <= 1.0)  # icosphere of radius 1 (vertices on the sphere)


@pytest.mark.parametrize("kind", ["box", "sphere"])
def test_closed_objects_get_a_light_outside_that_lights_them(tmp_path, kind):
    from viewer.session import prepare_scene

    prep = prepare_scene(_mesh_file(tmp_path, kind), quiet=True)
    scene = prep.scene
    cam = scene.default_camera.position
    assert not _inside_closed(kind, cam)  # the camera looks at the object from outside
    (pl,) = scene.point_lights
    (rl,) = scene.rect_lights
    assert not _inside_closed(kind, pl.position.astype(np.float64)), pl.position
    assert not _inside_closed(kind, rl.center.astype(np.float64)), rl.center
    share, samples = _lit_share(scene, pl.position.astype(np.float64))
    assert samples > 100 and share > 0.9, (share, samples)
    share_rect, _ = _lit_share(scene, rl.center.astype(np.float64))
    assert share_rect > 0.9
    # the rect light emits towards the object
    assert np.dot(rl.normal, np.zeros(3) - rl.center) > 0


def test_closed_box_render_has_shadow_rays_and_shading(tmp_path):
    """The issue's symptom: flat grey and no shadow rays. Now shadow rays are traced and the lit
    face is not one flat grey."""
    from PIL import Image

    out = tmp_path / "box.png"
    proc = subprocess.run([sys.executable, "-m", "viewer.cli", "render", _mesh_file(tmp_path, "box"),
                           "--effects", "shadows", "--size", "160x90", "-o", str(out)],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    shadows = int(re.search(r"shadows ([0-9,]+)", proc.stderr).group(1).replace(",", ""))
    assert shadows > 1000, proc.stderr
    img = np.asarray(Image.open(out), np.float64)
    centre = img[30:60, 60:100].mean(axis=2)
    sky = img[2, 2].mean()
    assert abs(centre.mean() - sky) > 10  # the object is lit, not the flat ambient grey


@pytest.mark.scenes
@pytest.mark.parametrize("rel", ["bunny/bun_zipper.ply", "sibenik/sibenik.obj", "conference/conference.ply"])
def test_shared_scenes_light_what_the_camera_sees(rel):
    from tests.conftest import prepared_scene

    prep = prepared_scene(shared_scene(rel))
    (pl,) = prep.scene.point_lights
    share, samples = _lit_share(prep.scene, pl.position.astype(np.float64))
    assert samples > 100 and share > 0.6, (rel, share, samples)


def test_ray_caster_matches_embree():
    """viewer.accel.raycast (the light placement's ray caster) against Embree: same first hits and
    the same occlusion answers on random rays through a procedural city."""
    from tests.conftest import prepared_scene
    from viewer.accel.raycast import cast_rays

    prep = prepared_scene("city", 30_000)
    tris = prep.scene.triangles
    rng = np.random.default_rng(7)
    lo, hi = (b.astype(np.float64) for b in prep.scene.bounds)
    o = rng.uniform(lo, hi, (800, 3))
    o[:, 1] = rng.uniform(0.2, 0.5 * hi[1], 800)
    d = rng.normal(size=(800, 3))
    tmax = rng.uniform(0.5, 2.0, 800) * np.linalg.norm(hi - lo) / np.linalg.norm(d, axis=1) * 0.3
    t, ids = cast_rays(prep.bvh, tris, o, d, 0.0, tmax)
    et, eid = EmbreeTracer(tris).trace(o, d, np.zeros(800), tmax)
    assert (ids >= 0).sum() > 200 and (ids < 0).sum() > 50
    assert np.mean(ids == eid) > 0.995
    both = (ids >= 0) & (eid >= 0)
    np.testing.assert_allclose(t[both], et[both], rtol=1e-4, atol=1e-4)
    _, any_ids = cast_rays(prep.bvh, tris, o, d, 0.0, tmax, any_hit=True)
    assert np.mean((any_ids >= 0) == (eid >= 0)) > 0.995

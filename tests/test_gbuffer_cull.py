"""Frustum culling of the G-buffer raster by BVH subtrees (viewer.passes.cull): the cut partitions
the triangle slots, the visible ranges hold every triangle that lies in the view pyramid (checked
per triangle in float64), and the culled G-buffer is the unculled one, pixel for pixel."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from viewer.camera import Camera
from viewer.gl.textures import read_texture
from viewer.passes.cull import bvh_cut, frustum_planes, visible_ranges

SIZE = (96, 54)


@pytest.fixture(scope="module")
def city():
    return prepared_scene("city", 20000)


def _cameras(scene) -> list[Camera]:
    lo, hi = (np.asarray(v, np.float64) for v in scene.bounds)
    c, d = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    street = c + np.array([0.0, -0.45, 0.0]) * (hi - lo)  # low among the buildings
    return [scene.default_camera or Camera.look_at(c + [0, 0, d], c),
            Camera.look_at(street, street + [1.0, 0.05, 0.3]),  # a street view: most of the city is out
            Camera.look_at(street, street + [-0.2, -0.1, -1.0], fov_y=20.0),
            Camera.look_at(c + [0, d * 3, 0.01], c + [0, d * 4, 0.0])]  # looking away: nothing to draw


def test_cut_partitions_the_slots(city):
    bvh = city.bvh
    cut = bvh_cut(bvh, 256)
    n = city.scene.triangle_count
    assert cut.first[0] == 0 and int(cut.count.sum()) == n
    np.testing.assert_array_equal(cut.first[1:], (cut.first + cut.count)[:-1])  # contiguous, disjoint
    np.testing.assert_array_equal(cut.count, bvh.node_count[cut.nodes])
    assert 16 < len(cut.nodes) < 4 * 256 + 64  # a cut, not the root or the leaves


def test_visible_ranges_hold_every_triangle_in_the_pyramid(city):
    """Independent check: each triangle whose float64 vertices reach into the pyramid (clipped
    against the four planes per triangle, by its vertices' convex hull) lies in a drawn range."""
    scene, bvh = city.scene, city.bvh
    cut = bvh_cut(bvh, 512)
    tris = scene.triangles.astype(np.float64)
    n = len(tris)
    culled_any = False
    for cam in _cameras(scene):
        aspect = SIZE[0] / SIZE[1]
        ranges = visible_ranges(cut, bvh.node_min, bvh.node_max, cam, aspect)
        drawn = np.zeros(n, bool)
        for f, c in ranges.tolist():
            drawn[f:f + c] = True
        # a triangle is surely outside when all three vertices are outside one plane
        planes = frustum_planes(cam, aspect, widen=0.0)
        d = np.einsum("tvj,pj->tvp", tris - np.asarray(cam.position), planes)  # (T, 3, 4)
        maybe_inside = ~(d < 0).all(axis=1).any(axis=1)
        assert not (maybe_inside & ~drawn).any()
        culled_any |= drawn.sum() < n
    assert culled_any


def test_culled_gbuffer_equals_the_full_raster(gl_ctx, city):
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    try:
        drawn = []
        for cam in _cameras(city.scene):
            out = {}
            for cull in (False, True):
                r.gbuffer.cull = cull
                r.gbuffer.render(cam)
                out[cull] = [read_texture(t).copy() for t in (r.gbuffer.tri_id, r.gbuffer.position,
                                                               r.gbuffer.normal, r.gbuffer.albedo)]
                if cull:
                    drawn.append(r.gbuffer.drawn_triangles)
            for a, b in zip(out[False], out[True], strict=True):
                np.testing.assert_array_equal(a, b)
        n = city.scene.triangle_count
        assert drawn[-1] == 0  # looking away from the scene
        assert min(drawn[1:3]) < n // 2  # street views draw a fraction of the city
    finally:
        r.release()


def test_traced_gbuffer_equals_the_raster(gl_ctx, city):
    """gbuffer_source "trace" (the backend's primary rays, then the raster's outputs per hit
    triangle) gives the raster's G-buffer: the same triangle per pixel (ties on shared edges
    aside) and, where the triangle is the same, the same position, normal, albedo and depth."""
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        for cam in _cameras(city.scene)[:3]:
            out = {}
            for source in ("raster", "trace"):
                r.gbuffer_source = source
                r.render(cam)
                out[source] = [read_texture(t).copy().reshape(SIZE[1], SIZE[0], -1)
                               for t in (g.tri_id, g.position, g.normal, g.albedo, g.depth)]
            ids_r, ids_t = out["raster"][0], out["trace"][0]
            same = ids_r == ids_t
            assert same.mean() >= 0.995, same.mean()
            assert ((ids_r >= 0) == (ids_t >= 0)).mean() >= 0.999
            for a, b in zip(out["raster"][1:], out["trace"][1:], strict=True):
                np.testing.assert_array_equal(a[same[..., 0]], b[same[..., 0]])
    finally:
        r.release()

"""pgrid far from the origin (issue 18, item 3): a closed mesh moved to 1e6, where float32 snaps it
onto a lattice of 1/16 steps (many triangles collapse to points or segments), traced through the
eye-centred point grid, the camera grid and a light grid, against the float64 reference; and
bounds on the point grid's pairs that catch the old pole-rule explosion (before: every collapsed
triangle was "around" the pole axis and took every azimuth, 8M pairs for the 100k dragon at 1e6).
Also back-face culling in the point grid, applied only where exact."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_grid import F32, _judge, needs_cl, trace_centred
from tests.test_hard_cases import assert_matches
from viewer.effects import RayType

SIZE = (96, 64)


def _sphere(offset: float, subdivisions: int = 4) -> np.ndarray:
    """A closed, outward-facing icosphere of radius 0.3 (edges ~0.02) around (offset, offset,
    offset), float32: at 1e6 (steps of 1/16) most of its triangles collapse."""
    from viewer.procedural import _icosphere

    return _icosphere(subdivisions, 0.3, (offset, offset, offset))


def _pinhole(eye: np.ndarray, target: np.ndarray, size=SIZE, fov_deg: float = 50.0):
    """Row-major pinhole rays from `eye` (float32 origins and unit directions), as bench-grids traces."""
    from viewer.bench.grids_far import primary_rays

    return primary_rays(np.asarray(eye, np.float64), np.asarray(target, np.float64), size, fov_deg)


def _eye_and_target(offset: float) -> tuple[np.ndarray, np.ndarray]:
    c = np.full(3, offset)
    eye = (c + np.array([0.15, 0.2, 0.8])).astype(F32).astype(np.float64)  # on the float32 lattice
    return eye, c


@needs_cl
@pytest.mark.parametrize("offset", [0.0, 1e5, 1e6])
def test_point_grid_primary_far_from_origin(offset):
    """Primary rays through the eye-centred point grid match the float64 reference at every offset,
    and the pairs stay near what the grid needs at the origin (no pole-rule widening)."""
    tris = _sphere(offset)
    eye, target = _eye_and_target(offset)
    o, d = _pinhole(eye, target)
    n = len(o)
    tmin, tmax = np.zeros(n, F32), np.full(n, np.inf, F32)
    t, tri, st = trace_centred(tris, o, d, tmin, tmax, RayType.PRIMARY, params="primary=angular,backface=off")
    collapsed = int(((tris[:, 0] == tris[:, 1]).all(1) & (tris[:, 1] == tris[:, 2]).all(1)).sum())
    if offset == 1e6:
        assert collapsed > 0.2 * len(tris)  # the case this test is about: the lattice collapses the mesh
    assert st["outside_rays"] == 0, st
    assert st["widened"] == 0, st  # no triangle near the eye's up axis here: none takes every azimuth
    assert st["culled"] >= collapsed, st  # a triangle collapsed to a point is never hit: culled
    # every visible triangle lies in a few tiles of the ~n/32 (tile_rays): a bound that the old
    # explosion (every collapsed triangle over all azimuths) exceeds many times over
    assert st["pairs"] <= 3 * len(tris), st
    out = _judge(tris, o, d, tmin, tmax, t, tri, False)
    assert out.rhit.sum() > 0.2 * n
    assert_matches(out)


@needs_cl
@pytest.mark.parametrize("eye", [(0.4e-3, 1.2e-3, 2.5e-3), (3e-4, 2e-5, 1.5e-3)])
def test_point_grid_primary_mixed_scale(eye):
    """The mixed scene in small (bench-grids' `mixed`): a 1e-3 icosphere (5,120 triangles, all
    boxed through their bounding spheres) on a 2e4 ground before a 1e4 wall, primary rays through
    the eye-centred point grid (the bench's layout) from 1e-3 away and from just above the ground
    (grazing it): every hit matches the float64 reference, although each ray now tests only the
    triangles whose angular box holds it and stops at the first staged block beyond its hit."""
    from viewer.bench.grids_far import scene_mixed
    from viewer.procedural import _icosphere

    ball = np.asarray(_icosphere(5, 0.5e-3, (0.0, 0.5e-3, 0.0)), F32).reshape(-1, 3, 3)
    big = scene_mixed()[0][-4:]  # the ground and the wall
    tris = np.concatenate([ball, big])
    o, d = _pinhole(np.asarray(eye), np.array([0.0, 0.5e-3, 0.0]))
    n = len(o)
    tmin, tmax = np.zeros(n, F32), np.full(n, np.inf, F32)
    t, tri, st = trace_centred(tris, o, d, tmin, tmax, RayType.PRIMARY, params="primary=angular")
    assert st["outside_rays"] == 0, st
    out = _judge(tris, o, d, tmin, tmax, t, tri, False)
    hit_ball = np.isin(out.rtri, np.arange(len(ball)))
    assert hit_ball.sum() > 0.05 * n and (out.rtri >= len(ball)).sum() > 0.05 * n  # both scales seen
    # judged at the ball's scale: the default distance tolerance and edge band are relative to the
    # 1e4 scene (8 ulps, 1e-6 x 1e4), wider than the ball, so any hit on it would pass as a tie
    assert_matches(out, abs_tol=8 * float(np.spacing(F32(3e-3))), edge_rel=3e-13)  # edge band 3e-9


@needs_cl
@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_camera_grid_primary_far_from_origin(offset):
    """The same rays as a pinhole image (the camera perspective grid) at the origin and at 1e6."""
    tris = _sphere(offset)
    eye, target = _eye_and_target(offset)
    o, d = _pinhole(eye, target)
    n = len(o)
    tmin, tmax = np.zeros(n, F32), np.full(n, np.inf, F32)
    t, tri, st = trace_centred(tris, o, d, tmin, tmax, RayType.PRIMARY, size=SIZE)
    assert st["pairs"] <= 3 * len(tris), st
    assert_matches(_judge(tris, o, d, tmin, tmax, t, tri, False))


@needs_cl
def test_light_grid_shadow_rays_far_from_origin():
    """Shadow rays from points on the sphere at 1e6 to a light beside it: the light grid is exact."""
    offset = 1e6
    tris = _sphere(offset)
    rng = np.random.default_rng(5)
    light = (np.full(3, offset) + np.array([0.6, 0.75, 0.25])).astype(F32)
    n = 6000
    w = rng.dirichlet([1, 1, 1], n)
    pick = rng.integers(0, len(tris), n)
    p = (w[:, :, None] * tris[pick].astype(np.float64)).sum(1)
    p += rng.normal(scale=0.02, size=p.shape)  # off the surface, both sides
    o = p.astype(F32)  # snapped to the lattice: the direction goes from there (as a renderer's would)
    v = light.astype(np.float64) - o
    dist = np.linalg.norm(v, axis=1)
    d = (v / dist[:, None]).astype(F32)
    tmin, tmax = np.zeros(n, F32), (dist * (1 - 1e-4)).astype(F32)
    t, tri, st = trace_centred(tris, o, d, tmin, tmax, RayType.SHADOW, light=light)
    assert st["outside_rays"] <= 0.01 * n, st
    assert st["pairs"] <= 4 * len(tris), st
    out = _judge(tris, o, d, tmin, tmax, t, tri, True)
    assert 0.1 * n < out.rhit.sum() < 0.95 * n
    assert_matches(out)


@needs_cl
@pytest.mark.parametrize("inside", [False, True])
def test_point_grid_back_face_culling_only_where_exact(inside):
    """backface=auto culls back faces of the closed sphere seen from outside (about half of it) and
    nothing when the eye is inside it; both are exact."""
    tris = _sphere(0.0, subdivisions=3)
    eye = np.array([0.15, 0.2, 0.8]) if not inside else np.array([0.02, 0.05, 0.07])
    eye = eye.astype(F32).astype(np.float64)
    o, d = _pinhole(eye, eye + np.array([-0.2, -0.25, -1.0]) if inside else np.zeros(3), fov_deg=70.0)
    n = len(o)
    tmin, tmax = np.zeros(n, F32), np.full(n, np.inf, F32)
    t, tri, st = trace_centred(tris, o, d, tmin, tmax, RayType.PRIMARY, params="primary=angular")
    if inside:
        assert st["culled_backface"] == 0, st  # the view's frustum only
    else:
        assert st["culled_backface"] > 0.4 * len(tris), st
    assert_matches(_judge(tris, o, d, tmin, tmax, t, tri, False))

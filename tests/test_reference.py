"""The two CPU reference tracers (Embree via embreex, float64 watertight brute force) against each other
and against hand-computed answers."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from viewer.reference import (
    EmbreeTracer,
    compare_hits,
    f32_ulp,
    point_triangle_distance,
    prepare_rays,
    ray_edge_distance,
    trace_float64,
)

F32 = np.float32
INF = np.inf


@pytest.fixture(scope="module")
def embree_ok():
    if not EmbreeTracer.available():
        pytest.fail("embreex is not installed (it is a test dependency: pip install -e .[test])")
    return True


def f32(a):
    return np.ascontiguousarray(np.asarray(a, dtype=F32))


def random_soup(rng, n, size=0.3):
    centres = rng.uniform(-1, 1, size=(n, 1, 3))
    return f32(centres + rng.normal(scale=size, size=(n, 3, 3)))


def random_rays(rng, n, spread=2.5):
    o = rng.uniform(-spread, spread, size=(n, 3))
    target = rng.uniform(-1, 1, size=(n, 3))
    d = (target - o) * rng.uniform(0.05, 20.0, size=(n, 1))     # deliberately not unit length
    return f32(o), f32(d)


def closed_meshes():
    ico = trimesh.creation.icosphere(subdivisions=3)
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    return {"icosphere": f32(ico.triangles), "box": f32(box.triangles)}


def both(tris, o, d, tmin, tmax, any_hit=False):
    te, ie = EmbreeTracer(tris).trace(o, d, tmin, tmax, any_hit=any_hit)
    tf, i_f = trace_float64(tris, o, d, tmin, tmax, any_hit=any_hit)
    return te, ie, tf, i_f


def stats_of(te, ie, tf, i_f, tris, o, d):
    """compare_hits with t tolerance 1e-5 relative + 8 float32 ulps of the coordinates / |d| absolute
    (a hit right next to the origin has a tiny t whose float32 error is relative to the coordinates)."""
    scale = np.maximum(np.abs(o).max(axis=1), np.abs(tris).max())
    abs_tol = 8 * f32_ulp(scale) / np.linalg.norm(d.astype(np.float64), axis=1)
    return compare_hits(te, ie, tf, i_f, tris, rel_tol=1e-5, abs_tol=abs_tol)


def assert_agreement(stats, min_hitmiss=0.999):
    assert stats["hitmiss_agree"] >= min_hitmiss, stats
    assert stats["n_id_mismatch"] <= max(1, int(1e-3 * stats["n_both_hit"])), stats
    # float32 Embree: t error grows like 1/sin(angle) for grazing hits; allow 0.1 % beyond 1e-5
    assert stats["n_t_exceed"] <= max(1, int(1e-3 * stats["n_both_hit"])), stats
    assert stats["n_bad_id"] == 0, stats


def check_contract(t, tri, ntri, tmin, tmax):
    assert t.dtype == np.float32 and tri.dtype == np.int32
    assert t.shape == tri.shape
    hit = tri >= 0
    assert np.all(tri < ntri)
    assert np.all(np.isinf(t[~hit]) & (t[~hit] > 0))
    assert np.all(np.isfinite(t[hit]))
    tmin = np.broadcast_to(tmin, t.shape)
    tmax = np.broadcast_to(tmax, t.shape)
    th = t[hit].astype(np.float64)
    assert np.all(th > tmin[hit]) and np.all(th < tmax[hit])          # strict, on the returned float32


# ----------------------------------------------------------------------------------------------
# float64 reference on hand-made cases
# ----------------------------------------------------------------------------------------------

def test_float64_known_answers():
    tri = f32([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    o = f32([[0.25, 0.25, 2], [0.25, 0.25, -2], [0.25, 0.25, 2], [2, 2, 2], [0.25, 0.25, 2]])
    d = f32([[0, 0, -1], [0, 0, 4], [0, 0, -0.5], [0, 0, -1], [0, 0, 1]])
    t, i = trace_float64(tri, o, d, np.zeros(5, F32), np.full(5, INF, F32))
    np.testing.assert_array_equal(i, [0, 0, 0, -1, -1])
    np.testing.assert_array_equal(t, F32([2.0, 0.5, 4.0, INF, INF]))    # t in units of |d|, back face hit
    check_contract(t, i, 1, 0.0, INF)


@pytest.mark.parametrize("tracer_name", ["float64", "embree"])
def test_returned_t_stays_strictly_inside_the_range(tracer_name):
    """t = 1/3 exactly; tmax = float32(1/3) > 1/3: a hit, but plain float32 rounding gives t == tmax."""
    if tracer_name == "embree" and not EmbreeTracer.available():
        pytest.fail("embreex is not installed")
    tri = f32([[[-1, -1, 0], [2, -1, 0], [-1, 2, 0]]])
    o, d = f32([[0, 0, 1]]), f32([[0, 0, -3]])
    tmax = F32(1 / 3)
    assert float(tmax) > 1 / 3
    if tracer_name == "embree":
        # Embree's own t is a float32 (it computes 1/3 -> tmax): it may call this a miss; never t == tmax
        t, i = EmbreeTracer(tri).trace(o, d, F32(0), tmax)
        assert i[0] == -1 or float(t[0]) < float(tmax)
    else:
        t, i = trace_float64(tri, o, d, F32(0), tmax)
        assert i[0] == 0 and t[0] == np.nextafter(tmax, F32(0))


def test_float64_ties_smallest_t_then_smallest_id():
    a = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    far = [[0, 0, -1], [1, 0, -1], [0, 1, -1]]
    tris = f32([far, a, a, far])                                    # 1 and 2 are duplicates
    t, i = trace_float64(tris, f32([[0.2, 0.2, 1]]), f32([[0, 0, -1]]), F32(0), F32(INF))
    assert i[0] == 1 and t[0] == 1.0


def test_float64_degenerate_triangles_never_hit():
    tris = f32([
        [[0, 0, 0], [1, 0, 0], [0.5, 0, 0]],        # collinear
        [[0, 0, 0], [0, 0, 0], [0, 1, 0]],          # repeated vertex
        [[0.3, 0.3, 0], [0.3, 0.3, 0], [0.3, 0.3, 0]],
        [[-1, -1, -1], [3, -1, -1], [-1, 3, -1]],   # real backdrop
    ])
    o = f32([[0.5, 0, 1], [0, 0.5, 1], [0.3, 0.3, 1], [0, 0, 1], [0.25, 0, 1]])
    d = f32(np.tile([[0, 0, -1]], (5, 1)))
    t, i = trace_float64(tris, o, d, F32(0), F32(INF))
    np.testing.assert_array_equal(i, [3] * 5)
    np.testing.assert_allclose(t, 2.0)


def test_float64_inactive_rays_and_empty_inputs():
    tri = f32([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    o = f32([[0.2, 0.2, 1]] * 6)
    d = f32([[0, 0, -1]] * 5 + [[0, 0, 0]])
    o[3, 0] = np.nan
    d[4, 2] = np.inf
    tmin = f32([0, 0, 1, 0, 0, 0])
    tmax = f32([1, 0, 1, INF, INF, INF])                          # ray 0: hit at t = 1 = tmax -> miss
    t, i = trace_float64(tri, o, d, tmin, tmax)
    np.testing.assert_array_equal(i, [-1] * 6)
    assert np.all(np.isinf(t))
    *_, active = prepare_rays(o, d, tmin, tmax)
    np.testing.assert_array_equal(active, [True, False, False, False, False, False])
    t, i = trace_float64(np.zeros((0, 3, 3), F32), o, d, tmin, tmax)
    assert i.shape == (6,) and np.all(i == -1)
    t, i = trace_float64(tri, np.zeros((0, 3), F32), np.zeros((0, 3), F32), np.zeros(0), np.zeros(0))
    assert t.shape == (0,) and i.shape == (0,) and t.dtype == np.float32 and i.dtype == np.int32


@pytest.mark.parametrize("tracer_name", ["float64", "embree"])
def test_fan_is_watertight(tracer_name):
    """Rays exactly through the shared vertex and shared edges of a fan (dyadic, exact in float32)."""
    if tracer_name == "embree" and not EmbreeTracer.available():
        pytest.fail("embreex is not installed")
    rim = np.array([[1, 0, 0], [0.75, 0.75, 0], [0, 1, 0], [-0.75, 0.75, 0],
                    [-1, 0, 0], [-0.75, -0.75, 0], [0, -1, 0], [0.75, -0.75, 0]])
    tris = f32([[[0, 0, 0.25], rim[k], rim[(k + 1) % 8]] for k in range(8)])
    pts = [[0, 0, 0.25]] + [np.array([0, 0, 0.25]) + (j / 64) * (rim[k] - [0, 0, 0.25])
                            for k in range(8) for j in range(1, 64)]
    pts = np.array(pts)
    for dvec in ([0, 0, -1], [0.25, -0.5, -1], [-0.125, 0.375, 1]):
        dvec = np.array(dvec, float)
        o = f32(pts - 2 * dvec)
        d = f32(np.broadcast_to(dvec, o.shape))
        assert np.all(o.astype(np.float64) + 2 * dvec == pts)          # the rays pass exactly through pts
        if tracer_name == "embree":
            t, i = EmbreeTracer(tris).trace(o, d, F32(0), F32(INF))
        else:
            t, i = trace_float64(tris, o, d, F32(0), F32(INF))
        assert np.all(i >= 0), np.flatnonzero(i < 0)
        np.testing.assert_allclose(t, 2.0, rtol=1e-12 if tracer_name == "float64" else 1e-6)


@pytest.mark.parametrize("origin", [[0, 0, 0], [0.3, -0.2, 0.1]])
def test_closed_mesh_no_leak_through_vertices_and_edges(embree_ok, origin):
    """Rays from inside an icosphere aimed exactly at its vertices and at points on its edges.

    Embree needs its robust mode here: with ``robust=False`` about 10 % of these rays leak."""
    m = trimesh.creation.icosphere(subdivisions=3)
    tris = f32(m.triangles)
    v = f32(m.vertices)
    e = m.edges_unique
    s = f32(np.random.default_rng(0).uniform(0, 1, (len(e), 1)))
    targets = np.concatenate([v, f32(v[e[:, 0]] + s * (v[e[:, 1]] - v[e[:, 0]])),
                              f32(0.5 * (v[e[:, 0]] + v[e[:, 1]]))])
    org = f32(origin)
    d = f32(targets - org)
    o = f32(np.broadcast_to(org, d.shape))
    te, ie, tf, i_f = both(tris, o, d, F32(0), F32(INF))
    assert np.all(i_f >= 0) and np.all(ie >= 0)
    s = stats_of(te, ie, tf, i_f, tris, o, d)
    assert s["n_id_mismatch"] == 0 and s["n_t_exceed"] == 0, s


# ----------------------------------------------------------------------------------------------
# Embree against the float64 reference
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1])
def test_random_soup_embree_vs_float64(embree_ok, seed):
    rng = np.random.default_rng(seed)
    tris = random_soup(rng, 500)
    o, d = random_rays(rng, 40000)
    tmin = np.zeros(len(o), F32)
    tmax = np.full(len(o), INF, F32)
    te, ie, tf, i_f = both(tris, o, d, tmin, tmax)
    check_contract(te, ie, len(tris), tmin, tmax)
    check_contract(tf, i_f, len(tris), tmin, tmax)
    s = stats_of(te, ie, tf, i_f, tris, o, d)
    assert s["n_both_hit"] > 5000
    assert_agreement(s)
    # any disagreement must be explained by an edge within float32 rounding
    bad = np.flatnonzero((ie >= 0) != (i_f >= 0))
    if len(bad):
        tid = np.where(ie[bad] >= 0, ie[bad], i_f[bad])
        dist = ray_edge_distance(tris, tid, o[bad], d[bad])
        assert np.all(dist <= 1e-6 * np.abs(o[bad]).max(axis=1).clip(1.0)), dist


@pytest.mark.parametrize("name", ["icosphere", "box"])
def test_closed_mesh_embree_vs_float64(embree_ok, name):
    tris = closed_meshes()[name]
    rng = np.random.default_rng(7)
    n = 15000
    o_out, d_out = random_rays(rng, n, spread=3.0)
    # rays from inside must all hit (no leak)
    o_in = f32(rng.uniform(-0.2, 0.2, size=(n, 3)))
    d_in = f32(rng.normal(size=(n, 3)) * rng.uniform(0.1, 10, size=(n, 1)))
    o = np.concatenate([o_out, o_in])
    d = np.concatenate([d_out, d_in])
    tmin = np.zeros(2 * n, F32)
    tmax = np.full(2 * n, INF, F32)
    te, ie, tf, i_f = both(tris, o, d, tmin, tmax)
    s = stats_of(te, ie, tf, i_f, tris, o, d)
    assert_agreement(s)
    assert s["n_t_exceed"] == 0, s
    assert np.all(i_f[n:] >= 0) and np.all(ie[n:] >= 0)
    # hit points lie on the reported triangles
    for t, i in ((te, ie), (tf, i_f)):
        h = np.flatnonzero(i >= 0)
        p = o[h].astype(np.float64) + t[h, None].astype(np.float64) * d[h]
        assert np.all(point_triangle_distance(p, tris[i[h]]) <= 1e-5)


def test_any_hit_consistent_with_closest_hit(embree_ok):
    rng = np.random.default_rng(3)
    tris = random_soup(rng, 300)
    o, d = random_rays(rng, 10000)
    tmin = f32(rng.uniform(0, 0.3, len(o)))
    tmax = f32(rng.uniform(0.2, 1.5, len(o)))
    tracer = EmbreeTracer(tris)
    tc, ic = tracer.trace(o, d, tmin, tmax)
    ta, ia = tracer.trace(o, d, tmin, tmax, any_hit=True)
    tf, i_f = trace_float64(tris, o, d, tmin, tmax, any_hit=True)
    check_contract(ta, ia, len(tris), tmin, tmax)
    np.testing.assert_array_equal(ia >= 0, ic >= 0)
    occl = compare_hits(ta, np.where(ia >= 0, 0, -1), tf, np.where(i_f >= 0, 0, -1))
    assert occl["hitmiss_agree"] >= 0.999, occl
    h = np.flatnonzero(ia >= 0)
    assert np.all(ta[h] >= tc[h])                                    # never closer than the closest hit
    p = o[h].astype(np.float64) + ta[h, None].astype(np.float64) * d[h]
    assert np.all(point_triangle_distance(p, tris[ia[h]]) <= 1e-5)   # a genuine hit on that triangle


@pytest.mark.parametrize("tracer_name", ["embree", "float64"])
def test_tmin_tmax_honoured(embree_ok, tracer_name):
    tris = closed_meshes()["icosphere"]
    rng = np.random.default_rng(5)
    n = 2000
    o, d = random_rays(rng, n, spread=3.0)
    if tracer_name == "embree":
        tracer = EmbreeTracer(tris)

        def run(tmin, tmax):
            return tracer.trace(o, d, tmin, tmax)
    else:
        def run(tmin, tmax):
            return trace_float64(tris, o, d, tmin, tmax)

    zero = np.zeros(n, F32)
    t, i = run(zero, np.full(n, INF, F32))
    od = o.astype(np.float64)
    dd = d.astype(np.float64)
    line_dist = np.linalg.norm(np.cross(od, dd), axis=1) / np.linalg.norm(dd, axis=1)
    outside = np.linalg.norm(od, axis=1) > 1.1
    h = np.flatnonzero((i >= 0) & (line_dist < 0.8) & outside)   # chords long enough for the tmin step
    assert len(h) > 200
    th = t[h].astype(np.float64)
    # tmax just below the hit -> miss (the sphere's first hit is its only hit before t)
    below = np.full(n, INF, F32)
    below[h] = f32(th * (1 - 1e-4))
    t2, i2 = run(zero, below)
    assert np.all(i2[h] == -1)
    # tmax just above -> the same hit
    above = np.full(n, INF, F32)
    above[h] = f32(th * (1 + 1e-4))
    t3, i3 = run(zero, above)
    np.testing.assert_array_equal(i3[h], i[h])
    # tmin just above the first hit -> the far side of the sphere (a different, farther hit)
    tmin = zero.copy()
    tmin[h] = f32(th * (1 + 1e-4))
    t4, i4 = run(tmin, np.full(n, INF, F32))
    assert np.all(i4[h] >= 0) and np.all(t4[h] > tmin[h]) and np.all(i4[h] != i[h])
    # tmax <= tmin: inactive
    t5, i5 = run(zero + 1, zero + 1)
    assert np.all(i5 == -1) and np.all(np.isinf(t5))
    t6, i6 = run(zero + 2, zero + 1)
    assert np.all(i6 == -1)


def test_tmin_offset_embree_matches_float64(embree_ok):
    """Embree has no tnear in embreex: the origin is moved to o + tmin d. Results must still agree."""
    tris = closed_meshes()["icosphere"]
    rng = np.random.default_rng(11)
    o, d = random_rays(rng, 6000, spread=3.0)
    tmin = f32(rng.uniform(0, 1.5, len(o)))
    tmax = f32(tmin + rng.uniform(0, 2.0, len(o)))
    te, ie, tf, i_f = both(tris, o, d, tmin, tmax)
    s = stats_of(te, ie, tf, i_f, tris, o, d)
    assert_agreement(s)


def test_axis_parallel_directions(embree_ok):
    tris = np.concatenate([closed_meshes()["box"], random_soup(np.random.default_rng(2), 100)])
    g = np.linspace(-1.3, 1.3, 23)
    gx, gy = np.meshgrid(g, g)
    rays_o, rays_d = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            o = np.zeros((gx.size, 3))
            o[:, axis] = -3.0 * sign
            o[:, (axis + 1) % 3] = gx.ravel()
            o[:, (axis + 2) % 3] = gy.ravel()
            dvec = np.zeros(3)
            dvec[axis] = sign * 0.5
            dvec[(axis + 1) % 3] = -0.0                   # negative zero on purpose
            rays_o.append(o)
            rays_d.append(np.broadcast_to(dvec, o.shape))
    o = f32(np.concatenate(rays_o))
    d = f32(np.concatenate(rays_d))
    assert np.any(np.signbit(d) & (d == 0))
    tmin = np.zeros(len(o), F32)
    tmax = np.full(len(o), INF, F32)
    te, ie, tf, i_f = both(tris, o, d, tmin, tmax)
    s = stats_of(te, ie, tf, i_f, tris, o, d)
    assert_agreement(s, min_hitmiss=0.999)
    # rays aimed at the box (|coords| < extents/2 inside the grid) must hit it in both
    box_half = np.array([1.0, 0.5, 0.25])
    inside = np.ones(len(o), bool)
    for k in range(3):
        inside &= (np.abs(o[:, k]) < box_half[k] - 1e-3) | (d[:, k] != 0)
    assert inside.sum() > 100
    assert np.all(ie[inside] >= 0) and np.all(i_f[inside] >= 0)


def test_embree_empty_inputs_and_inactive(embree_ok):
    empty = EmbreeTracer(np.zeros((0, 3, 3), F32))
    t, i = empty.trace(f32([[0, 0, 1]]), f32([[0, 0, -1]]), F32(0), F32(INF))
    assert t.shape == (1,) and i[0] == -1 and np.isinf(t[0])
    tri = f32([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    tr = EmbreeTracer(tri)
    t, i = tr.trace(np.zeros((0, 3), F32), np.zeros((0, 3), F32), np.zeros(0, F32), np.zeros(0, F32))
    assert t.shape == (0,) and t.dtype == np.float32 and i.dtype == np.int32
    o = f32([[0.2, 0.2, 1]] * 6)
    d = f32([[0, 0, -1]] * 5 + [[0, 0, 0]])
    o[3, 0] = np.nan
    d[4, 2] = np.inf
    tmin = f32([0, 0, 1, 0, 0, 0])
    tmax = f32([1, 0, 1, INF, INF, INF])
    t, i = tr.trace(o, d, tmin, tmax)
    np.testing.assert_array_equal(i, [-1] * 6)
    t, i = tr.trace(f32([[0.2, 0.2, 1]]), f32([[0, 0, -4]]), F32(0), F32(INF))
    assert i[0] == 0 and t[0] == 0.25                                 # units of |d|


def test_raw_rays_keep_the_active_rays_and_cover_their_range(embree_ok):
    """raw_rays: only active rays, each starting a little before o + tmin d and reaching a little past
    tmax (float64 check); time_raw traces them on 1 and 2 threads."""
    tr = EmbreeTracer(f32([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]]))
    o = f32([[0.2, 0.2, 1]] * 5)
    d = f32([[0, 0, -2]] * 4 + [[0, 0, 0]])
    o[3, 0] = np.nan
    tmin = f32([0, 0.25, 1, 0, 0])
    tmax = f32([1, 2, 0.5, 1, 1])
    raw = tr.raw_rays(o, d, tmin, tmax)
    assert len(raw) == 2 and raw.origins.dtype == raw.far.dtype == np.float32
    o64, d64 = o[:2].astype(np.float64), d[:2].astype(np.float64)
    start = o64 + tmin[:2, None] * d64
    back = (start - raw.origins) @ d64[0] / (d64[0] @ d64[0])      # how far before o + tmin d (units of |d|)
    assert np.all(back >= 0) and np.all(back < 1e-4) and back[0] == 0       # tmin = 0: the origin itself
    assert np.all(raw.far >= tmax[:2] - tmin[:2]) and np.all(raw.far < (tmax[:2] - tmin[:2]) * 1.01 + 1e-3)
    for threads in (1, 2):
        wall, cpu = tr.time_raw(raw, any_hit=False, threads=threads)
        assert wall > 0 and cpu >= 0
    assert tr.time_raw(tr.raw_rays(o[2:3], d[2:3], tmin[2:3], tmax[2:3]), any_hit=True) == (0.0, 0.0)


@pytest.mark.parametrize("any_hit", [False, True])
def test_ray_starting_on_a_surface(embree_ok, any_hit):
    """tmin = 0 is strict: a ray starting exactly on a triangle does not hit it (robust Embree reports
    t = 0 hits; EmbreeTracer re-traces those from a nudged start)."""
    tris = f32([[[-1, -1, 0], [2, -1, 0], [-1, 2, 0]], [[-1, -1, -1], [2, -1, -1], [-1, 2, -1]]])
    rng = np.random.default_rng(12)
    p = np.c_[rng.integers(-16, 16, (200, 2)) / 64, np.zeros(200)]
    d = np.c_[rng.uniform(-0.2, 0.2, (200, 2)), -rng.uniform(0.5, 2, 200)]
    o, d = f32(p), f32(d)
    tmax = f32(np.where(np.arange(200) % 2 == 0, INF, 0.5 / np.abs(d[:, 2])))   # odd rays stop short
    te, ie, tf, i_f = both(tris, o, d, F32(0), tmax, any_hit=any_hit)
    np.testing.assert_array_equal(i_f, np.where(np.arange(200) % 2 == 0, 1, -1))
    np.testing.assert_array_equal(ie, i_f)
    np.testing.assert_allclose(te, tf, rtol=1e-6)


def test_embree_skips_degenerate_and_keeps_ids():
    if not EmbreeTracer.available():
        pytest.fail("embreex is not installed")
    tris = f32([
        [[0, 0, 0], [1, 0, 0], [0.5, 0, 0]],
        [[-1, -1, -1], [3, -1, -1], [-1, 3, -1]],
        [[0, 0, 0], [0, 0, 0], [0, 1, 0]],
        [[-1, -1, -2], [3, -1, -2], [-1, 3, -2]],
    ])
    o = f32([[0.5, 0, 1], [0, 0.5, 1]])
    d = f32([[0, 0, -1], [0, 0, -1]])
    t, i = EmbreeTracer(tris).trace(o, d, F32(0), F32(INF))
    np.testing.assert_array_equal(i, [1, 1])
    t, i = EmbreeTracer(tris).trace(o, d, F32(2.5), F32(INF))
    np.testing.assert_array_equal(i, [3, 3])
    np.testing.assert_allclose(t, 3.0, rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# compare_hits
# ----------------------------------------------------------------------------------------------

def test_compare_hits_counts():
    tris = f32(np.arange(5 * 9).reshape(5, 3, 3))
    tris[4] = tris[3][[2, 0, 1]]                                 # 4 duplicates 3 (rotated vertices)
    t_a = F32([1.0, INF, 2.0, 3.0, 5.0, 5.0, 7.0, 1.0])
    i_a = np.int32([0, -1, 1, 2, 3, 1, 4, 0])
    t_b = F32([1.0, 1.0, INF, 3.0000001, 5.5, 5.0, 7.5, 1.000005])
    i_b = np.int32([0, 2, -1, 1, 2, 1, 3, 0])
    s = compare_hits(t_a, i_a, t_b, i_b, tris)
    assert s["n_rays"] == 8
    assert s["n_b_only"] == 1 and s["n_a_only"] == 1 and s["n_both_hit"] == 6
    assert s["hitmiss_agree"] == 6 / 8
    assert s["n_same_id"] == 3                                   # rays 0, 5, 7
    assert s["n_tie"] == 2                                       # ray 3 (same t), ray 6 (duplicate)
    assert s["n_id_mismatch"] == 1                               # ray 4
    assert s["n_t_exceed"] == 2                                  # rays 4 and 6 (t differs by 10%/7%)
    assert not s["ok"]
    assert abs(s["max_rel_err"] - 0.5 / 5.5) < 1e-6
    s2 = compare_hits(t_a, i_a, t_a, i_a, tris)
    assert s2["ok"] and s2["max_rel_err"] == 0.0 and s2["id_agree"] == 1.0
    s3 = compare_hits(F32([]), np.int32([]), F32([]), np.int32([]))
    assert s3["ok"] and s3["n_rays"] == 0


# ----------------------------------------------------------------------------------------------
# range ends decided in float64, whatever Embree's float32 t says
# ----------------------------------------------------------------------------------------------

def _exact_t(tri, o, d):
    """Exact rational plane distance of one ray (Fraction), for the expected answers."""
    from fractions import Fraction

    q = [[Fraction(float(x)) for x in v] for v in np.asarray(tri, np.float64)]
    oo = [Fraction(float(x)) for x in o]
    dd = [Fraction(float(x)) for x in d]
    e1 = [q[1][k] - q[0][k] for k in range(3)]
    e2 = [q[2][k] - q[0][k] for k in range(3)]
    n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
    return sum(n[k] * (q[0][k] - oo[k]) for k in range(3)) / sum(n[k] * dd[k] for k in range(3))


def _range_end_cases(rng, n=300):
    """Rays onto big tilted triangles with tmax (or tmin) at the float32 values next to the exact hit
    distance, and exactly at it where that is a float32: the cases where a float32 t rounds across."""
    from fractions import Fraction

    tris, o_all, d_all, lo_all, hi_all, want = [], [], [], [], [], []
    for i in range(n):
        c = rng.uniform(-3, 3, 3) * (10.0 ** rng.integers(0, 4))
        a, b = rng.normal(size=3), rng.normal(size=3)
        tri = f32([c - 50 * a - 50 * b, c + 100 * a, c + 100 * b])
        o = f32(c + rng.uniform(-0.5, 0.5, 3) + rng.normal(size=3) * rng.choice([1e-3, 1, 30]))
        d = f32(c - o.astype(np.float64) + rng.normal(size=3) * 0.01)
        if i % 5 == 0:                                            # straight down onto z = const, t exact
            tri = f32([[-1e3, -1e3, 0], [1e3, -1e3, 0], [0, 1e3, 0]]) + f32(c * [0, 0, 1])
            o = f32([c[0] * 1e-3, c[1] * 1e-3, c[2] + rng.choice([1.0, 0.7, 3.3e-4])])
            d = f32([0, 0, -rng.choice([1.0, 0.3, 2.5])])
        te = _exact_t(tri, o, d)
        if te <= 0:
            continue
        t32 = np.float32(float(te))
        for end in {np.nextafter(t32, F32(-INF)), t32, np.nextafter(t32, F32(INF))}:
            e = Fraction(float(end))
            for as_tmax in (True, False):
                tris.append(tri)
                o_all.append(o)
                d_all.append(d)
                lo_all.append(F32(0) if as_tmax else end)
                hi_all.append(end if as_tmax else F32(INF))
                want.append(te < e if as_tmax else te > e)
    k = len(tris)
    return (f32(tris), f32(o_all), f32(d_all), f32(lo_all), f32(hi_all), np.array(want), np.arange(k))


class _ShiftedT:
    """An Embree scene whose closest-hit distances come back moved by `steps` float32 steps."""

    def __init__(self, scene, steps: int):
        self.scene = scene
        self.steps = steps

    def run(self, o32, d32, dists=None, query="INTERSECT", output=None):
        res = self.scene.run(o32, d32, dists=dists, query=query, output=output)
        if query == "INTERSECT" and output:
            t = np.asarray(res["tfar"], np.float32)
            for _ in range(abs(self.steps)):
                t = np.nextafter(t, F32(INF) if self.steps > 0 else F32(-INF))
            res["tfar"] = t
        return res


def test_range_ends_decided_in_float64_not_float32(embree_ok):
    """Hits at float32 distances next to tmax / tmin (and exactly at them) are kept or dropped as the
    exact distance says, for the Embree reference and the float64 tracer. Embree's own float32 t is
    then shifted by up to two float32 steps either way (what another CPU's kernel may return, e.g.
    0.99999994 for an exact 1 on AVX2): the reference's decisions must not change, because it
    decides on a float64 distance to the triangle Embree returned, not on Embree's t."""
    rng = np.random.default_rng(21)
    tris, o, d, lo, hi, want, ids = _range_end_cases(rng)
    assert want.sum() > 100 and (~want).sum() > 100
    # every ray against its own triangle (rays of one triangle share a tracer)
    groups = {}
    for k in range(len(tris)):
        groups.setdefault(tris[k].tobytes(), []).append(k)
    results = {}
    for mode in ("plain", "shifted"):
        got_e = np.zeros(len(tris), bool)
        got_f = np.zeros(len(tris), bool)
        for ks in groups.values():
            ks = np.array(ks)
            tri = tris[ks[:1]]
            tracer = EmbreeTracer(tri)
            if mode == "shifted":
                tracer._scene = _ShiftedT(tracer._scene, int(rng.integers(-2, 3)))
            te, ie = tracer.trace(o[ks], d[ks], lo[ks], hi[ks])
            got_e[ks] = ie >= 0
            tf, i_f = trace_float64(tri, o[ks], d[ks], lo[ks], hi[ks])
            got_f[ks] = i_f >= 0
            for tt, ii in ((te, ie), (tf, i_f)):                   # returned t strictly inside the range
                h = ii >= 0
                assert np.all((tt[h] > lo[ks][h]) & (tt[h] < hi[ks][h]))
        results[mode] = got_e
        bad = np.flatnonzero(got_f != want)
        assert len(bad) == 0, f"float64 tracer: {len(bad)} wrong range decisions, e.g. rays {bad[:5]}"
        bad = np.flatnonzero(got_e != want)
        assert len(bad) == 0, (f"Embree reference ({mode} float32 t): {len(bad)} wrong range decisions, e.g. "
                               + "; ".join(f"o={o[k].tolist()} d={d[k].tolist()} range=({lo[k]}, {hi[k]}) "
                                           f"want {want[k]}" for k in bad[:3]))
    assert np.array_equal(results["plain"], results["shifted"])


# ----------------------------------------------------------------------------------------------
# far from the origin: rays that start on a surface
# ----------------------------------------------------------------------------------------------

FAR_SHIFT = np.array([1e6, 0.0, 0.0])


def far_room():
    """The built-in room (10 x 5 x 10, closed, ~3.5k triangles) moved to x = 1e6, where float32 steps
    are 1/16: (triangles float32, point light position float64)."""
    from viewer.procedural import make_room

    room = make_room()
    tris = f32(room.triangles.astype(np.float64) + FAR_SHIFT)
    light = np.asarray(room.point_lights[0].position, np.float64) + FAR_SHIFT
    return tris, light


def _offset_origin(p, n):
    """NumPy copy of offsetRayOrigin (shaders/sampling.glsl): 256 float32 steps along the normal."""
    p = f32(p)
    ofi = (256.0 * n).astype(np.int32)
    bits = p.view(np.int32)
    moved = np.where(p < 0, bits - ofi, bits + ofi).astype(np.int32).view(np.float32)
    return np.where(np.abs(p) < 1 / 32, p + F32(1 / 65536) * f32(n), moved).astype(F32)


def far_surface_rays(tris, light, rng, n=1500):
    """Secondary rays as the pipeline makes them on the far room: from points on random triangles
    (rounded to float32, so they lie within 1/32 of the surface, on either side) and from the same
    points offset like raygen does; AO-length, unbounded and shadow rays (tmax just short of the
    light), tmin 0. Returns (o, d, tmin, tmax) float32."""
    t64 = tris.astype(np.float64)
    area = np.linalg.norm(np.cross(t64[:, 1] - t64[:, 0], t64[:, 2] - t64[:, 0]), axis=1)
    k = rng.choice(np.flatnonzero(area > 0), n)                  # (float32 rounding far out can flatten some)
    v = tris[k].astype(np.float64)
    b = rng.dirichlet([1, 1, 1], n)
    p = (b[:, :, None] * v).sum(axis=1)
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm *= rng.choice([-1.0, 1.0], (n, 1))
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= np.sign((u * nrm).sum(axis=1, keepdims=True))            # hemisphere of the chosen side
    o_list, d_list, hi_list = [], [], []
    for origin in (f32(p), _offset_origin(p, nrm)):
        o_list += [origin, origin]
        d_list += [u, u]
        hi_list += [np.full(n, 0.75), np.full(n, INF)]
        to_light = light - origin.astype(np.float64)
        dist = np.linalg.norm(to_light, axis=1)
        o_list.append(origin)
        d_list.append(to_light / dist[:, None])
        hi_list.append(dist * (1 - 1e-4))
    o = f32(np.concatenate(o_list))
    return o, f32(np.concatenate(d_list)), np.zeros(len(o), F32), f32(np.concatenate(hi_list))


def far_agreement(te, ie, tf, i_f, tris, o, d):
    """Hit/miss and id agreement of (te, ie) with the float64 tracer (tf, i_f), counting a
    disagreement as excused only where the ray passes within 1e-5 of the room's size of an edge of
    either triangle (float32 rounding of the local coordinates); plus hits whose point o + t d is
    not on the reported triangle (1e-5 of the room's size)."""
    extent = float(np.ptp(tris.reshape(-1, 3).astype(np.float64), axis=0).max())
    diff = np.flatnonzero((ie >= 0) != (i_f >= 0))
    da = ray_edge_distance(tris, ie[diff], o[diff], d[diff])
    db = ray_edge_distance(tris, i_f[diff], o[diff], d[diff])
    unexcused = diff[np.minimum(da, db) > 1e-5 * extent]
    h = np.flatnonzero(ie >= 0)
    pts = o[h].astype(np.float64) + te[h, None].astype(np.float64) * d[h].astype(np.float64)
    off = point_triangle_distance(pts, tris[ie[h]])
    st = compare_hits(te, ie, tf, i_f, tris, rel_tol=1e-5, tie_rel=1e-5, abs_tol=8 * f32_ulp(1e6))
    return {"rays": len(o), "hitmiss_agree": st["hitmiss_agree"], "id_agree": st["id_agree"],
            "n_disagree": len(diff), "n_unexcused": len(unexcused), "n_off_triangle": int((off > 1e-5 * extent).sum()),
            "n_id_mismatch": st["n_id_mismatch"]}


@pytest.mark.parametrize("any_hit", [False, True])
def test_far_from_origin_rays_starting_on_surfaces(embree_ok, any_hit):
    """The room at x = 1e6 (float32 step 1/16): rays starting on (within rounding of) its surfaces or
    offset from them as raygen does. The Embree reference must return what the float64 tracer returns
    (hit/miss up to edge rounding, ids up to ties) and only genuine hits; it used to return t = 0 for
    such rays and re-trace from an origin nudged 1/4 unit on, past real hits and through walls."""
    tris, light = far_room()
    rng = np.random.default_rng(31)
    o, d, lo, hi = far_surface_rays(tris, light, rng)
    te, ie = EmbreeTracer(tris).trace(o, d, lo, hi, any_hit=any_hit)
    tf, i_f = trace_float64(tris, o, d, lo, hi)
    st = far_agreement(te, ie, tf, i_f, tris, o, d)
    assert (i_f >= 0).mean() > 0.3 and (i_f < 0).mean() > 0.1, st
    assert st["n_unexcused"] == 0 and st["n_off_triangle"] == 0, st
    if not any_hit:
        assert st["n_id_mismatch"] == 0, st


def main() -> None:
    """Figures for the far-from-origin case (``python3 -m tests.test_reference``): the Embree reference
    against the float64 tracer on the rays of the test above, then the pipeline's own secondary rays of
    the far room rendered by every GL backend, each against both references."""
    from dataclasses import replace

    from viewer.accel.bvh import build_bvh
    from viewer.backends import backend_info, backend_names
    from viewer.camera import Camera
    from viewer.effects import parse_effects
    from viewer.gl.context import shared_context
    from viewer.procedural import make_room
    from viewer.renderer import Renderer

    tris, light = far_room()
    o, d, lo, hi = far_surface_rays(tris, light, np.random.default_rng(31))
    tf, i_f = trace_float64(tris, o, d, lo, hi)
    for any_hit in (False, True):
        te, ie = EmbreeTracer(tris).trace(o, d, lo, hi, any_hit=any_hit)
        st = far_agreement(te, ie, tf, i_f, tris, o, d)
        print(f"surface rays, any_hit={any_hit}: Embree reference vs float64 {st}")
    room = make_room()
    pl = [replace(p, position=f32(p.position + FAR_SHIFT)) for p in room.point_lights]
    rl = [replace(r, corner=f32(r.corner + FAR_SHIFT)) for r in room.rect_lights]
    cam = Camera(room.default_camera.position + FAR_SHIFT, room.default_camera.orientation, room.default_camera.fov_y)
    scene = replace(room, triangles=tris, point_lights=pl, rect_lights=rl, default_camera=cam)
    bvh = build_bvh(scene.triangles)
    scene = scene.reordered(bvh.tri_order)
    embree = EmbreeTracer(scene.triangles)
    ctx = shared_context()
    for name in backend_names():
        if backend_info(name).device != "gl":
            continue
        r = Renderer(ctx, scene, bvh, (160, 90), name, parse_effects("shadows,soft:1,ao:1,diffuse:1,reflections"))
        r.render(cam)
        rep = r.render(cam, capture=True)
        r.release()
        for cp in rep.captured:
            a = cp.rays.active
            oo, dd, ll, hh = cp.rays.origins[a], cp.rays.directions[a], cp.rays.tmin[a], cp.rays.tmax[a]
            te, ie = embree.trace(oo, dd, ll, hh, any_hit=cp.ray_type.any_hit)
            tf, i_f = trace_float64(scene.triangles, oo, dd, ll, hh)
            agree = [compare_hits(x, y, tf, i_f)["hitmiss_agree"] for x, y in ((te, ie), (cp.t[a], cp.tri[a]))]
            vs_embree = compare_hits(cp.t[a], cp.tri[a], te, ie)["hitmiss_agree"]
            print(f"far room 160x90 {name:6s} {cp.ray_type.label:11s} {int(a.sum()):6d} rays: hit/miss agreement "
                  f"{name} vs Embree reference {vs_embree:.4%}, Embree reference vs float64 {agree[0]:.4%}, "
                  f"{name} vs float64 {agree[1]:.4%}")


if __name__ == "__main__":
    main()

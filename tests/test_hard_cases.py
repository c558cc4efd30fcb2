"""Hard cases for every registered backend (``viewer.backends.backend_names()``, traced through
``viewer.tracing.trace_rays``) against the float64 watertight reference
(``viewer.reference.trace_float64``) on the same float32 inputs. The Embree reference backend runs
them too: it is the judge elsewhere, so it must meet the same bars. Backends skip only where they
cannot run (an OpenCL backend without an OpenCL device) or are approximate by design
(``info.exact`` False); see ``tests.conftest.backend_params``.

Shared convention (see ``viewer.reference``): ``t`` in units of ``|d|``, ``+inf``/-1 on a miss, hits only
for ``tmin < t < tmax``, inactive rays (``tmax <= tmin``, non-finite data, zero direction) miss.

What counts as agreement (``assert_matches``):

* hit/miss must agree, except where the ray passes within ``edge_rel`` (default 1e-6) times the
  coordinate magnitude of an edge of the triangle either tracer reports: there the answer depends on
  float32 rounding (a few ulps) and either is accepted. The distance is measured between the ray's
  line and the edge (``ray_edge_distance``), which also covers grazing rays, whose in-plane hit point
  is ill-conditioned. "No leak" cases pass ``must_hit``: those rays must hit, no excuse.
* ids must agree, or be a tie: another triangle met at the same distance (shared edge/vertex).
* ``t`` within ``rel_tol * t + abs_tol`` where ``abs_tol`` defaults to 8 float32 ulps of the coordinate
  magnitude divided by ``|d|`` (relevant only far from the origin).
* every reported hit is a genuine one: ``o + t d`` lies on the reported triangle (within 1e-4 of the
  scene extent plus 16 ulps of the coordinates / sin(angle between ray and plane)),
  ``tmin < t < tmax``, the id is valid and not a degenerate triangle; ``t`` is never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import trimesh

from tests.conftest import backend_params, checked_backend, reference_float64
from viewer.reference import (
    compare_hits,
    f32_ulp,
    point_triangle_distance,
    prepare_rays,
    ray_edge_distance,
    trace_float64,
)

try:
    from viewer.tracing import trace_rays
    _IMPORT_ERROR: Exception | None = None
except Exception as exc:  # the module under test is missing or broken: every test must error, not skip
    trace_rays = None
    _IMPORT_ERROR = exc

F32 = np.float32
INF = np.inf


@pytest.fixture(scope="module", params=backend_params(reference=True))
def backend(request):
    """Every registered backend, the reference (Embree) included: all are judged by the float64 tracer."""
    if trace_rays is None:
        raise RuntimeError(f"viewer.tracing.trace_rays cannot be imported "
                           f"({type(_IMPORT_ERROR).__name__}: {_IMPORT_ERROR})") from _IMPORT_ERROR
    return checked_backend(request.param)


def f32(a):
    return np.ascontiguousarray(np.asarray(a, dtype=F32))


# ----------------------------------------------------------------------------------------------
# running and judging a case
# ----------------------------------------------------------------------------------------------

@dataclass
class Outcome:
    tris: np.ndarray
    o: np.ndarray
    d: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    t: np.ndarray          # tracer under test
    tri: np.ndarray
    rt: np.ndarray         # float64 reference
    rtri: np.ndarray
    any_hit: bool

    @property
    def hit(self):
        return self.tri >= 0

    @property
    def rhit(self):
        return self.rtri >= 0

    def describe(self, rays, limit=8) -> str:
        lines = []
        for r in np.asarray(rays)[:limit]:
            lines.append(f"  ray {r}: o={self.o[r].tolist()} d={self.d[r].tolist()} "
                         f"range=({self.tmin[r]}, {self.tmax[r]}) tested=({self.t[r]}, {self.tri[r]}) "
                         f"reference=({self.rt[r]}, {self.rtri[r]})")
        more = len(rays) - limit
        return "\n".join(lines) + (f"\n  ... and {more} more" if more > 0 else "")


def run_case(backend, tris, o, d, tmin=0.0, tmax=INF, any_hit=False) -> Outcome:
    tris = f32(tris).reshape(-1, 3, 3)
    o = f32(o).reshape(-1, 3)
    d = f32(d).reshape(-1, 3)
    tmin = f32(np.broadcast_to(np.asarray(tmin, F32), (len(o),)))
    tmax = f32(np.broadcast_to(np.asarray(tmax, F32), (len(o),)))
    t, tri = trace_rays(tris, o, d, tmin, tmax, any_hit=any_hit, backend=backend)
    t = np.asarray(t)
    tri = np.asarray(tri)
    rt, rtri = reference_float64(tris, o, d, tmin, tmax)
    out = Outcome(tris, o, d, tmin, tmax, t, tri, rt, rtri, any_hit)
    check_contract(out)
    return out


def coord_scale(out: Outcome, rays=None) -> np.ndarray:
    """Per-ray coordinate magnitude: max |coordinate| of the origin and of the whole scene (>= 1e-30)."""
    rays = np.arange(len(out.o)) if rays is None else rays
    scene = float(np.abs(out.tris).max()) if len(out.tris) else 0.0
    return np.maximum(np.abs(out.o[rays].astype(np.float64)).max(axis=1), scene).clip(1e-30)


def check_contract(out: Outcome):
    """Shapes, dtypes and the validity of every reported hit."""
    n = len(out.o)
    assert out.t.shape == (n,) and out.tri.shape == (n,), (out.t.shape, out.tri.shape)
    assert out.t.dtype == np.float32, out.t.dtype
    assert out.tri.dtype == np.int32, out.tri.dtype
    assert not np.isnan(out.t).any(), "NaN distances:\n" + out.describe(np.flatnonzero(np.isnan(out.t)))
    miss = ~out.hit
    bad = np.flatnonzero(miss & ~(np.isposinf(out.t)))
    assert len(bad) == 0, "a miss must report t = +inf:\n" + out.describe(bad)
    assert np.all(out.tri < len(out.tris)) and np.all(out.tri >= -1), "triangle id out of range"
    h = np.flatnonzero(out.hit)
    bad = h[~np.isfinite(out.t[h])]
    assert len(bad) == 0, "a hit must have a finite t:\n" + out.describe(bad)
    th = out.t[h].astype(np.float64)
    bad = h[~((th > out.tmin[h]) & (th < out.tmax[h]))]
    assert len(bad) == 0, "hit outside (tmin, tmax):\n" + out.describe(bad)
    *_, active = prepare_rays(out.o, out.d, out.tmin, out.tmax)
    bad = np.flatnonzero(out.hit & ~active)
    assert len(bad) == 0, "an inactive ray reported a hit:\n" + out.describe(bad)
    if len(h):
        p = out.o[h].astype(np.float64) + th[:, None] * out.d[h].astype(np.float64)
        tv = out.tris[out.tri[h]].astype(np.float64)
        dist = point_triangle_distance(p, tv)
        # a float32 t is off by a few ulps of the coordinates / sin(angle to the plane) along the ray
        nrm = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
        dh = out.d[h].astype(np.float64)
        sin = np.abs((nrm * dh).sum(axis=1)) / (np.linalg.norm(nrm, axis=1) * np.linalg.norm(dh, axis=1))
        extent = np.ptp(out.tris.reshape(-1, 3), axis=0).max()
        tol = 1e-4 * extent + 16 * f32_ulp(coord_scale(out, h)) / sin.clip(1e-30)
        bad = h[~(dist <= tol)]
        assert len(bad) == 0, ("hit point o + t d is not on the reported triangle:\n" + out.describe(bad)
                               + f"\n  distances {dist[~(dist <= tol)][:8]}")
        deg = np.linalg.norm(np.cross(out.tris[:, 1].astype(np.float64) - out.tris[:, 0],
                                      out.tris[:, 2].astype(np.float64) - out.tris[:, 0]), axis=1) == 0
        bad = h[deg[out.tri[h]]]
        assert len(bad) == 0, "a degenerate (zero-area) triangle was reported as hit:\n" + out.describe(bad)


def near_edge(out: Outcome, rays, edge_rel) -> np.ndarray:
    """Rays (subset) passing within edge_rel * coordinate magnitude of an edge of either reported triangle."""
    rays = np.asarray(rays, dtype=np.int64)
    if len(rays) == 0 or edge_rel <= 0:
        return np.zeros(len(rays), bool)
    da = ray_edge_distance(out.tris, out.tri[rays], out.o[rays], out.d[rays])
    db = ray_edge_distance(out.tris, out.rtri[rays], out.o[rays], out.d[rays])
    return np.minimum(da, db) <= edge_rel * coord_scale(out, rays)


def assert_matches(out: Outcome, must_hit=None, edge_rel=1e-6, rel_tol=1e-5, abs_tol=None,
                   excuse=None, check_ids=None):
    """Assert agreement with the reference (see the module docstring). Returns compare_hits' dict.

    ``must_hit``: bool (R,) rays that must hit (no excuse). ``excuse``: bool (R,) rays whose hit/miss
    is not judged (documented per case). ``check_ids``: default True for closest-hit, False for any-hit.
    """
    n = len(out.o)
    if check_ids is None:
        check_ids = not out.any_hit
    excuse = np.zeros(n, bool) if excuse is None else np.asarray(excuse, bool)
    if abs_tol is None:
        abs_tol = 8 * f32_ulp(coord_scale(out)) / np.linalg.norm(out.d.astype(np.float64), axis=1).clip(1e-30)
    if must_hit is not None:
        must_hit = np.asarray(must_hit, bool)
        leak = np.flatnonzero(must_hit & ~out.hit)
        assert len(leak) == 0, f"{len(leak)} rays that must hit missed (leak):\n" + out.describe(leak)

    disagree = np.flatnonzero((out.hit != out.rhit) & ~excuse)
    ok = near_edge(out, disagree, edge_rel)
    bad = disagree[~ok]
    assert len(bad) == 0, (f"{len(bad)} hit/miss disagreements with the reference away from any edge:\n"
                           + out.describe(bad))

    stats = compare_hits(out.t, out.tri, out.rt, out.rtri, out.tris, rel_tol=rel_tol, tie_rel=rel_tol,
                         abs_tol=abs_tol)
    if check_ids:
        both = out.hit & out.rhit & ~excuse
        scale = np.maximum(np.abs(out.t.astype(np.float64)), np.abs(out.rt.astype(np.float64)))
        with np.errstate(invalid="ignore"):
            close = np.abs(out.t.astype(np.float64) - out.rt) <= rel_tol * scale + abs_tol
        same_or_tie = (out.tri == out.rtri) | close
        cand = np.flatnonzero(both & ~same_or_tie)
        bad = cand[~near_edge(out, cand, edge_rel)]
        assert len(bad) == 0, (f"{len(bad)} rays hit a different triangle at a different distance:\n"
                               + out.describe(bad))
        same = np.flatnonzero(both & (out.tri == out.rtri))
        bad = same[~close[same]]
        assert len(bad) == 0, f"{len(bad)} rays: same triangle, distance off:\n" + out.describe(bad)
    return stats


# ----------------------------------------------------------------------------------------------
# scenes (all vertex coordinates dyadic where rays must pass exactly through them)
# ----------------------------------------------------------------------------------------------

RIM = np.array([[1, 0, 0], [0.75, 0.75, 0], [0, 1, 0], [-0.75, 0.75, 0],
                [-1, 0, 0], [-0.75, -0.75, 0], [0, -1, 0], [0.75, -0.75, 0]], float)


def fan(apex_z):
    c = np.array([0.0, 0.0, apex_z])
    return f32([[c, RIM[k], RIM[(k + 1) % 8]] for k in range(8)]), c


def fan_points(apex_z, steps=64, rng=None):
    """Shared vertex, dyadic points on the 8 shared spokes (midpoints included) and on the rim edges."""
    c = np.array([0.0, 0.0, apex_z])
    shared = [c] + [c + (j / steps) * (RIM[k] - c) for k in range(8) for j in range(1, steps)]
    rim = [RIM[k] + (j / steps) * (RIM[(k + 1) % 8] - RIM[k]) for k in range(8) for j in range(0, steps)]
    return np.array(shared), np.array(rim)


def dyadic_box(half=(1.0, 0.75, 0.5), centre=(0.0, 0.0, 0.0)):
    m = trimesh.creation.box(extents=2 * np.asarray(half))
    m.apply_translation(centre)
    return m


def mesh_targets(m, rng, steps=16):
    """Vertices, dyadic points on every edge (incl. face diagonals), float32-rounded random edge points."""
    v = np.asarray(m.vertices, np.float64)
    e = m.edges_unique
    dy = np.concatenate([v[e[:, 0]] + (j / steps) * (v[e[:, 1]] - v[e[:, 0]]) for j in range(1, steps)])
    s = rng.uniform(0, 1, (len(e), 1))
    rnd = f32(v[e[:, 0]] + s * (v[e[:, 1]] - v[e[:, 0]]))
    return np.concatenate([v, dy, rnd])


def fibonacci_dirs(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


def random_soup(rng, n, size=0.3):
    centres = rng.uniform(-1, 1, size=(n, 1, 3))
    return f32(centres + rng.normal(scale=size, size=(n, 3, 3)))


# ----------------------------------------------------------------------------------------------
# cases
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("apex_z", [0.0, 0.25], ids=["planar", "cone"])
def test_fan_shared_vertex_and_edges(backend, apex_z):
    """Rays exactly through the fan's shared vertex and through points of its shared edges: no ray may
    miss. Rays through the unshared rim edges are compared with the reference (edge excuse applies:
    whether a boundary edge is inclusive is rounding-dependent, and no leak is possible there)."""
    tris, _ = fan(apex_z)
    shared, rim = fan_points(apex_z)
    dirs = [[0, 0, -1], [0.25, -0.5, -1], [-0.125, 0.375, 1], [0, 0, 0.5], [0.5, 0.5, -2]]
    o_all, d_all, must = [], [], []
    for dvec in dirs:
        dvec = np.array(dvec, float)
        for pts, is_shared in ((shared, True), (rim, False)):
            o = pts - 2 * dvec
            assert np.array_equal(f32(o).astype(np.float64) + 2 * dvec, pts)   # exactly through pts
            o_all.append(o)
            d_all.append(np.broadcast_to(dvec, o.shape))
            must.append(np.full(len(o), is_shared))
    out = run_case(backend, tris, np.concatenate(o_all), np.concatenate(d_all))
    must = np.concatenate(must)
    assert out.rhit[must].all()                       # sanity: the reference has no leak
    assert_matches(out, must_hit=must)
    np.testing.assert_allclose(out.t[must], 2.0, rtol=1e-6)


@pytest.mark.parametrize("mesh", ["icosphere", "box"])
def test_closed_mesh_no_leak(backend, mesh):
    """Rays from inside a closed mesh through its vertices and edges must hit (no leak out); rays from
    outside aimed at its vertices and edges must hit."""
    rng = np.random.default_rng(1)
    m = trimesh.creation.icosphere(subdivisions=2) if mesh == "icosphere" else dyadic_box()
    tris = f32(m.triangles)
    targets = mesh_targets(m, rng)
    o_list, d_list = [], []
    for org in ([0, 0, 0], [0.25, -0.125, 0.0625], rng.uniform(-0.3, 0.3, 3)):
        org = f32(org)
        o_list.append(np.broadcast_to(org, targets.shape))
        d_list.append(f32(targets - org))
    n_inside = sum(len(x) for x in o_list)
    # from outside: origin 3x further out along the target's position, slightly perturbed
    o_out = f32(3 * targets + rng.normal(scale=0.05, size=targets.shape))
    o_list.append(o_out)
    d_list.append(f32(targets - o_out) * f32(rng.uniform(0.2, 5, (len(targets), 1))))
    out = run_case(backend, tris, np.concatenate(o_list), np.concatenate(d_list))
    assert out.rhit.all()                             # sanity: every ray of this case hits the reference
    must = np.ones(len(out.o), bool)
    assert_matches(out, must_hit=must)
    assert n_inside > 0


def test_axis_parallel_rays(backend):
    """Directions with components exactly 0, including -0.0, on a grid that includes the box's edges
    and face diagonals (dyadic), plus a random soup."""
    rng = np.random.default_rng(2)
    box = f32(dyadic_box().triangles)
    tris = np.concatenate([box, random_soup(rng, 60)])
    g = np.arange(-1.25, 1.25 + 1e-9, 0.0625)
    gx, gy = np.meshgrid(g, g)
    o_list, d_list, must = [], [], []
    half = np.array([1.0, 0.75, 0.5])
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            for zero in (0.0, -0.0):
                o = np.zeros((gx.size, 3))
                o[:, axis] = -3.0 * sign
                o[:, a1] = gx.ravel()
                o[:, a2] = gy.ravel()
                dvec = np.array([zero, zero, zero])
                dvec[axis] = sign * 0.75
                o_list.append(o)
                d_list.append(np.broadcast_to(dvec, o.shape))
                must.append((np.abs(o[:, a1]) < half[a1]) & (np.abs(o[:, a2]) < half[a2]))
    d = f32(np.concatenate(d_list))
    assert np.any((d == 0) & np.signbit(d)) and np.any((d == 0) & ~np.signbit(d))
    out = run_case(backend, tris, np.concatenate(o_list), d)
    must = np.concatenate(must)
    assert out.rhit[must].all()
    assert_matches(out, must_hit=must)


@pytest.mark.parametrize("eps", [1e-1, 1e-3, 1e-5])
def test_grazing_rays(backend, eps):
    """Rays nearly parallel to a tilted quad (two triangles), crossing its plane on or near its edges.

    Hit/miss is compared with the reference; a disagreement is excused only where the ray passes within
    1e-6 x coordinate magnitude of an edge (ray-to-edge distance, see the module docstring). Rays through
    the middle part of the shared diagonal must hit."""
    rng = np.random.default_rng(int(-np.log10(eps)))
    q = np.array([[0, 0, 0], [1, 0, 0.25], [1, 1, 0.5], [0, 1, 0.25]], float)
    tris = f32([[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
    n = np.cross(q[1] - q[0], q[3] - q[0])
    n /= np.linalg.norm(n)
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)]
    pts, on_diag = [], []
    for a, b in edges:
        ev = q[b] - q[a]
        side = np.cross(n, ev)
        side /= np.linalg.norm(side)
        s = rng.uniform(0.05, 0.95, 120)
        off = rng.choice([0, 0, 1e-7, -1e-7, 1e-6, -1e-6, 1e-4, -1e-4, 1e-2, -1e-2], 120)
        pts.append(q[a] + s[:, None] * ev + off[:, None] * side)
        on_diag.append(np.full(120, (a, b) == (0, 2)) & (s > 0.2) & (s < 0.8) & (np.abs(off) <= 1e-6))
    pts = np.concatenate(pts)
    on_diag = np.concatenate(on_diag)
    # in-plane direction (random azimuth) tilted by eps towards the plane, from either side
    u = rng.normal(size=(len(pts), 3))
    u -= (u @ n)[:, None] * n
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    side = rng.choice([-1.0, 1.0], (len(pts), 1))
    d = u - side * eps * n
    o = pts - 1.5 * d
    out = run_case(backend, tris, o, d * rng.uniform(0.5, 2, (len(pts), 1)))
    must = on_diag & out.rhit
    assert must.sum() > 20
    # t of a grazing hit is ill-conditioned (relative error ~ 1e-7 / eps for a float32 tracer)
    assert_matches(out, must_hit=must, rel_tol=1e-5 + 2e-6 / eps)


def test_translated_scene(backend):
    """Everything moved by (1e5, -1e5, 5e4): the fan and box cases stay exact (dyadic coordinates
    representable at that magnitude), random rays on an icosphere compare with the reference. Float32
    spacing there is 2^-7, so distance tolerances include 8 ulps of the coordinates (abs_tol) and the
    edge excuse is 1e-6 x 1e5 = 0.1 units (as for any scene, relative to the coordinate magnitude)."""
    shift = np.array([1e5, -1e5, 5e4])
    rng = np.random.default_rng(4)
    # fan, steps of 1/16 so that every point stays exact after the shift
    tris_f, _ = fan(0.25)
    shared, _ = fan_points(0.25, steps=16)
    dvec = np.array([0.25, -0.5, -1.0])
    o_fan = shared - 2 * dvec + shift
    assert np.array_equal(f32(o_fan).astype(np.float64), o_fan)
    assert np.array_equal(f32(tris_f.astype(np.float64) + shift).astype(np.float64), tris_f + shift)
    # box, from inside through vertices and dyadic edge points
    box = dyadic_box()
    tgt = mesh_targets(box, rng, steps=16)[: len(box.vertices) + 15 * len(box.edges_unique)]
    o_box = np.broadcast_to(np.array([0.25, -0.125, 0.0625]), tgt.shape)
    # icosphere, random rays
    ico = trimesh.creation.icosphere(subdivisions=2)
    o_ico = rng.uniform(-3, 3, (3000, 3))
    d_ico = rng.uniform(-0.8, 0.8, (3000, 3)) - o_ico
    ico_tris = ico.triangles + np.array([4.0, 0, 0])
    o_ico = o_ico + np.array([4.0, 0, 0])

    tris = f32(np.concatenate([tris_f + shift, box.triangles + shift, ico_tris + shift]))
    o = np.concatenate([o_fan, o_box + shift, o_ico + shift])
    d = np.concatenate([np.broadcast_to(dvec, o_fan.shape), tgt - o_box, d_ico])
    out = run_case(backend, tris, o, d)
    n_fan, n_box = len(o_fan), len(o_box)
    must = np.zeros(len(o), bool)
    must[: n_fan + n_box] = True
    assert out.rhit[must].all()
    assert_matches(out, must_hit=must)


def test_huge_triangles_shared_edge_near_the_origin(backend):
    """Mixed scale: a 2e4-wide ground of two triangles whose shared edge passes 1.5e-3 from the ray
    origins (1.2e-3 above it), with a 1e-3 box standing on it. The float32 test moves that edge by
    up to a few ulps of 1.4e4 (~1e-3): an acceleration structure that lists only the triangle a ray
    hits exactly loses the rays the float test gives to the other one. Every ray going down must hit
    (the ground is one closed surface for them), whichever ground triangle it reports."""
    rng = np.random.default_rng(11)
    g = 1e4
    ground = np.array([[[-g, 0, -g], [g, 0, -g], [g, 0, g]], [[-g, 0, -g], [g, 0, g], [-g, 0, g]]])
    box = dyadic_box().triangles * 1e-3 / 2 + np.array([0.0, 0.5e-3, 0.0])  # standing on the ground
    tris = f32(np.concatenate([ground, box]))
    eye = np.array([0.4e-3, 1.2e-3, 2.5e-3])
    n = 4000
    d = rng.normal(size=(n, 3))
    d[:, 1] = -np.abs(d[:, 1]) - 0.05  # downwards
    o = np.broadcast_to(eye, (n, 3)).copy()
    o[n // 2:] += rng.normal(scale=1e-3, size=(n - n // 2, 3)) * [1, 0, 1]  # other origins at that height
    out = run_case(backend, tris, o, d)
    assert out.rhit.all()
    assert_matches(out, must_hit=np.ones(n, bool))


@pytest.mark.parametrize("where", ["near_origin", "magnitude_one"])
def test_tiny_triangles(backend, where):
    """Triangles of size 1e-6 hit at their centres: along -z (exact transverse position) and, near the
    origin, obliquely from 1e-3 away. No edge excuse: the centres are >= 4 float32 ulps from any edge."""
    rng = np.random.default_rng(5)
    n = 400
    if where == "near_origin":
        base = rng.uniform(-1e-3, 1e-3, (n, 3))
    else:
        base = rng.uniform(0.5, 0.99, (n, 3)) * rng.choice([-1, 1], (n, 3))
    # well-shaped triangles of size ~1e-6, random orientation
    ang = rng.uniform(0, 2 * np.pi, n)
    rot = np.stack([np.c_[np.cos(ang + k * 2 * np.pi / 3), np.sin(ang + k * 2 * np.pi / 3),
                          rng.uniform(-0.3, 0.3, n)] for k in range(3)], axis=1)
    tris = f32(base[:, None, :] + 0.6e-6 * rot)
    c = tris.astype(np.float64).mean(axis=1)
    o_list = [np.c_[c[:, 0], c[:, 1], c[:, 2] + 1.0]]          # straight down through (cx, cy)
    d_list = [np.broadcast_to([0.0, 0.0, -1.0], (n, 3))]
    if where == "near_origin":
        dv = rng.normal(size=(n, 3))
        dv[:, 2] = -np.abs(dv[:, 2]) - 0.5
        o_list.append(c - 1e-3 * dv)
        d_list.append(dv)
    o = np.concatenate(o_list)
    d = np.concatenate(d_list)
    o[:n, :2] = f32(c[:, :2])                                 # the rays' (x, y) are the rounded centres
    out = run_case(backend, tris, o, d)
    assert out.rhit.mean() > 0.95
    ids = np.concatenate([np.arange(n)] * len(o_list))
    must = out.rhit & (out.rtri == ids)
    assert_matches(out, must_hit=must, edge_rel=0.0)


def test_degenerate_triangles_never_hit(backend):
    """Collinear, repeated-vertex and single-point triangles in front of a backdrop; rays through their
    vertices and along their segments, several directions including ones in their line's planes."""
    degenerate = f32([
        [[0, 0, 0], [0.5, 0, 0], [0.25, 0, 0]],                  # collinear
        [[0, 0, 0], [0, 0.5, 0], [0, 0.5, 0]],                   # repeated vertex
        [[0.25, 0.25, 0], [0.25, 0.25, 0], [0.25, 0.25, 0]],     # a point
        [[-0.5, -0.5, 0.25], [0.5, 0.5, 0.25], [0, 0, 0.25]],    # collinear, diagonal
        [[0, -0.5, 0.125], [0, -0.5, 0.5], [0, -0.5, 0.25]],     # collinear along z (parallel to some rays)
    ])
    backdrop = f32([[[-2, -2, -1], [2, -2, -1], [2, 2, -1]], [[-2, -2, -1], [2, 2, -1], [-2, 2, -1]]])
    tris = np.concatenate([degenerate, backdrop])
    pts = []
    for t in degenerate.astype(np.float64):
        for j in range(0, 9):
            pts.append(t[0] + (j / 8) * (t[1] - t[0]))
            pts.append(t[1] + (j / 8) * (t[2] - t[1]))
    pts = np.array(pts)
    o_list, d_list = [], []
    for dvec in ([0, 0, -1], [0.5, 0, -1], [0, -0.25, -1], [0.125, 0.25, -0.5]):
        dvec = np.array(dvec, float)
        o_list.append(pts - 2 * dvec)
        d_list.append(np.broadcast_to(dvec, pts.shape))
    out = run_case(backend, tris, np.concatenate(o_list), np.concatenate(d_list))
    assert not np.isin(out.rtri, np.arange(len(degenerate))).any()
    assert not np.isin(out.tri, np.arange(len(degenerate))).any(), "a degenerate triangle was hit"
    assert out.rhit.all()
    assert_matches(out, must_hit=np.ones(len(out.o), bool))


def collinear_probe(seed: int = 1, n_rays: int = 3072):
    """Issue 18's probe: float32 triangles with three distinct, exactly collinear vertices among
    genuine ones and slivers, and rays aimed at points of the collinear segments (the float32
    edge functions of such a triangle need not cancel: every backend reported hits on them).
    Returns (triangles, origins, directions, degenerate mask)."""
    rng = np.random.default_rng(seed)
    q = 2.0 ** -20
    n = 48
    a = np.round(rng.uniform(-1, 1, (n, 3)) / q) * q
    e = np.round(rng.uniform(-0.5, 0.5, (n, 3)) / q) * q
    k = rng.integers(1, 4, n)[:, None]
    exact_edges = np.stack([a, a + e, a + (1 + k) * e], 1)              # float32 edges
    u = rng.integers(-3, 4, (16, 3)).astype(np.float64)
    u[np.abs(u).sum(1) == 0] = [1, 2, 3]
    s = np.array([2.0 ** -40, 1.0, 3.0])
    wide = s[None, :, None] * u[:, None, :]                              # edges not float32
    sliver = exact_edges[:16].copy()
    sliver[:, 2, 0] += q                                                 # off the line by 2^-20
    good = rng.uniform(-1.5, 1.5, (48, 1, 3)) + rng.uniform(-0.3, 0.3, (48, 3, 3))
    tris = f32(np.concatenate([exact_edges, wide, sliver, good]))
    degenerate = np.zeros(len(tris), bool)
    degenerate[:n + len(u)] = True
    order = rng.permutation(len(tris))
    tris, degenerate = tris[order], degenerate[order]
    v = tris.astype(np.float64)
    pick = rng.choice(np.flatnonzero(degenerate | (np.arange(len(tris)) % 3 == 0)), n_rays)
    w = rng.uniform(0, 1, (n_rays, 1))
    target = v[pick, 0] + w * (v[pick, 2] - v[pick, 0])
    o = target + rng.normal(0, 3, (n_rays, 3))
    return tris, f32(o), f32(target - o), degenerate


def test_float32_collinear_triangles_never_hit(backend):
    """Random rays through zero-area triangles with distinct float32-collinear vertices (edges exact
    in float32, and edges that are not), next to genuine slivers 2^-20 off the line: no backend
    reports a zero-area triangle (closest and any hit), and all agree with the float64 reference."""
    tris, o, d, degenerate = collinear_probe()
    for any_hit in (False, True):
        out = run_case(backend, tris, o, d, any_hit=any_hit)
        assert not degenerate[out.rtri[out.rhit]].any()
        bad = np.flatnonzero(out.hit & degenerate[np.maximum(out.tri, 0)])
        assert len(bad) == 0, "a zero-area triangle was hit:\n" + out.describe(bad)
        assert out.rhit.sum() > len(o) // 10
        assert_matches(out)


def test_camera_inside_closed_box(backend):
    """Primary-like rays from eyes inside a closed box (centre, off-centre, 1e-3 from a wall, near a
    corner): every ray hits, including rays aimed exactly at the corners and along the face diagonals."""
    box = dyadic_box(half=(2.0, 1.5, 1.25))
    tris = f32(box.triangles)
    rng = np.random.default_rng(6)
    dirs = fibonacci_dirs(1500)
    targets = mesh_targets(box, rng, steps=8)
    o_list, d_list = [], []
    for eye in ([0, 0, 0], [0.5, -0.25, 0.125], [1.999, 0.5, 0.25], [-1.9375, -1.4375, 1.1875]):
        eye = f32(eye)
        o_list += [np.broadcast_to(eye, dirs.shape), np.broadcast_to(eye, targets.shape)]
        d_list += [dirs * rng.uniform(0.1, 10, (len(dirs), 1)), f32(targets - eye)]
    out = run_case(backend, tris, np.concatenate(o_list), np.concatenate(d_list))
    assert out.rhit.all()
    assert_matches(out, must_hit=np.ones(len(out.o), bool))


@pytest.mark.parametrize("normalised", [False, True])
def test_light_on_surface(backend, normalised):
    """Shadow rays from floor/wall points to lights lying exactly on the ceiling/another wall, with
    tmax exactly the distance to the light (tmin 1e-4: the rays start on a surface).

    The light's own surface is met at t == tmax (exactly in real arithmetic): whether it counts depends
    on rounding, so those rays -- the ones whose nearest reference hit beyond tmin is within 1e-5 of
    tmax -- are excused from the hit/miss comparison (they must still be valid: no NaN, t < tmax).
    Rays blocked by the occluder in between must agree. With tmax = (1 - 1e-4) x distance everything
    must agree."""
    room = dyadic_box(half=(2.0, 2.0, 1.25))
    block = dyadic_box(half=(0.5, 0.5, 0.5), centre=(0.25, -0.25, -0.5))
    tris = f32(np.concatenate([room.triangles, block.triangles]))
    rng = np.random.default_rng(7)
    floor = np.c_[rng.integers(-60, 61, (600, 2)) / 32, np.full(600, -1.25)]
    wall = np.c_[np.full(300, -2.0), rng.integers(-60, 61, (300, 2)) / 32 * np.array([1, 0.625])]
    lights = np.array([[0.5, 0.25, 1.25], [2.0, -0.75, 0.5], [1.0, 2.0, 0.0]])   # ceiling, two walls
    o_list, d_list, dist_list = [], [], []
    for light in lights:
        for p in (floor, wall):
            v = light - p
            if normalised:
                dist = np.linalg.norm(v, axis=1)
                o_list.append(p)
                d_list.append(v / dist[:, None])
                dist_list.append(dist)
            else:
                o_list.append(p)
                d_list.append(v)
                dist_list.append(np.ones(len(p)))
    o = np.concatenate(o_list)
    d = np.concatenate(d_list)
    dist = f32(np.concatenate(dist_list))
    # the reference's nearest hit beyond tmin, whatever tmax: near tmax -> boundary ray
    rt_free, _ = trace_float64(f32(tris), f32(o), f32(d), F32(1e-4), F32(INF))
    boundary = np.abs(rt_free.astype(np.float64) - dist) <= 1e-5 * dist
    for any_hit in (True, False):
        out = run_case(backend, tris, o, d, tmin=1e-4, tmax=dist, any_hit=any_hit)
        blocked = out.rhit & ~boundary
        assert blocked.sum() > 50 and (~out.rhit).sum() > 50
        assert_matches(out, excuse=boundary)
        out2 = run_case(backend, tris, o, d, tmin=1e-4, tmax=f32(dist * (1 - 1e-4)), any_hit=any_hit)
        assert_matches(out2)


def test_any_hit_agrees_on_occlusion(backend):
    """any_hit=True: occluded-or-not agrees with the reference (edge excuse); the returned (t, tri) is
    a genuine hit in range (checked for every case by check_contract)."""
    rng = np.random.default_rng(8)
    ico = trimesh.creation.icosphere(subdivisions=2)
    tris = np.concatenate([random_soup(rng, 200), f32(ico.triangles * 0.5)])
    n = 6000
    o = rng.uniform(-2.5, 2.5, (n, 3))
    d = (rng.uniform(-1, 1, (n, 3)) - o) * rng.uniform(0.2, 5, (n, 1))
    tmin = rng.uniform(0, 0.3, n)
    tmax = rng.uniform(0.2, 1.5, n)
    tmax[: n // 10] = INF
    out = run_case(backend, tris, o, d, tmin=tmin, tmax=tmax, any_hit=True)
    assert 0.2 < out.rhit.mean() < 0.95
    assert_matches(out)
    closest = run_case(backend, tris, o, d, tmin=tmin, tmax=tmax, any_hit=False)
    assert_matches(closest)
    h = out.hit & closest.hit
    assert np.all(out.t[h] >= closest.t[h] * (1 - 1e-6))


def test_inactive_rays_and_direction_units(backend):
    """tmax <= tmin, non-finite data and zero directions miss; t is in units of |d|."""
    tris = f32([[[-4, -4, 0], [4, -4, 0], [0, 4, 0]]])
    o = np.tile([[0.0, 0.0, 2.0]], (9, 1))
    d = np.tile([[0.0, 0.0, -1.0]], (9, 1))
    tmin = np.array([0, 1, 2, 3, -1, 0, 0, 0, 0], float)
    tmax = np.array([INF, 1, 1, -1, -2, INF, INF, INF, 2], float)   # last: hit at t == tmax -> miss
    o[5, 0] = np.nan
    d[6, 1] = np.inf
    d[7] = 0.0
    out = run_case(backend, tris, o, d, tmin=tmin, tmax=tmax)
    np.testing.assert_array_equal(out.tri, [0, -1, -1, -1, -1, -1, -1, -1, -1])
    np.testing.assert_array_equal(out.rtri, out.tri)
    # non-unit directions
    rng = np.random.default_rng(9)
    n = 200
    o = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.5, 3, n)]
    u = np.c_[rng.uniform(-0.1, 0.1, (n, 2)), -np.ones(n)]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    scales = np.array([1e-3, 0.37, 1.0, 7.5, 1e3])
    o_all = np.concatenate([o] * len(scales))
    d_all = np.concatenate([u * s for s in scales])
    out = run_case(backend, tris, o_all, d_all)
    assert out.hit.all()
    assert_matches(out)
    t_unit = out.t.reshape(len(scales), n) * scales[:, None]
    np.testing.assert_allclose(t_unit, np.broadcast_to(t_unit[2], t_unit.shape), rtol=1e-5)
    np.testing.assert_allclose(t_unit[2], (o[:, 2] / -u[:, 2]), rtol=1e-5)
    # empty inputs
    t, tri = trace_rays(tris, np.zeros((0, 3), F32), np.zeros((0, 3), F32), np.zeros(0, F32),
                        np.zeros(0, F32), backend=backend)
    assert len(t) == 0 and len(tri) == 0

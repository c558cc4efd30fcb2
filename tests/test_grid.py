"""Uniform grid (viewer.accel.grid) against a float64 NumPy binning, and the grid tracers (ugrid)
against the float64 watertight reference on grid-specific hard cases and the shared hard cases,
and against Embree on every ray type a Renderer generates.

Binning checked: every triangle is listed in every cell it meets (the separating-axis
triangle/box test in float64, no margin) and in no cell that the triangle misses by more than the
documented eps margin (the same test on cells grown by 1.5 eps); refs are grouped by cell in cell
order, cell ranges partition them, no pair is listed twice.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from tests.test_hard_cases import (  # noqa: F401  (collected here again, with the grid backends)
    assert_matches,
    run_case,
    test_any_hit_agrees_on_occlusion,
    test_axis_parallel_rays,
    test_camera_inside_closed_box,
    test_closed_mesh_no_leak,
    test_degenerate_triangles_never_hit,
    test_fan_shared_vertex_and_edges,
    test_grazing_rays,
    test_inactive_rays_and_direction_units,
    test_light_on_surface,
    test_tiny_triangles,
    test_translated_scene,
)
from viewer.accel.grid import GRID_DTYPE, GridSpec, grid_header, grid_resolution, scene_box, triangles_f4
from viewer.paths import RECORDINGS
from viewer.reference import EmbreeTracer, compare_hits


def _cl_reason() -> str | None:
    try:
        from viewer.cl import cl_available
    except Exception as exc:  # noqa: BLE001 - any import failure means no usable OpenCL layer
        return f"viewer.cl not importable: {exc}"
    return cl_available()


CL_REASON = _cl_reason()
needs_cl = pytest.mark.skipif(CL_REASON is not None, reason=f"no OpenCL device: {CL_REASON}")
GRID_BACKENDS = ["ugrid", "pgrid"]
F32 = np.float32


@pytest.fixture(scope="module", params=GRID_BACKENDS)
def backend(request):
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    return request.param


@pytest.fixture
def grid_res(monkeypatch):
    """Fix the grid resolution of the grid backends (longest axis) through their environment."""
    def set_res(backend: str, res: int) -> None:
        monkeypatch.setenv("RTWALK_" + backend.upper(), f"resolution={res}")
    return set_res


# ------------------------------------------------------------------------------------------------
# the build against NumPy


def ref_ranges(tris: np.ndarray, header: np.ndarray, grow: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive cell ranges per triangle of its box (grown by `grow` * eps cells), float64;
    triangles outside the grid or with non-finite vertices get empty ranges (lo > hi)."""
    t = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    h = header[0]
    glo, cell = h["lo"][:3].astype(np.float64), h["cell"][:3].astype(np.float64)
    eps = grow * h["eps"][:3].astype(np.float64)
    res = h["res"][:3].astype(np.int64)
    with np.errstate(invalid="ignore"):
        mn, mx = t.min(1), t.max(1)
        lo = (mn - glo) / cell - eps
        hi = (mx - glo) / cell + eps
        out = (hi < 0).any(1) | (lo >= res).any(1) | ~np.isfinite(mn).all(1) | ~np.isfinite(mx).all(1)
    lo = np.clip(np.floor(np.nan_to_num(lo)), 0, res - 1).astype(np.int64)
    hi = np.clip(np.floor(np.nan_to_num(hi)), 0, res - 1).astype(np.int64)
    lo[out], hi[out] = 1, 0
    return lo, hi


def pair_codes(lo: np.ndarray, hi: np.ndarray, res: np.ndarray, tris: np.ndarray | None = None,
               header: np.ndarray | None = None, grow: float = 0.0) -> np.ndarray:
    """tri * ncells + cell for every cell of every range (vectorised enumeration); with `tris` and
    `header`, only the cells the triangle meets, each cell grown by `grow` * eps (tri_meets_cells)."""
    ext = np.maximum(hi - lo + 1, 0)
    cnt = ext.prod(1)
    tri = np.repeat(np.arange(len(lo)), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    e = ext[tri]
    x = lo[tri, 0] + k % e[:, 0]
    y = lo[tri, 1] + (k // e[:, 0]) % e[:, 1]
    z = lo[tri, 2] + k // (e[:, 0] * e[:, 1])
    if tris is not None:
        keep = tri_meets_cells(tris, header, tri, np.stack([x, y, z], 1), grow)
        tri, x, y, z = tri[keep], x[keep], y[keep], z[keep]
    ncells = int(np.prod(res))
    return tri * ncells + (x + res[0] * (y + res[1] * z))


def tri_meets_cells(tris: np.ndarray, header: np.ndarray, tri: np.ndarray, cell: np.ndarray,
                    grow: float) -> np.ndarray:
    """Whether triangle tri[k] meets cell[k] grown by `grow` * eps cells per axis: the
    separating-axis test (Akenine-Moller 2001: the box's 3 axes, the triangle's normal, the 9 edge
    x axis products), float64 in cell units. Degenerate triangles lose the axes that are zero,
    which leaves the exact test for a segment or a point."""
    h = header[0]
    glo, cell_size = h["lo"][:3].astype(np.float64), h["cell"][:3].astype(np.float64)
    half = 0.5 + grow * h["eps"][:3].astype(np.float64)
    t = (np.asarray(tris, np.float64).reshape(-1, 3, 3)[tri] - glo) / cell_size
    v = t - (cell + 0.5)[:, None, :]  # box centre at the origin
    ok = ~((v.min(1) > half) | (v.max(1) < -half)).any(1)  # the box's axes
    edges = [v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]]
    axes = [np.cross(edges[0], edges[1])]
    for e in edges:
        for j in range(3):
            unit = np.zeros(3)
            unit[j] = 1.0
            axes.append(np.cross(e, unit))
    for a in axes:
        p = np.einsum("kvj,kj->kv", v, a)
        r = (half * np.abs(a)).sum(1)
        ok &= ~((p.min(1) > r) | (p.max(1) < -r))
    return ok


def build_grid(tris: np.ndarray, spec: GridSpec):
    from viewer.accel.grid import UniformGrid
    from viewer.cl import cl_context

    ctx = cl_context()
    cl = ctx.cl
    f4 = triangles_f4(tris)
    buf = cl.Buffer(ctx.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=f4) if f4.size else \
        cl.Buffer(ctx.context, cl.mem_flags.READ_ONLY, 64)
    g = UniformGrid(ctx)
    lo, hi = scene_box(tris)
    stats = g.build(buf, len(tris), lo, hi, spec)
    out = g.to_numpy()
    cell_blocks, blocks = g.blocks_to_numpy()
    g.release()
    check_blocks(tris, out[1], out[2], cell_blocks, blocks)
    buf.release()
    return stats, *out


def check_blocks(tris, cells, refs, cell_blocks, blocks) -> None:
    """Each cell's SoA blocks hold its refs in order, four per block, with their vertices; padding
    lanes are slot -1 and NaN."""
    from viewer.accel.grid import GRID_BLOCK_DTYPE

    assert blocks.dtype == GRID_BLOCK_DTYPE and GRID_BLOCK_DTYPE.itemsize == 160
    count = cells[:, 1].astype(np.int64)
    nb = (count + 3) // 4
    assert np.array_equal(cell_blocks.astype(np.int64), np.cumsum(nb) - nb)
    assert len(blocks) == nb.sum()
    # expected slot of every (block, lane)
    cell_of_block = np.repeat(np.arange(len(cells)), nb)
    k = (np.arange(len(blocks)) - cell_blocks[cell_of_block].astype(np.int64))[:, None] * 4 + np.arange(4)
    valid = k < count[cell_of_block][:, None]
    src = cells[cell_of_block, 0].astype(np.int64)[:, None] + k
    want = np.where(valid, refs[np.where(valid, src, 0)].astype(np.int64), -1)
    assert np.array_equal(blocks["slot"], want)
    v = blocks["v"].transpose(0, 2, 1).reshape(-1, 4, 3, 3)  # (block, lane, vertex, axis)
    t = np.asarray(tris, F32).reshape(-1, 3, 3)
    assert np.array_equal(v[valid], t[want[valid]], equal_nan=True)
    assert np.isnan(v[~valid]).all()


def check_grid(tris: np.ndarray, spec: GridSpec) -> dict:
    stats, header, cells, refs = build_grid(tris, spec)
    assert header.dtype == GRID_DTYPE and GRID_DTYPE.itemsize == 96
    res = header["res"][0, :3].astype(np.int64)
    assert stats.res == tuple(res) and stats.cells == int(np.prod(res)) == header["res"][0, 3]
    assert cells.shape == (stats.cells, 2) and refs.shape == (stats.pairs,)
    start, count = cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)
    nz = count > 0
    assert int(nz.sum()) == stats.nonempty
    assert count.sum() == stats.pairs
    # ranges partition the refs in cell order
    assert np.array_equal(start[nz], np.cumsum(count[nz]) - count[nz])
    cell_of = np.repeat(np.flatnonzero(nz), count[nz])
    codes = refs.astype(np.int64) * stats.cells + cell_of
    assert np.unique(codes).size == codes.size, "a triangle listed twice in one cell"
    assert np.all(refs < max(len(tris), 1))
    need = pair_codes(*ref_ranges(tris, header), res, tris, header)
    v = np.asarray(tris, np.float32).reshape(-1, 3, 3)
    never_hit = ((v[:, 0] == v[:, 1]).all(1) | (v[:, 1] == v[:, 2]).all(1) | (v[:, 2] == v[:, 0]).all(1))
    need = need[~never_hit[need // stats.cells]]  # two equal vertices: never hit, so never binned
    missing = ~np.isin(need, codes)
    assert not missing.any(), f"{int(missing.sum())} triangle-cell pairs the triangles meet are not listed"
    allowed = pair_codes(*ref_ranges(tris, header, grow=1.5), res, tris, header, grow=1.5)
    extra = ~np.isin(codes, allowed)
    assert not extra.any(), f"{int(extra.sum())} pairs of cells the triangles miss by more than the eps margin"
    return {"stats": stats, "header": header, "need": len(need)}


def random_tris(n, seed=0, extent=20.0, size=1.0):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0, extent, (n, 1, 3))
    return (c + rng.normal(0, size, (n, 3, 3))).astype(F32)


@needs_cl
@pytest.mark.parametrize("n", [1, 7, 2000])
def test_build_matches_numpy_random(n):
    r = check_grid(random_tris(n, seed=n), GridSpec(density=2.0))
    if n == 2000:
        assert r["stats"].nonempty > 100


@needs_cl
def test_build_special_triangles():
    """A triangle spanning every cell, degenerate ones, a non-finite one, vertices exactly on cell
    planes, a flat scene axis."""
    tris = [random_tris(300, seed=1, extent=8.0, size=0.4)]
    tris.append(np.array([[[0, 0, 0], [8, 8, 0], [8, 8, 8]]], F32))  # spans the box diagonal
    tris.append(np.array([[[3, 3, 3], [3, 3, 3], [3, 3, 3]], [[1, 1, 1], [2, 2, 2], [3, 3, 3]]], F32))
    tris.append(np.array([[[np.nan, 0, 0], [1, 1, 1], [2, 2, 0]]], F32))
    t = np.concatenate(tris)
    r = check_grid(t, GridSpec(resolution=8))
    assert r["stats"].res == (8, 8, 8)
    # cell-plane vertices: a grid whose planes are integers, triangles between planes
    _, header, _, _ = build_grid(t, GridSpec(resolution=8))
    lo, cell = header["lo"][0, :3], header["cell"][0, :3]
    k = np.array([[[2, 2, 2], [3, 2, 2], [3, 3, 2]], [[4, 4, 4], [4, 5, 4], [4, 5, 5]]], np.float64)
    on_planes = (lo + k * cell).astype(F32)
    check_grid(np.concatenate([t, on_planes]), GridSpec(resolution=8))
    flat = random_tris(500, seed=3, extent=10.0, size=0.5)
    flat[:, :, 2] = 1.5
    r = check_grid(flat, GridSpec(density=3.0))
    assert r["stats"].res[2] == 1


def test_resolution_rule():
    lo, hi = np.zeros(3), np.array([40.0, 20.0, 10.0])
    res = grid_resolution(lo, hi, 100_000, GridSpec(density=2.0))
    cells = int(np.prod(res))
    assert 150_000 <= cells <= 300_000, res  # about density * N cells
    assert res[0] / res[1] == pytest.approx(2, rel=0.1) and res[1] / res[2] == pytest.approx(2, rel=0.1)
    more = grid_resolution(lo, hi, 100_000, GridSpec(density=8.0))
    assert np.prod(more) > 3 * cells
    assert tuple(grid_resolution(lo, hi, 100_000, GridSpec(resolution=64))) == (64, 32, 16)
    capped = grid_resolution(lo, hi, 10**9, GridSpec(density=4.0, max_axis=100))
    assert capped.max() <= 100
    h = grid_header(lo, hi, res)
    assert np.all(h["lo"][0, :3] <= lo) and np.all(h["hi"][0, :3] >= hi)


# ------------------------------------------------------------------------------------------------
# grid-specific hard cases (same judging as tests/test_hard_cases.py)


def _grid_of(tris: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, cell, res) of the grid a grid backend builds over `tris` with resolution=res."""
    lo, hi = scene_box(tris)
    r = grid_resolution(lo, hi, len(tris), GridSpec(resolution=res))
    h = grid_header(lo, hi, r)
    return h["lo"][0, :3].astype(np.float64), h["cell"][0, :3].astype(np.float64), r


def _soup(rng, n=400, extent=8.0, size=0.5):
    c = rng.uniform(0, extent, (n, 1, 3))
    return (c + rng.normal(0, size, (n, 3, 3))).astype(F32)


@pytest.mark.parametrize("any_hit", [False, True])
def test_rays_along_cell_planes(backend, grid_res, any_hit):
    """Origins and whole rays lying exactly in cell planes (direction component 0 or -0.0)."""
    rng = np.random.default_rng(11)
    tris = _soup(rng)
    grid_res(backend, 8)
    glo, cell, res = _grid_of(tris, 8)
    o_list, d_list = [], []
    for axis in range(3):
        for k in range(0, int(res[axis]) + 1):
            m = 40
            o = rng.uniform(-1, 9, (m, 3))
            o[:, axis] = glo[axis] + k * cell[axis]
            d = rng.normal(size=(m, 3))
            d[:, axis] = 0.0 if k % 2 else -0.0
            d[: m // 4, (axis + 1) % 3] = 0.0  # along a cell edge line too
            o_list.append(o)
            d_list.append(d)
    o = np.concatenate(o_list).astype(F32)
    d = np.concatenate(d_list).astype(F32)
    out = run_case(backend, tris, o, d, any_hit=any_hit)
    assert out.rhit.sum() > 0.2 * len(o)
    assert_matches(out)


def test_origins_on_cell_boundaries(backend, grid_res):
    """Origins exactly on cell faces, edges and corners (inside and on the grid's own boundary),
    random and axis-parallel directions, tmin 0 and > 0."""
    rng = np.random.default_rng(12)
    tris = _soup(rng, 600)
    grid_res(backend, 6)
    glo, cell, res = _grid_of(tris, 6)
    idx = np.stack(np.meshgrid(*[np.arange(int(r) + 1) for r in res], indexing="ij"), -1).reshape(-1, 3)
    corners = glo + idx * cell
    o = np.repeat(corners, 6, axis=0).astype(F32)
    d = rng.normal(size=(len(o), 3))
    d[::3] = np.eye(3)[rng.integers(0, 3, len(o[::3]))] * rng.choice([-1.0, 1.0], (len(o[::3]), 1))
    d = d.astype(F32)
    tmin = np.where(rng.random(len(o)) < 0.5, 0.0, 0.25).astype(F32)
    for any_hit in (False, True):
        out = run_case(backend, tris, o, d, tmin=tmin, any_hit=any_hit)
        assert out.rhit.sum() > 0.1 * len(o)
        assert_matches(out)


def test_triangle_spanning_all_cells(backend, grid_res):
    """One triangle across the whole grid with small ones: rays must find it behind empty cells
    and in front of the small ones."""
    rng = np.random.default_rng(13)
    big = np.array([[[0, 0, 0], [16, 0, 16], [0, 16, 16]]], F32)
    small = _soup(rng, 200, extent=16.0, size=0.3)
    tris = np.concatenate([big, small])
    grid_res(backend, 16)
    # rays from outside towards points of the big triangle's interior: must hit something
    w = rng.dirichlet([1, 1, 1], 2000)
    target = (w[:, :, None] * big[0][None].astype(np.float64)).sum(1)
    nrm = np.array([-1.0, -1.0, 1.0]) / np.sqrt(3)  # from both sides, at least 30 degrees off the plane
    side = rng.choice([-1.0, 1.0], (2000, 1))
    o = (target + side * 30 * nrm + rng.normal(size=(2000, 3)) * 10).astype(F32)
    d = (target - o).astype(F32)
    out = run_case(backend, tris, o, d)
    assert_matches(out, must_hit=np.ones(len(o), bool))
    assert (out.tri == 0).mean() > 0.5


def test_path_through_empty_cells(backend, grid_res):
    """Two tiny clusters at opposite corners of a fine grid: rays from one walk ~100 empty cells."""
    rng = np.random.default_rng(14)
    a = (rng.normal(0, 0.05, (20, 3, 3)) + 0.5).astype(F32)
    b = (rng.normal(0, 0.05, (20, 3, 3)) + 63.5).astype(F32)
    quad = np.array([[[63, 63, 63.5], [64, 63, 63.5], [64, 64, 63.5]], [[63, 63, 63.5], [64, 64, 63.5],
                                                                      [63, 64, 63.5]]], F32)
    tris = np.concatenate([a, b, quad])
    grid_res(backend, 64)
    n = 3000
    o = rng.uniform(0, 1, (n, 3)).astype(F32)
    target = np.c_[rng.uniform(63.05, 63.95, (n, 2)), np.full(n, 63.5)]
    d = (target - o).astype(F32)
    for any_hit in (False, True):
        out = run_case(backend, tris, o, d, tmin=np.full(n, 1e-3, F32), any_hit=any_hit)
        assert_matches(out, must_hit=np.ones(n, bool))
    # rays stopped short of the far cluster (tmax) must miss it
    out = run_case(backend, tris, o, d, tmin=np.full(n, 0.6, F32), tmax=np.full(n, 0.9, F32))
    assert_matches(out)


def test_rays_starting_outside_and_inside(backend, grid_res):
    """Origins far outside, just outside, on and inside the grid box; segments ending inside it."""
    rng = np.random.default_rng(15)
    tris = _soup(rng, 500)
    grid_res(backend, 10)
    glo, cell, res = _grid_of(tris, 10)
    ghi = glo + cell * res
    centre = (glo + ghi) / 2
    n = 4000
    scale = rng.choice([0.3, 0.5, 0.5000001, 0.6, 5.0, 1000.0], (n, 1))
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = (centre + dirs * scale * (ghi - glo) * 2).astype(F32)
    d = (centre + rng.normal(size=(n, 3)) * 2 - o).astype(F32)
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(0.2, 1.0, n), np.inf).astype(F32)
    for any_hit in (False, True):
        out = run_case(backend, tris, o, d, tmax=tmax, any_hit=any_hit)
        assert out.rhit.sum() > 0.2 * n
        assert_matches(out)


# ------------------------------------------------------------------------------------------------
# every ray type of a frame against Embree


@needs_cl
@pytest.mark.parametrize("name", GRID_BACKENDS)
def test_renderer_every_ray_type_agrees_with_embree(gl_ctx, name):
    """A Renderer with the grid backend on city at 320x180: each captured pass against Embree, with the
    agreement bars glsl meets (tests/test_agreement.py)."""
    from viewer.effects import RayType, parse_effects
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    camera = rec.camera_for_frame(rec.frame_count() // 3)
    settings = parse_effects("primary,shadows,soft:2,ao:2,diffuse:2,reflections")
    r = Renderer(gl_ctx, prep.scene, prep.bvh, (320, 180), name, settings)
    try:
        rep = r.render(camera, capture=True)
    finally:
        r.release()
    assert rep.backend_stats.get("rays", 0) > 0
    embree = EmbreeTracer(prep.scene.triangles)
    seen = set()
    for cp in rep.captured:
        act = cp.rays.active
        if not act.any():
            continue
        seen.add(cp.ray_type)
        o, d, lo, hi = cp.rays.origins[act], cp.rays.directions[act], cp.rays.tmin[act], cp.rays.tmax[act]
        rt, rtri = embree.trace(o, d, lo, hi, any_hit=cp.ray_type.any_hit)
        st = compare_hits(cp.t[act], cp.tri[act], rt, rtri, prep.scene.triangles)
        label = (cp.ray_type.label, cp.sample, st)
        assert st["hitmiss_agree"] >= 0.999, label
        assert st["n_bad_id"] == 0, label
        if not cp.ray_type.any_hit:
            need = 0.9999 if cp.ray_type == RayType.PRIMARY else 0.999
            assert st["id_agree"] >= need, label
    assert {RayType.PRIMARY, RayType.SHADOW, RayType.SOFT, RayType.AO, RayType.DIFFUSE} <= seen, seen


# ------------------------------------------------------------------------------------------------
# pgrid's point-centred grids: rays that all pass through a light or start at an eye


def trace_centred(tris, o, d, tmin, tmax, ray_type, light=None, params: str | None = None,
                  size: tuple[int, int] | None = None, keep=None):
    """Trace with pgrid as a pass of `ray_type` in a scene with one point light at `light`;
    returns (t, tri in input order, backend stats). `size`: the image the rays fill (row-major,
    row 0 first; default up to 1024 wide); `keep(backend)` is called after the trace."""
    return trace_centred_passes(tris, [(o, d, tmin, tmax)], ray_type, light, params, size, keep)[0]


def trace_centred_passes(tris, ray_sets, ray_type, light=None, params: str | None = None,
                         size: tuple[int, int] | None = None, keep=None):
    """trace_centred for several ray sets (o, d, tmin, tmax), one pass each, by ONE pgrid backend
    (a pass's buffers are sized from the one before, its counters are that one's):
    [(t, tri, stats)] per pass. Every set fills the same `size` (default: the largest set's)."""
    from viewer.accel.bvh import build_bvh
    from viewer.backends import create_backend
    from viewer.backends.base import BackendContext
    from viewer.gl.context import shared_context
    from viewer.gl.programs import ProgramCache
    from viewer.gl.scene import GpuScene
    from viewer.profiler import GpuProfiler
    from viewer.rays import HitBuffer, PassInfo, RayBatch
    from viewer.scene import Material, PointLight, Scene

    ctx = shared_context()
    tris = np.ascontiguousarray(tris, F32)
    bvh = build_bvh(tris)
    lights = [PointLight(np.asarray(light, F32), np.ones(3, F32))] if light is not None else []
    scene = Scene("pg", tris, np.zeros(len(tris), np.int32), [Material("grey", np.full(3, 0.7, F32))],
                  point_lights=lights).reordered(bvh.tri_order)
    if size is None:
        n_max = max(len(rs[0]) for rs in ray_sets)
        width = min(n_max, 1024)
        size = (width, -(-n_max // width))
    pad = size[0] * size[1]
    gpu = GpuScene.upload(ctx, scene, bvh)
    rays, hits = RayBatch(ctx, size), HitBuffer(ctx, size)
    out = []
    try:
        bc = BackendContext(ctx, ProgramCache(ctx), GpuProfiler(ctx, enabled=False), gpu, scene, bvh)
        be = create_backend("pgrid", bc, params)
        for o, d, tmin, tmax in ray_sets:
            n = len(o)
            org = np.zeros((pad, 4), F32)
            dirs = np.zeros((pad, 4), F32)
            dirs[:, 2], dirs[:, 3] = 1.0, -1.0
            org[:n, :3], org[:n, 3] = o, tmin
            dirs[:n, :3], dirs[:n, 3] = d, np.minimum(tmax, F32(3.4e38))
            rays.origin.write(org.tobytes())
            rays.direction.write(dirs.tobytes())
            be.begin_frame(0)
            res = be.trace(rays, PassInfo(ray_type, light=0), hits)
            if keep is not None:
                keep(be)
            t, slot = hits.read()
            t, slot = t[:n], slot[:n]
            tri = np.where(slot >= 0, bvh.tri_order[np.maximum(slot, 0)], -1).astype(np.int32)
            out.append((t, tri, res.stats))
        be.release()
    finally:
        rays.release()
        hits.release()
        gpu.release()
    return out


def _judge(tris, o, d, tmin, tmax, t, tri, any_hit):
    from tests.conftest import reference_float64
    from tests.test_hard_cases import Outcome, check_contract

    rt, rtri = reference_float64(tris, o, d, tmin, tmax)  # the same rays for each set of pgrid parameters
    out = Outcome(tris, o, d, tmin, tmax, t, tri, rt, rtri, any_hit)
    check_contract(out)
    return out


@needs_cl
@pytest.mark.parametrize("light_at", ["inside", "outside", "on_cell_plane"])
@pytest.mark.parametrize("params", ["chunk=16", "chunk=64", "chunk=256", "chunk=32,balance=false,slabs=1"])
def test_pgrid_shadow_rays_through_light(light_at, params):
    """Shadow rays from surface points to a point light inside / outside the scene: the spherical
    grid handles (nearly) all of them, and every answer matches the float64 reference."""
    from viewer.effects import RayType

    rng = np.random.default_rng(21)
    tris = _soup(rng, 1500, extent=10.0, size=0.4)
    light = {"inside": [5.0, 5.0, 5.0], "outside": [5.0, 30.0, 5.0], "on_cell_plane": [5.0, 5.0, 0.0]}[light_at]
    light = np.asarray(light, F32)
    n = 20000
    w = rng.dirichlet([1, 1, 1], n)
    pick = rng.integers(0, len(tris), n)
    p = (w[:, :, None] * tris[pick].astype(np.float64)).sum(1)  # points on triangles
    p += rng.normal(scale=1e-3, size=p.shape)
    l_vec = light.astype(np.float64) - p
    dist = np.linalg.norm(l_vec, axis=1)
    o = p.astype(F32)
    d = (l_vec / dist[:, None]).astype(F32)
    tmin = np.zeros(n, F32)
    tmax = (dist * (1 - 1e-4)).astype(F32)
    tmax[:100] = -1.0  # inactive rays
    t, tri, stats = trace_centred(tris, o, d, tmin, tmax, RayType.SHADOW,
                                  light=light, params=params)
    padding = stats["rays"] - n  # the texture's unused texels are inactive rays
    assert stats["outside_rays"] <= 0.01 * n, stats  # the grid took the rays
    assert stats["inactive_rays"] == padding + 100, stats  # nothing to trace: no chunk, a miss
    assert stats["pairs"] > 0 and stats["chunks"] > 0
    if "balance=false" in params:
        assert stats["chunk_occupancy"] > 1  # whole tiles: more rays than work-items per group
    out = _judge(tris, o, d, tmin, tmax, t, tri, True)
    assert 0.1 * n < out.rhit.sum() < 0.95 * n
    assert_matches(out)


@needs_cl
@pytest.mark.parametrize("tiles", [0, 3, 40])
def test_pgrid_primary_rays_from_eye(tiles):
    """Rays from one eye point (closest hit): the eye-centred angular grid with the slab check
    against the float64 reference, including axis-parallel directions and an eye inside the scene."""
    from viewer.effects import RayType

    rng = np.random.default_rng(22)
    tris = _soup(rng, 1500, extent=10.0, size=0.4)
    for eye in ([5.0, 5.0, 5.0], [-8.0, 4.0, 3.0]):
        eye = np.asarray(eye, F32)
        n = 20000
        target = rng.uniform(0, 10, (n, 3))
        d = (target - eye).astype(F32)
        d[:200] = np.eye(3)[rng.integers(0, 3, 200)] * rng.choice([-1.0, 1.0], (200, 1))
        o = np.broadcast_to(eye, (n, 3)).astype(F32)
        tmin = np.zeros(n, F32)
        tmax = np.full(n, np.inf, F32)
        t, tri, stats = trace_centred(tris, o, d, tmin, tmax, RayType.PRIMARY,
                                      params=f"tiles={tiles},primary=angular")
        assert stats["outside_rays"] == 0 and stats["inactive_rays"] == stats["rays"] - n, stats  # padding
        out = _judge(tris, o, d, tmin, tmax, t, tri, False)
        assert out.rhit.sum() > 0.3 * n
        assert_matches(out)


@needs_cl
def test_pgrid_rays_off_the_centre_take_the_uniform_grid():
    """Shadow-pass rays that do not go through the light (random rays) are still exact."""
    from viewer.effects import RayType

    rng = np.random.default_rng(23)
    tris = _soup(rng, 800, extent=10.0, size=0.4)
    n = 5000
    o = rng.uniform(0, 10, (n, 3)).astype(F32)
    d = rng.normal(size=(n, 3)).astype(F32)
    tmin = np.zeros(n, F32)
    tmax = np.full(n, np.inf, F32)
    t, tri, stats = trace_centred(tris, o, d, tmin, tmax, RayType.SHADOW, light=[5, 5, 5])
    assert stats["outside_rays"] > 0.9 * n
    assert_matches(_judge(tris, o, d, tmin, tmax, t, tri, True))


def _all_hits(tris, o, d, tmin, tmax, rounds: int = 12) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every (ray, triangle) intersection along the segments (float64 reference, nearest first),
    as (ray indices, triangle indices) per round."""
    from viewer.reference import trace_float64

    lo = tmin.astype(np.float64).copy()
    out = []
    for _ in range(rounds):
        t, tri = trace_float64(tris, o, d, lo, tmax)
        hit = np.flatnonzero(tri >= 0)
        if not len(hit):
            break
        out.append((hit, tri[hit]))
        lo[hit] = np.nextafter(t[hit], np.inf)
    return out


@needs_cl
@pytest.mark.parametrize("light", [[5.0, 5.0, 5.0], [5.0, 30.0, 5.0], [5.0, 12.0, 5.0], "boxed"])
def test_light_grid_lists_every_occluder_in_the_rays_tile(light):
    """Conservative binning of the spherical grid: every triangle a shadow segment meets (float64
    reference, all of them, not only the first) is listed in the cells of that ray's light tile,
    and the ray's angles lie in that triangle's angular box (the trace's per-ray test; small
    triangles are boxed through their bounding sphere, large ones exactly).
    Lights inside, far outside and right above the soup; "boxed": a light inside a small closed
    box in the middle of the soup, so rays come from every direction and the box faces pierced by
    the grid's pole axis surround the pole (their azimuth range is everything)."""
    import trimesh

    from viewer.effects import RayType

    rng = np.random.default_rng(24)
    tris = np.concatenate([_soup(rng, 1200, extent=10.0, size=0.5),
                           _soup(rng, 40, extent=10.0, size=3.0)])  # large triangles over many tiles
    if light == "boxed":
        light = [5.0, 5.0, 5.0]
        box = trimesh.creation.box([1.0, 1.0, 1.0]).apply_translation(light).triangles.astype(F32)
        near = np.linalg.norm(tris.mean(1) - np.asarray(light), axis=1) > 2.5
        tris = np.concatenate([tris[near], box])
    light = np.asarray(light, F32)
    n = 6000
    w = rng.dirichlet([1, 1, 1], n)
    p = (w[:, :, None] * tris[rng.integers(0, len(tris), n)].astype(np.float64)).sum(1)
    l_vec = light.astype(np.float64) - p
    dist = np.linalg.norm(l_vec, axis=1)
    o, d = p.astype(F32), (l_vec / dist[:, None]).astype(F32)
    tmin, tmax = np.full(n, 1e-4, F32), (dist * (1 - 1e-4)).astype(F32)
    grid = {}

    def keep(be):
        pg = be.pgrid
        cl, q = pg.ctx.cl, pg.ctx.queue
        key, _, length = pg.chunks.to_numpy(pg.ctx)
        vals = np.empty(int(length.sum()), np.uint32)
        cl.enqueue_copy(q, vals, pg.ray_vals)
        na, nt = pg.stats.tiles
        ns = pg.stats.slabs
        cell_start = np.empty(na * nt * ns + 1, np.uint32)
        cl.enqueue_copy(q, cell_start, pg.cell_start)
        refs = np.empty(max(pg.stats.pairs, 1), np.uint32)
        if pg.stats.pairs:
            cl.enqueue_copy(q, refs, pg.refs)
        tile_of = np.full(len(vals), -1, np.int64)
        ch = np.repeat(np.arange(len(key)), length.astype(np.int64))
        tile_of[vals] = np.where(key[ch] < na * nt, key[ch].astype(np.int64), -1)
        boxes = np.empty((len(be.bc.bvh.tri_order), 4), np.float32)
        cl.enqueue_copy(q, boxes, pg.tri_box)
        angles = [np.empty(len(vals), np.float32) for _ in range(2)]
        for a, buf in zip(angles, pg.ray_angles, strict=True):
            cl.enqueue_copy(q, a, buf)
        grid.update(tile_of=tile_of, cell_start=cell_start, refs=refs[: pg.stats.pairs], ns=ns,
                    order=be.bc.bvh.tri_order, boxes=boxes, angles=angles)

    trace_centred(tris, o, d, tmin, tmax, RayType.SHADOW, light=light, keep=keep)
    tile_of = grid["tile_of"][:n]
    assert (tile_of >= 0).mean() > 0.9  # nearly every ray is in the grid
    slot_of = np.empty(len(grid["order"]), np.int64)
    slot_of[grid["order"]] = np.arange(len(grid["order"]))
    cs, refs, ns = grid["cell_start"], grid["refs"], grid["ns"]
    boxes, (alpha, theta) = grid["boxes"], grid["angles"]
    checked = 0
    for rays, tri in _all_hits(tris, o, d, tmin, tmax):
        keep_ = tile_of[rays] >= 0
        for r, t in zip(rays[keep_], slot_of[tri[keep_]], strict=True):
            tile = tile_of[r]
            listed = refs[cs[tile * ns]:cs[(tile + 1) * ns]]
            assert t in listed, f"ray {r}: occluder slot {t} not in light tile {tile}"
            # the trace tests the ray's angles against the triangle's own angular box first
            b = boxes[t]
            assert b[0] <= alpha[r] <= b[1] and b[2] <= theta[r] <= b[3], \
                f"ray {r} (alpha {alpha[r]}, theta {theta[r]}): outside occluder slot {t}'s box {b}"
            checked += 1
    assert checked > 0.2 * n


@needs_cl
def test_fast_atan2_error_bound(tmp_path):
    """pg_atan2_fast (the light grid's binning) stays within the 2e-6 rad its slack assumes, in
    every quadrant, on the axes and diagonals, and for tiny and huge inputs."""
    from viewer.accel.pointgrid import KERNEL
    from viewer.cl import build, cl_context

    ctx = cl_context()
    src = tmp_path / "atan_check.cl"
    src.write_text('#include "pointgrid.cl"\n'
                   '__kernel void atan_check(__global const float2 *yx, __global float *out, const uint n) {\n'
                   '    uint i = get_global_id(0);\n'
                   '    if (i < n) out[i] = pg_atan2_fast(yx[i].x, yx[i].y);\n}\n')
    prog = build(src, {"WG": 64}, ctx, search=[KERNEL.parent])
    rng = np.random.default_rng(5)
    ang = np.concatenate([rng.uniform(-np.pi, np.pi, 400_000), np.arange(-8, 9) * np.pi / 8])
    mag = np.exp(rng.uniform(-40, 40, len(ang)))
    yx = np.stack([np.sin(ang) * mag, np.cos(ang) * mag], 1).astype(F32)
    yx = np.concatenate([yx, np.array([[0, 1], [1, 0], [0, -1], [-1, 0], [1e-30, 1], [1, 1], [-1, -1]], F32)])
    cl = ctx.cl
    mf = cl.mem_flags
    a = cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=yx)
    out = np.empty(len(yx), F32)
    b = cl.Buffer(ctx.context, mf.WRITE_ONLY, out.nbytes)
    cl.Kernel(prog, "atan_check")(ctx.queue, (len(yx),), None, a, b, np.uint32(len(yx)))
    cl.enqueue_copy(ctx.queue, out, b)
    ref = np.arctan2(yx[:, 0].astype(np.float64), yx[:, 1].astype(np.float64))
    err = np.abs(out.astype(np.float64) - ref)
    err = np.minimum(err, 2 * np.pi - err)  # +pi and -pi are the same direction
    assert err.max() <= 2e-6, err.max()


def _shadow_rays(rng, tris, light, n, pick=None):
    """n shadow segments from points on the triangles (those `pick` selects) to `light`."""
    idx = rng.choice(np.flatnonzero(pick) if pick is not None else np.arange(len(tris)), n)
    w = rng.dirichlet([1, 1, 1], n)
    p = (w[:, :, None] * tris[idx].astype(np.float64)).sum(1)
    l_vec = np.asarray(light, np.float64) - p
    dist = np.linalg.norm(l_vec, axis=1)
    return p.astype(F32), (l_vec / dist[:, None]).astype(F32), np.full(n, 1e-4, F32), (dist * (1 - 1e-4)).astype(F32)


@needs_cl
def test_light_grid_buffers_sized_from_the_last_pass_overflow_exactly():
    """The light grid's pair buffers are sized from the same light's last pass (no wait after the
    first): rays towards a corner of the scene (a narrow grid, few pairs), then rays from all of
    it, overflow them; that pass's rays all take the uniform grid (still exact), and the pass
    after has room again. The counters come a pass late."""
    from viewer.effects import RayType

    rng = np.random.default_rng(41)
    tris = _soup(rng, 3000, extent=10.0, size=0.4)
    light = [5.0, 5.0, 5.0]
    corner = (tris.mean(1) > 8.0).all(1)
    narrow = _shadow_rays(rng, tris, light, 300, corner)
    wide = _shadow_rays(rng, tris, light, 4000)
    runs = trace_centred_passes(tris, [narrow, wide, wide, wide], RayType.SHADOW, light, size=(1000, 4))
    for (o, d, tmin, tmax), (t, tri, _) in zip([narrow, wide, wide, wide], runs, strict=True):
        out = _judge(tris, o, d, tmin, tmax, t, tri, True)
        assert out.rhit.sum() > 0.1 * len(o)
        assert_matches(out)
    pairs = [st["pairs"] for _, _, st in runs]
    outside = [st["outside_rays"] for _, _, st in runs]
    # pass 3 reports pass 2's overflow (no pairs, every active ray outside), pass 4 pass 3's grid
    assert pairs[0] > 0 and pairs[2] == 0 and pairs[3] > 1.25 * pairs[0] + 1024, pairs
    assert outside[2] >= 0.99 * len(wide[0]) and outside[3] < 0.1 * len(wide[0]), outside


@needs_cl
@pytest.mark.parametrize("tiling", ["auto", "tiles=40", "tile_deg=2"])
def test_light_grid_placed_on_the_device_as_the_float64_reference(tiling):
    """pg_frame and pg_place place the light grid on the device (no read-back): its frame, margin,
    angular rectangle and tiles agree with the float64 host reference (choose_frame on the same
    strided sample, placement_reference on the same statistics), and its distance level bits are
    at least level_bits(cell bits)."""
    from viewer.accel.grid import scene_box, triangles_f4
    from viewer.accel.pointgrid import (
        FRAME_SAMPLE,
        ST_INIT,
        PointGrid,
        PointGridSpec,
        choose_frame,
        level_bits,
        placement_reference,
    )
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    rng = np.random.default_rng(43)
    tris = _soup(rng, 2000, extent=10.0, size=0.4)
    light = np.array([5.0, 14.0, 5.0])
    o, d, tmin, tmax = _shadow_rays(rng, tris, light, 9001)
    org = np.concatenate([o, tmin[:, None]], 1).astype(F32)
    dirs = np.concatenate([d, tmax[:, None]], 1).astype(F32)
    dirs[::5, 3] = -1.0  # some inactive rays
    kw = {} if tiling == "auto" else {"tiles": 40} if tiling == "tiles=40" else {"tile_angle": float(np.radians(2))}
    spec = PointGridSpec(**kw)
    ctx = cl_context()
    bufs = [clio.upload(ctx, a) for a in (triangles_f4(tris), org, dirs)]
    pg = PointGrid(ctx)
    try:
        n = len(org)
        pg.build(bufs[0], len(tris), *scene_box(tris), bufs[1], bufs[2], n, light, spec, exact=True)
        h = pg.header_numpy()[0]
        st = np.empty_like(ST_INIT)
        clio.copy(ctx.queue, st, pg.outside_counter)
    finally:
        pg.release()
        for b in bufs:
            b.release()
    step = max(1, n // FRAME_SAMPLE)
    for got, want in zip((h["fwd"], h["up"], h["right"]), choose_frame(light, org[::step], dirs[::step]),
                         strict=True):
        assert np.allclose(got[:3], want, atol=2e-6), (got, want)
    assert int(st[1]) == n // 5 + 1 and int(st[0]) < 0.01 * n  # inactive rays; nearly all in the grid
    m, (a0, e0, a1, e1), na, nt = placement_reference(st, n, spec)
    assert abs(h["centre"][3] - m) <= 1e-6 * m
    assert np.allclose(h["rect"][:2], [a0, e0], atol=1e-6)
    assert abs(int(h["res"][0]) - na) <= 1 and abs(int(h["res"][1]) - nt) <= 1, (h["res"], na, nt)
    assert np.allclose(h["rect"][2:], [h["res"][0] / (a1 - a0), h["res"][1] / (e1 - e0)], rtol=1e-5)
    cells = int(h["res"][0] * h["res"][1] * h["res"][2])
    assert h["res"][3] == cells and h["up"][3] >= level_bits(max(1, (cells - 1).bit_length()))

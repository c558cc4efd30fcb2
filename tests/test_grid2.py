"""Two-level grid (viewer.accel.grid2, ugrid levels=2) against the float64 watertight reference.

The teapot-in-a-stadium case: a 1e-3 sphere mesh standing on a 2e4 ground with a 1e4 wall; rays
from beside it, from 5e3 away, grazing along the ground, and shadow rays from its surface. The
shared hard cases and the top-grid plane cases run again with sub-grids forced everywhere (a
near-single-cell top grid, every cell with a triangle gets a sub-grid). A budget on the triangle
tests per ray on the mixed scene keeps it from silently falling back to testing the whole object.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from tests.test_grid import (  # noqa: F401  (collected here again, with sub-grids forced)
    CL_REASON,
    test_origins_on_cell_boundaries,
    test_path_through_empty_cells,
    test_rays_along_cell_planes,
    test_rays_starting_outside_and_inside,
    test_triangle_spanning_all_cells,
)
from tests.test_hard_cases import (  # noqa: F401
    assert_matches,
    run_case,
    test_any_hit_agrees_on_occlusion,
    test_axis_parallel_rays,
    test_camera_inside_closed_box,
    test_closed_mesh_no_leak,
    test_fan_shared_vertex_and_edges,
    test_grazing_rays,
    test_tiny_triangles,
    test_translated_scene,
)

F32 = np.float32
FORCED = "levels=2,sub_min=1,sub_density=4"


@pytest.fixture(params=["sub_big=1e9", "sub_big=0.25"])
def backend(monkeypatch, request):
    """ugrid with a very coarse top grid whose every occupied cell gets a sub-grid: with every
    triangle in the sub-grids, and with the longer ones in the cells' big lists."""
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    monkeypatch.setenv("RTWALK_UGRID", f"density=0.01,{FORCED},{request.param}")
    return "ugrid"


@pytest.fixture
def grid_res(monkeypatch):
    """The top grid's resolution fixed as test_grid's cases expect, sub-grids forced."""
    def set_res(backend: str, res: int) -> None:
        monkeypatch.setenv("RTWALK_UGRID", f"resolution={res},{FORCED}")
    return set_res


def mixed_scene(subdivisions: int, size: float = 1e-3, ground: float = 2e4) -> np.ndarray:
    """An icosphere of diameter `size` resting on a `ground`-wide square, a wall half as tall."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    small = (m.vertices * size / 2 + [0.0, size / 2, 0.0])[m.faces]
    g, w = ground / 2, ground / 4
    floor = [[[-g, 0, -g], [g, 0, -g], [g, 0, g]], [[-g, 0, -g], [g, 0, g], [-g, 0, g]]]
    wall = [[[-g, 0, -w], [g, 0, -w], [g, 2 * w, -w]], [[-g, 0, -w], [g, 2 * w, -w], [-g, 2 * w, -w]]]
    return np.concatenate([small, floor, wall]).astype(F32)


def mixed_rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays at the sphere from 3e-3 and from 5e3 away, and grazing along the ground towards it."""
    target = rng.uniform(-6e-4, 6e-4, (n, 3)) + [0.0, 5e-4, 0.0]
    near = np.array([1e-3, 1.5e-3, 3e-3])
    far = np.array([3e3, 2e3, 4e3])
    graze = np.c_[rng.uniform(-1e-2, 1e-2, n), rng.uniform(0, 2e-4, n), np.full(n, 2e-2)]
    o = np.concatenate([np.broadcast_to(near, (n, 3)), np.broadcast_to(far, (n, 3)), graze])
    d = np.concatenate([target - near, target - far, target - graze])
    return o.astype(F32), d.astype(F32)


@pytest.fixture(params=["ugrid", "voxelwalk", "voxelwalk-ec", "pgrid"])
def ugrid_default(request):
    """The backends whose default walks the two-level grid: ugrid, voxelwalk's IVW (its any-hit
    rays and primary rays; closest hits go through IVW with mode=ivw, set here), voxelwalk's
    one-launch EC (closest hits; viewer.tracing traces them as primary rays, hence primary=ec) and
    pgrid's grid for the rays its per-pass grids do not take (primary=grid sends these there)."""
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    if request.param == "pgrid":
        request.getfixturevalue("monkeypatch").setenv("RTWALK_PGRID", "primary=grid")
        return "pgrid"
    if request.param.startswith("voxelwalk"):
        monkeypatch = request.getfixturevalue("monkeypatch")
        monkeypatch.setenv("RTWALK_VOXELWALK", "mode=ec,primary=ec" if request.param.endswith("ec") else "mode=ivw")
        return "voxelwalk"
    return request.param


@pytest.mark.parametrize("any_hit", [False, True])
def test_mixed_scale_matches_float64(ugrid_default, any_hit):
    """Default ugrid (two-level) on the teapot-in-a-stadium scene: hits equal the reference."""
    rng = np.random.default_rng(21)
    tris = mixed_scene(3)
    o, d = mixed_rays(rng, 1500)
    out = run_case(ugrid_default, tris, o, d, any_hit=any_hit)
    small = out.rtri < len(tris) - 4
    assert small.mean() > 0.3 and (~small & out.rhit).any()  # both the sphere and the ground are hit
    assert_matches(out)


def test_mixed_scale_shadow_rays_from_surface(ugrid_default):
    """Segments from points just above the sphere to a light 1e3 away, tmin > 0: any hit and
    closest hit agree with the reference (the ground and wall are big triangles of the same cells)."""
    rng = np.random.default_rng(22)
    tris = mixed_scene(3)
    v = tris[:-4].astype(np.float64)
    w = rng.dirichlet([1, 1, 1], 1500)
    p = (w[:, :, None] * v[rng.integers(0, len(v), 1500)]).sum(1)
    n = p - [0.0, 5e-4, 0.0]
    o = (p + 1e-6 * n / np.linalg.norm(n, axis=1, keepdims=True)).astype(F32)
    light = np.array([300.0, 800.0, 200.0])
    d = (light - o).astype(F32)
    for any_hit in (False, True):
        out = run_case(ugrid_default, tris, o, d, tmin=1e-6, tmax=1.0, any_hit=any_hit)
        assert out.rhit.any() and not out.rhit.all()
        assert_matches(out)


def _tests_per_ray(tris: np.ndarray, o: np.ndarray, d: np.ndarray, levels: int) -> np.ndarray:
    """Triangle tests of each ray through ugrid's kernel (COUNT_TESTS) over a grid of `levels`."""
    from viewer.accel.grid import UniformGrid, scene_box, triangles_f4
    from viewer.accel.grid2 import TwoLevelGrid
    from viewer.backends.ugrid import GridTracer
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    grid = TwoLevelGrid(ctx) if levels == 2 else UniformGrid(ctx)
    tbuf = clio.upload(ctx, triangles_f4(tris), what="test triangles")
    grid.build(tbuf, len(tris), *scene_box(tris))
    n = len(o)
    ot = np.zeros((n, 4), F32)
    dt = np.zeros((n, 4), F32)
    ot[:, :3], dt[:, :3], dt[:, 3] = o, d, np.inf
    bufs = [clio.upload(ctx, a, what="test rays") for a in (ot, dt)]
    rw = ctx.cl.mem_flags.READ_WRITE
    out_t, out_id, tests = (clio.upload(ctx, np.zeros(n, t), rw, "test hits") for t in (F32, np.int32, np.int32))
    GridTracer(ctx, grid).enqueue(bufs[0], bufs[1], out_t, out_id, n, False, tests=tests)
    got = np.empty(n, np.int32)
    clio.copy(ctx.queue, got, tests)
    for b in (tbuf, *bufs, out_t, out_id, tests):
        b.release()
    grid.release()
    return got


def test_mixed_scale_triangle_tests_bounded():
    """The 20,480-triangle sphere on the ground: the two-level walk tests a few dozen triangles
    per ray (a uniform grid sized for the ground tests the whole sphere: thousands)."""
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    rng = np.random.default_rng(23)
    tris = mixed_scene(5)
    o, d = mixed_rays(rng, 2000)
    two = _tests_per_ray(tris, o, d, 2)
    one = _tests_per_ray(tris, o, d, 1)
    assert one.mean() > 5000  # the case is what it claims: one top cell holds the sphere
    assert two.mean() < 200, f"mean triangle tests per ray {two.mean():.1f} (budget 200; measured 109)"
    assert two.max() < 2000, f"most triangle tests of one ray {two.max()} (budget 2000; measured 985)"


@pytest.mark.parametrize("big", [1e9, 0.25])
def test_forced_configuration_uses_sub_grids(big):
    """The configuration the shared cases run under above really walks sub-grids (and big lists)."""
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    from viewer.accel.grid import GridSpec, scene_box, triangles_f4
    from viewer.accel.grid2 import SubSpec, TwoLevelGrid
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    rng = np.random.default_rng(24)
    c = rng.uniform(-1, 1, (300, 1, 3))
    tris = (c + rng.normal(scale=0.2, size=(300, 3, 3))).astype(F32)
    ctx = cl_context()
    tbuf = clio.upload(ctx, triangles_f4(tris), what="test triangles")
    grid = TwoLevelGrid(ctx, sub=SubSpec(min_small=1, big_frac=big, density=4.0))
    st = grid.build(tbuf, len(tris), *scene_box(tris), GridSpec(density=0.01))
    sub = grid.sub_to_numpy()
    assert st.subgrids >= 1 and (sub["sub_of"] >= 0).sum() == st.subgrids
    listed = np.zeros(len(tris), bool)
    _, cells, refs = grid.to_numpy()
    listed[refs] = True
    assert st.subpairs + st.big >= listed.sum()  # every binned triangle is in a sub-grid or a big list
    assert (st.big > 0) == (big < 1)
    grid.release()
    tbuf.release()


@pytest.fixture
def mixed_on_device():
    """(CL context, the mixed scene's triangles, their device buffer, the scene box)."""
    if CL_REASON is not None:
        pytest.skip(CL_REASON)
    from viewer.accel.grid import scene_box, triangles_f4
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    tris = mixed_scene(4)
    tb = clio.upload(ctx, triangles_f4(tris), what="test triangles")
    try:
        yield ctx, tris, tb, scene_box(tris)
    finally:
        tb.release()


def test_two_level_build_waits_as_the_uniform_grid(mixed_on_device):
    """The sub level adds no wait: a first build waits twice, a rebuild at the same resolution
    once (its counts ride on the top build's last wait), and the rebuild equals a fresh build."""
    from viewer import iostats
    from viewer.accel.grid2 import TwoLevelGrid
    from viewer.cl import io as clio

    ctx, tris, tb, box = mixed_on_device
    exact, again = TwoLevelGrid(ctx), TwoLevelGrid(ctx)
    try:
        clio.finish(ctx.queue)
        iostats.begin_frame()
        st = exact.build(tb, len(tris), *box)
        assert iostats.end_frame().host_syncs == 2
        assert st.subgrids >= 1 and st.big >= 1
        ref = exact.sub_to_numpy()
        again.build(tb, len(tris), *box)
        clio.finish(ctx.queue)
        iostats.begin_frame()
        st2 = again.build(tb, len(tris), *box)
        io = iostats.end_frame()
        assert io.host_syncs == 1, io
        assert (st2.subgrids, st2.subcells, st2.subpairs, st2.big) == (st.subgrids, st.subcells, st.subpairs, st.big)
        got = again.sub_to_numpy()
        for k in ("sub_of", "subs", "scells"):
            assert got[k].tobytes() == ref[k].tobytes(), k
    finally:
        exact.release()
        again.release()


def test_sub_level_stays_within_the_memory_budget(mixed_on_device):
    """A budget the top grid fits but the sub level does not: the sub density is lowered (or the
    sub-grids dropped) until the whole build fits, and the grid still answers as the reference."""
    from viewer.accel.grid2 import SubSpec, TwoLevelGrid
    from viewer.backends.ugrid import GridTracer
    from viewer.cl import io as clio
    from viewer.cl.limits import BUDGET_SHARE, DeviceLimits
    from viewer.reference import trace_float64

    ctx, tris, tb, box = mixed_on_device
    grid = TwoLevelGrid(ctx, sub=SubSpec(density=8.0))
    try:
        full = grid.build(tb, len(tris), *box)
        top = _top_bytes(grid, tb, tris, box)
        sub_part = full.nbytes - top
        assert full.shrunk == 0 and sub_part > 0
        budget = top + sub_part // 3
        lim = DeviceLimits(max_alloc=2**40, global_mem=int(budget / BUDGET_SHARE) + 1)
        st = grid.build(tb, len(tris), *box, limits=lim)
        assert st.shrunk >= 1 and st.nbytes <= lim.budget, (st, lim.budget, top)
        rng = np.random.default_rng(25)
        o, d = mixed_rays(rng, 500)
        n = len(o)
        ot, dt = np.zeros((n, 4), F32), np.zeros((n, 4), F32)
        ot[:, :3], dt[:, :3], dt[:, 3] = o, d, np.inf
        rays = [clio.upload(ctx, a, what="test rays") for a in (ot, dt)]
        rw = ctx.cl.mem_flags.READ_WRITE
        out_t, out_id = (clio.upload(ctx, np.zeros(n, t), rw, "test hits") for t in (F32, np.int32))
        GridTracer(ctx, grid).enqueue(rays[0], rays[1], out_t, out_id, n, False)
        got, got_t = np.empty(n, np.int32), np.empty(n, F32)
        clio.copy(ctx.queue, got, out_id)
        clio.copy(ctx.queue, got_t, out_t)
        ref_t, ref = trace_float64(tris, o, d, np.zeros(n, F32), np.full(n, np.inf, F32))
        # a different triangle at the same distance is a tie (the ground's two halves meet under the sphere)
        same = (got == ref) | np.isclose(got_t, ref_t, rtol=1e-5, atol=0)
        assert same.all(), (np.flatnonzero(~same)[:8], st)
        for b in (*rays, out_t, out_id):
            b.release()
    finally:
        grid.release()


def _top_bytes(grid, tb, tris, box) -> int:
    """Device bytes of the top level alone (the same uniform grid, built on its own)."""
    from viewer.accel.grid import UniformGrid

    g = UniformGrid(grid.ctx)
    try:
        return g.build(tb, len(tris), *box).nbytes
    finally:
        g.release()

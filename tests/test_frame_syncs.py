"""Host synchronisations per frame of the grid backends (viewer.iostats): per-frame grid builds,
ray reordering and EC iterations run on the device with no host round trip between their
kernels, so a steady frame waits on the device a small, fixed number of times whatever the
number of lights and passes, and an EC pass waits once however many iterations it takes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.conftest import opencl_missing
from viewer import iostats

SIZE = (160, 90)
MAX_SYNCS = 10
BACKENDS = ("ugrid", "pgrid", "voxelwalk")


@pytest.fixture(autouse=True)
def _needs_cl():
    if opencl_missing():
        pytest.skip(opencl_missing())


def _scene(lights: int):
    """city (60k triangles) with `lights` point lights (its own one plus copies moved aside)."""
    from tests.conftest import prepared_scene
    from viewer.accel.grid import scene_box

    prep = prepared_scene("city", 60_000)
    base = prep.scene.point_lights[0]
    lo, hi = scene_box(np.asarray(prep.scene.triangles, np.float32).reshape(-1, 3, 3))
    ext = float(np.max(hi - lo))
    extra = [dataclasses.replace(base, position=np.asarray(base.position, np.float32)
                                 + np.array([0.15 * k, 0.0, -0.1 * k], np.float32) * np.float32(ext))
             for k in range(1, lights)]
    return prep, dataclasses.replace(prep.scene, point_lights=[base, *extra])


def _steady_io(backend: str, effects: str, lights: int = 1):
    """The counts of the second frame of a two-frame replay of city-near."""
    return _steady_report(backend, effects, lights).io


def _steady_report(backend: str, effects: str, lights: int = 1):
    """The FrameReport of the second frame of a two-frame replay of city-near."""
    from viewer.effects import parse_effects
    from viewer.gl.context import shared_context
    from viewer.paths import RECORDINGS
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    prep, scene = _scene(lights)
    rec = load_recording(RECORDINGS / "city-near.json")
    r = Renderer(shared_context(), scene, prep.bvh, SIZE, backend, parse_effects(effects))
    try:
        r.render(rec.camera_for_frame(10))
        rep = r.render(rec.camera_for_frame(11))
        assert r.frame_path == "device"
        return rep
    finally:
        r.release()


@pytest.mark.parametrize("backend", BACKENDS)
def test_steady_frame_host_syncs_bounded_and_independent_of_passes_and_lights(backend, gl_ctx):
    io4 = _steady_io(backend, "primary,shadows,ao:4")
    assert io4.host_syncs <= MAX_SYNCS, io4
    io8 = _steady_io(backend, "primary,shadows,ao:8", lights=2)
    assert io8.cl_launches > io4.cl_launches, (io4, io8)  # the extra passes and the second light ran
    assert io8.host_syncs == io4.host_syncs, (io4, io8)


@pytest.mark.parametrize("backend", BACKENDS)
def test_steady_frame_host_syncs_independent_of_effects(backend, gl_ctx):
    """The accumulators of every sampled effect come out after one wait (their copies enqueued
    first): five accumulated effects wait as often as one."""
    one = _steady_io(backend, "primary,shadows")
    five = _steady_io(backend, "primary,shadows,soft:1,ao:2,diffuse:1,reflections")
    assert five.bytes_to_host > one.bytes_to_host  # the other accumulators did come out
    assert five.host_syncs == one.host_syncs <= MAX_SYNCS, (one, five)


def test_voxelwalk_frame_launches_do_not_grow_with_ec_iterations(monkeypatch, gl_ctx):
    """A steady frame with EC passes (diffuse: closest hits) makes the same launches and waits on
    a coarse grid and on a fine one, whose walks take several times the iterations (levels=1: with
    sub-grids the coarse grid's dense cells are walked by sub-cell, so it takes as many)."""
    reps = {}
    for res in (12, 160):
        monkeypatch.setenv("RTWALK_VOXELWALK", f"mode=ec,resolution={res},levels=1")
        reps[res] = _steady_report("voxelwalk", "primary,diffuse:2")
    its = {res: rep.backend_stats["iterations"] for res, rep in reps.items()}
    assert its[160] >= 2 * its[12] > 0, its
    assert reps[160].io.cl_launches == reps[12].io.cl_launches, (reps[12].io, reps[160].io)
    assert reps[160].io.host_syncs == reps[12].io.host_syncs <= MAX_SYNCS, (reps[12].io, reps[160].io)


def test_pgrid_adds_no_wait_of_its_own(gl_ctx):
    """pgrid's per-pass grids (the camera grid, one light grid per point light) wait on the
    device no more often than the uniform grid's frame, which builds nothing per pass: their
    placement, buffer sizes and launch sizes stay on the device (13 waits with one light and 17
    with two before)."""
    base = _steady_io("ugrid", "primary,shadows,ao:4")
    for effects, lights in (("primary,shadows,ao:4", 1), ("primary,shadows,ao:8", 2)):
        io = _steady_io("pgrid", effects, lights)
        assert io.host_syncs == base.host_syncs, (base, io)
        assert io.bytes_to_host <= base.bytes_to_host + 1024, (base, io)  # only counters, copied a pass late


def _reflection_like_rays(n_side: int = 48):
    """Rays from scattered points inside the city's box in scattered directions (incoherent, like
    reflections: many EC iterations)."""
    from tests.conftest import prepared_scene
    from viewer.accel.grid import scene_box

    prep = prepared_scene("city", 60_000)
    tris = np.asarray(prep.scene.triangles, np.float32).reshape(-1, 3, 3)
    lo, hi = scene_box(tris)
    rng = np.random.default_rng(7)
    n = n_side * n_side
    o = np.zeros((n, 4), np.float32)
    d = np.zeros((n, 4), np.float32)
    o[:, :3] = lo + rng.random((n, 3)) * (hi - lo)
    v = rng.normal(size=(n, 3))
    d[:, :3] = v / np.linalg.norm(v, axis=1, keepdims=True)
    d[:, 3] = np.inf
    d[::7, 3] = -1.0  # some inactive rays
    return tris, o, d, (n_side, n_side)


def _ec_passes(resolution: int, ec_sort: str, tmax: float = np.inf):
    """Two EC passes over the reflection-like rays (tmax: a fraction of the scene's diagonal) on a
    grid of `resolution` cells on the longest axis (0: auto): [(io, PassStats) per pass], and the
    hits of the second pass and of IVW."""
    from viewer.accel.grid import GridSpec, UniformGrid, scene_box, triangles_f4
    from viewer.backends.voxelwalk import VoxelWalker
    from viewer.cl import HitStage, RayStage, cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    tris, o, d, size = _reflection_like_rays()
    lo, hi = scene_box(tris)
    d[d[:, 3] > 0, 3] = np.float32(tmax * float(np.linalg.norm(hi - lo)))
    tb = clio.upload(ctx, triangles_f4(tris))
    grid = UniformGrid(ctx)
    grid.build(tb, len(tris), *scene_box(tris), GridSpec(resolution=resolution))
    walker = VoxelWalker(ctx, grid, chunk=64, window=1, ec_sort=ec_sort)
    rs, hs = RayStage(size, ctx), HitStage(size, ctx)
    try:
        rs.upload_arrays(o, d)
        walker.trace_ivw(tb, rs.origin, rs.dir, hs.t, hs.tri, rs.n, False)
        ivw = hs.read()
        per_pass = []
        for _ in range(2):  # the second pass knows the iteration count from the first
            clio.finish(ctx.queue)
            iostats.begin_frame()
            ps = walker.trace_ec(tb, rs.origin, rs.dir, hs.t, hs.tri, rs.n, size=size)
            per_pass.append((iostats.end_frame(), ps))
        return per_pass, hs.read(), ivw
    finally:
        rs.release()
        hs.release()
        walker.release()
        grid.release()
        tb.release()


def test_ec_global_sort_waits_once_and_launches_a_fixed_number_per_iteration():
    """EC with the thesis's global sort: one host wait per pass however many iterations; launches
    grow by a fixed number per iteration (no per-iteration host work), and the result equals IVW's
    (up to ties: its atomic minimum takes the lowest slot at equal distances)."""
    per_pass, (t_ec, id_ec), (t_ivw, id_ivw) = _ec_passes(0, "global")
    io, ps = per_pass[1]
    assert ps.iterations >= 8, ps.iterations  # enough iterations to tell per-iteration waits apart
    assert io.host_syncs == 1, io
    # launches: a fixed number per enqueued iteration, and no more iterations enqueued than run
    io1, ps1 = per_pass[0]
    per_iter = 40
    assert io.cl_launches <= per_iter * ps.iterations + 16, io
    assert io1.host_syncs <= 1 + int(np.ceil(np.log2(max(ps1.iterations, 8) / 8))) + 1, io1
    same = (id_ec == id_ivw) | ((id_ec >= 0) & (t_ec == t_ivw))
    assert same.all()
    assert np.array_equal(np.isinf(t_ec), np.isinf(t_ivw))


def test_ec_launches_do_not_grow_with_iterations():
    """EC in one launch (ec_tile.cl): the same few launches and no wait per pass whether the rays
    take 2 or 50 iterations (coarse and fine grids, short and long rays), and IVW's hits bit for
    bit. Its totals come back with a later wait (here the test's queue finish before pass 2)."""
    runs = {}
    for res, tmax in ((8, 0.02), (0, np.inf), (96, np.inf)):
        per_pass, (t_ec, id_ec), (t_ivw, id_ivw) = _ec_passes(res, "tile", tmax)
        assert np.array_equal(id_ec, id_ivw) and np.array_equal(t_ec, t_ivw)
        for io, _ps in per_pass:
            assert io.host_syncs == 0, io
        runs[(res, tmax)] = per_pass[1]
    its = sorted(ps.iterations for _, ps in runs.values())
    assert its[0] <= 4 and its[-1] >= 4 * its[0] and its[-1] >= 16, its
    launches = {io.cl_launches for io, _ in runs.values()}
    assert launches == {5}, runs  # tile flags, compaction (3), the EC loop


def test_grid_rebuild_waits_once_and_retries_on_overflow():
    """A rebuild at the last resolution sizes its pair buffers from the last build and waits once;
    it equals an exact build, and when the pairs outgrow the buffers it builds again exactly."""
    from tests.conftest import prepared_scene
    from viewer.accel.grid import GridSpec, UniformGrid, scene_box, triangles_f4
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    tris = np.asarray(prepared_scene("city", 60_000).scene.triangles, np.float32).reshape(-1, 3, 3)
    tb = clio.upload(ctx, triangles_f4(tris))
    box = scene_box(tris)
    exact, again = UniformGrid(ctx), UniformGrid(ctx)
    try:
        exact.build(tb, len(tris), *box, GridSpec())
        ref = exact.to_numpy(), exact.blocks_to_numpy()
        again.build(tb, len(tris), *box, GridSpec())
        clio.finish(ctx.queue)
        iostats.begin_frame()
        st = again.build(tb, len(tris), *box, GridSpec())
        io = iostats.end_frame()
        assert io.host_syncs == 1, io
        assert st.pairs == exact.stats.pairs and st.nonempty == exact.stats.nonempty
        for a, b in zip(again.to_numpy()[1:] + again.blocks_to_numpy(), ref[0][1:] + ref[1], strict=True):
            assert a.tobytes() == b.tobytes()
        again._last = (again._last[0], 10)  # buffers far too small: the overflow is seen, then an exact build
        st = again.build(tb, len(tris), *box, GridSpec())
        assert st.pairs == exact.stats.pairs
        assert again.to_numpy()[2].tobytes() == ref[0][2].tobytes()
    finally:
        exact.release()
        again.release()
        tb.release()

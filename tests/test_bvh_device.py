"""Device BVH builder (viewer.accel.bvh_device): the tree checked against the triangles with plain
NumPy (tests.test_bvh.check_tree: every triangle in one leaf, conservative exact float32 boxes,
a valid binary tree in breadth-first order), traversal against float64 brute force and Embree,
SAH quality against the binned SAH builder, and edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_bvh import box_grid_tris, check_gpu_nodes, check_tree, clustered_tris, random_tris
from tests.test_clbvh import CL_REASON, check_bvh4, random_rays
from viewer.accel.bvh import build_bvh
from viewer.accel.bvh4 import build_bvh4
from viewer.reference import EmbreeTracer, compare_hits, trace_float64

pytestmark = pytest.mark.skipif(CL_REASON is not None, reason=f"no OpenCL device: {CL_REASON}")


def device_bvh(tris, **kw):
    from viewer.accel.bvh_device import build_bvh_device

    return build_bvh_device(tris, **kw)


def walk_reaches_each_node_once(bvh) -> None:
    """Independent of the parent links: a walk from the root meets every node exactly once."""
    seen = np.zeros(len(bvh.node_left), np.int64)
    stack = [0]
    while stack:
        v = stack.pop()
        seen[v] += 1
        if bvh.node_left[v] >= 0:
            stack += [int(bvh.node_left[v]), int(bvh.node_right[v])]
    assert (seen == 1).all()


@pytest.mark.parametrize("n", [1, 2, 3, 5, 17, 100])
def test_small_sizes(n):
    tris = random_tris(n, seed=n)
    bvh = device_bvh(tris)
    check_tree(bvh, tris)
    walk_reaches_each_node_once(bvh)
    check_gpu_nodes(bvh)
    if n <= 2:  # at most min_leaf triangles: one leaf
        assert bvh.stats.nodes == 1


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", [0, 777, 4999])
def test_non_finite_input_refused(value, where):
    """The device build checks the coordinates on the device (centre_bounds) with the SAH build's
    error; huge finite coordinates are accepted."""
    from viewer.accel.bvh import NON_FINITE

    tris = random_tris(5000, seed=2)
    tris[where, where % 3, (where // 3) % 3] = value
    with pytest.raises(ValueError, match=NON_FINITE):
        device_bvh(tris)
    with pytest.raises(ValueError, match=NON_FINITE):
        build_bvh(tris)
    tris[where] = 3e38  # finite: no error
    check_tree(device_bvh(tris), tris)


@pytest.mark.parametrize("make", [random_tris, clustered_tris, box_grid_tris])
def test_scenes_structure_and_bvh4(make):
    tris = make(6000, seed=3)
    bvh = device_bvh(tris)
    check_tree(bvh, tris)
    walk_reaches_each_node_once(bvh)
    check_gpu_nodes(bvh)
    check_bvh4(bvh.triangles_in_leaf_order(tris), build_bvh4(bvh), bool(bvh.is_leaf()[0]))


def test_coincident_centroids():
    """Equal Morton codes everywhere (every box centre exactly 0: v0 = a, v1 = -a, v2 inside):
    ties are broken by index and the build still ends with valid leaves; identical triangles too."""
    rng = np.random.default_rng(5)
    a = rng.normal(0, 1, (300, 3)).astype(np.float32)
    tris = np.stack([a, -a, a * rng.uniform(-1, 1, (300, 1)).astype(np.float32)], axis=1)
    centre = (tris.min(axis=1) + tris.max(axis=1)) * np.float32(0.5)
    assert (centre == 0).all()
    bvh = device_bvh(tris)
    check_tree(bvh, tris)
    walk_reaches_each_node_once(bvh)
    same = np.repeat(tris[:1], 64, axis=0)
    bvh = device_bvh(same)
    check_tree(bvh, same)
    walk_reaches_each_node_once(bvh)


def test_far_offset_scene():
    """A scene 1e6 away from the origin: boxes stay exact and conservative, traversal agrees."""
    tris = random_tris(3000, seed=9, extent=50.0, size=0.8) + np.float32(1e6)
    bvh = device_bvh(tris)
    check_tree(bvh, tris)
    sah = build_bvh(tris)
    assert bvh.stats.sah_cost <= 1.15 * sah.stats.sah_cost


def test_sah_within_bound_of_sah_builder():
    from viewer.procedural import make_city

    tris = make_city(40000, 1).triangles
    dev, ref = device_bvh(tris), build_bvh(tris)
    check_tree(dev, tris)
    assert dev.stats.sah_cost <= 1.10 * ref.stats.sah_cost, (dev.stats.sah_cost, ref.stats.sah_cost)


def test_leaf_parameters():
    tris = box_grid_tris(3000, seed=2)
    bvh = device_bvh(tris, max_leaf=8, min_leaf=1)
    check_tree(bvh, tris, max_leaf=8, min_leaf=1)


def test_one_triangle_leaves():
    """Leaves of one triangle: 2n - 1 kept nodes, more than the buffers the layout borrows from PLOC
    and more than the cluster-box buffer the tree is written to when it fits (both fall back)."""
    tris = box_grid_tris(2000, seed=5)
    bvh = device_bvh(tris, max_leaf=1, min_leaf=1)
    check_tree(bvh, tris, max_leaf=1, min_leaf=1)
    walk_reaches_each_node_once(bvh)
    assert bvh.stats.nodes == 2 * len(tris) - 1


@pytest.mark.parametrize("make,n,leaf", [(random_tris, 1, 4), (random_tris, 2, 4), (box_grid_tris, 3000, 4),
                                         (clustered_tris, 20000, 4), (box_grid_tris, 2000, 8)])
def test_device_stats_equal_tree_stats(make, n, leaf):
    """The build's stats (sums made on the device) are tree_stats of the tree it returns."""
    from viewer.accel.bvh import tree_stats

    tris = make(n, seed=7)
    bvh = device_bvh(tris, max_leaf=leaf, min_leaf=min(2, leaf))
    ref = tree_stats(bvh.node_min, bvh.node_max, bvh.node_left, bvh.node_count, bvh.node_depth, n)
    got = bvh.stats
    for f in ("triangles", "nodes", "inner_nodes", "leaves", "depth", "leaf_size_histogram", "memory_bytes"):
        assert getattr(got, f) == getattr(ref, f), f
    assert got.sah_cost == pytest.approx(ref.sah_cost, rel=1e-12)


def _trace_clbvh(tris, bvh, o, d, lo, hi, any_hit):
    """clbvh on the given tree; ids mapped back to the input triangles."""
    from viewer.backends.clbvh import ClbvhScene
    from viewer.cl.transfer import HitStage, RayStage

    n = len(o)
    size = (n, 1)
    scene = ClbvhScene(bvh.triangles_in_leaf_order(tris), bvh)
    rs, hs = RayStage(size, scene.ctx), HitStage(size, scene.ctx)
    try:
        rs.upload_arrays(np.c_[o, lo], np.c_[d, hi])
        scene.enqueue(rs.origin, rs.dir, hs.t, hs.tri, n, any_hit)
        t, slot = hs.read()
    finally:
        rs.release()
        hs.release()
        scene.release()
    t, slot = np.asarray(t).reshape(-1)[:n], np.asarray(slot).reshape(-1)[:n]
    return t, np.where(slot >= 0, bvh.tri_order[np.maximum(slot, 0)], -1)


@pytest.mark.parametrize("any_hit", [False, True])
def test_clbvh_on_device_tree_matches_float64(any_hit):
    tris = random_tris(400, seed=4, extent=20.0, size=2.0)
    o, d = random_rays(3000, seed=4, lo=-2.0, hi=22.0)
    lo = np.zeros(len(o), np.float32)
    hi = np.full(len(o), np.inf, np.float32)
    t, tri = _trace_clbvh(tris, device_bvh(tris), o, d, lo, hi, any_hit)
    rt, rtri = trace_float64(tris, o, d, lo, hi, any_hit=any_hit)
    st = compare_hits(t, tri, rt, rtri, tris)
    assert st["hitmiss_agree"] == 1.0 and st["n_bad_id"] == 0, st
    if not any_hit:
        assert st["id_agree"] == 1.0 and st["max_rel_err"] < 1e-4, st


def test_clbvh_on_device_tree_matches_embree():
    tris = random_tris(20000, seed=2, extent=50.0, size=0.8)
    o, d = random_rays(20000, seed=3, lo=-5.0, hi=55.0)
    lo = np.zeros(len(o), np.float32)
    hi = np.full(len(o), np.inf, np.float32)
    t, tri = _trace_clbvh(tris, device_bvh(tris), o, d, lo, hi, False)
    rt, rtri = EmbreeTracer(tris).trace(o, d, lo, hi, any_hit=False)
    st = compare_hits(t, tri, rt, rtri, tris)
    assert st["hitmiss_agree"] >= 0.9999 and st["n_bad_id"] == 0 and st["id_agree"] >= 0.9999, st


def test_glsl_on_device_tree_matches_float64(monkeypatch):
    """The GLSL backend through viewer.tracing with RTWALK_BVH_BUILDER=device."""
    from viewer import tracing

    monkeypatch.setenv("RTWALK_BVH_BUILDER", "device")
    tracing._CACHE.clear()
    tris = random_tris(300, seed=6, extent=20.0, size=2.0)
    o, d = random_rays(2000, seed=6, lo=-2.0, hi=22.0)
    lo = np.zeros(len(o), np.float32)
    hi = np.full(len(o), np.inf, np.float32)
    try:
        t, tri = tracing.trace_rays(tris, o, d, lo, hi, backend="glsl")
    finally:
        tracing._CACHE.clear()
    rt, rtri = trace_float64(tris, o, d, lo, hi)
    st = compare_hits(t, tri, rt, rtri, tris)
    assert st["hitmiss_agree"] == 1.0 and st["n_bad_id"] == 0 and st["id_agree"] == 1.0, st


def test_block_nearest_equals_per_cluster_nearest():
    """The pair-once block kernels (scalar and eight pairs at a time) find the same neighbours as the
    plain per-cluster search (so the same tree), across block boundaries and with more blocks than
    clusters at the end."""
    from viewer.accel.bvh_device import RADIUS1_ITERATIONS, device_builder

    tris = box_grid_tris(5000, seed=8)
    b = device_builder()
    assert b.vector_nearest  # radius 8: eight pairs at a time
    try:
        b.radius1_iterations = 0  # the radius-1 start is the vector path's only (tested below)
        b.block_nearest = False
        plain = b.build(tris)
        b.block_nearest, b.vector_nearest = True, False
        block = b.build(tris)
        b.vector_nearest = True
        vec = b.build(tris)
    finally:
        b.block_nearest = b.vector_nearest = True
        b.radius1_iterations = RADIUS1_ITERATIONS
    for f in ("node_min", "node_max", "node_left", "node_right", "node_first", "node_count", "tri_order"):
        assert np.array_equal(getattr(plain, f), getattr(block, f)), f
        assert np.array_equal(getattr(plain, f), getattr(vec, f)), f


@pytest.mark.parametrize("make,n", [(box_grid_tris, 5000), (random_tris, 3001), (clustered_tris, 20000),
                                    (random_tris, 2)])
def test_radius1_search_equals_vector_search_at_radius_1(make, n):
    """nearest_r1 (the first iteration's search) finds the neighbours and per-block counts that
    nearest_vec finds at radius 1, across block boundaries: every iteration at radius 1 gives the
    same tree either way."""
    from viewer.accel.bvh_device import DeviceBvhBuilder

    tris = make(n, seed=5)
    b = DeviceBvhBuilder(radius=1)
    b.radius1_floors = (0,)  # small inputs too
    b.radius1_iterations = 0
    vec = b.build(tris)
    b.radius1_iterations = 10**9
    r1 = b.build(tris)
    for f in ("node_min", "node_max", "node_left", "node_right", "node_first", "node_count", "tri_order"):
        assert np.array_equal(getattr(vec, f), getattr(r1, f)), f
    b.release()


def test_refuses_builds_the_device_cannot_hold(monkeypatch):
    from viewer.accel import bvh_device
    from viewer.errors import RtwalkError

    dev = bvh_device.device_builder().ctx.device
    monkeypatch.setattr(bvh_device, "BYTES_PER_TRIANGLE", dev.global_mem_size)  # 2 triangles > memory
    with pytest.raises(RtwalkError, match="device memory"):
        device_bvh(random_tris(2))


def test_builder_choice(monkeypatch):
    from viewer.accel.builders import AUTO_DEVICE_MIN, per_frame_builder, resolve_builder
    from viewer.errors import RtwalkError

    monkeypatch.delenv("RTWALK_BVH_BUILDER", raising=False)
    assert per_frame_builder() == "device"  # OpenCL is there (module skip otherwise)
    assert resolve_builder(None, 1000) == "sah"
    assert resolve_builder(None, AUTO_DEVICE_MIN) == "device"
    assert resolve_builder("sah", AUTO_DEVICE_MIN) == "sah"
    monkeypatch.setenv("RTWALK_BVH_BUILDER", "device")
    assert resolve_builder(None, 10) == "device"
    assert resolve_builder("sah", 10) == "sah"  # the option wins over the environment
    monkeypatch.setenv("RTWALK_BVH_BUILDER", "sah")
    assert per_frame_builder() == "sah"
    monkeypatch.setenv("RTWALK_BVH_BUILDER", "fast")
    with pytest.raises(RtwalkError, match="RTWALK_BVH_BUILDER"):
        resolve_builder(None, 10)


def test_no_host_round_trip_per_iteration():
    """PLOC reads the cluster count back only every check_every iterations: the host syncs of a
    build are a constant (reductions, phase finishes, read-back of the tree), the same for every
    size, plus iterations / check_every."""
    import math

    from viewer import iostats
    from viewer.accel.bvh_device import device_builder

    b = device_builder()
    b.build(random_tris(100))
    fixed = []
    for n in (2000, 20000):
        tris = box_grid_tris(n, seed=1)
        iostats.begin_frame()
        b.build(tris)
        io = iostats.end_frame()
        assert b.iterations >= 3 * b.check_every
        assert io.bytes_to_device >= tris.nbytes
        fixed.append(io.host_syncs - math.ceil(b.iterations / b.check_every))
    assert fixed[0] == fixed[1] <= 30, fixed


def test_bench_bvh_rows_per_builder(tmp_path, capsys):
    import json

    from viewer.cli import main

    assert main(["bench-bvh", "--builders", "sah,device", "--sizes", "3000,5000", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "bvh-build.json").read_text())
    assert report["complete"] is True
    rows = report["rows"]
    assert [(r["builder"], r["target"]) for r in rows] == [("sah", 3000), ("device", 3000), ("sah", 5000),
                                                           ("device", 5000)]
    for r in rows:
        assert r["build_time_s"] > 0 and r["sah_cost"] > 1
        assert r["throughput_mtris_per_s"] == pytest.approx(r["triangles"] / r["build_time_s"] / 1e6)
    sah, dev = rows[0], rows[1]
    assert dev["io"]["cl_launches"] >= 4 * dev["iterations"]  # 4 launches per PLOC iteration
    assert dev["io"]["host_syncs"] <= 30 + -(-dev["iterations"] // 4)
    assert sah["io"]["cl_launches"] == 0
    assert dev["sah_ratio"] == pytest.approx(dev["sah_cost"] / sah["sah_cost"])
    assert "device" in capsys.readouterr().out


def test_overflowing_areas():
    """Coordinates so large that float32 surface areas overflow (inf, NaN costs): still a valid tree."""
    tris = (random_tris(500, seed=4, extent=1.0, size=0.3) * np.float32(1e25)).astype(np.float32)
    bvh = device_bvh(tris)
    check_tree(bvh, tris)
    walk_reaches_each_node_once(bvh)
    check_gpu_nodes(bvh)


@pytest.mark.parametrize("backend", ["glsl", "clbvh"])
def test_renderer_on_device_tree_agrees_with_embree(backend, gl_ctx):
    """prepare_scene with the device builder, then a Renderer frame (primary, shadows, AO)
    traced by each BVH backend, every captured pass against Embree."""
    from tests.test_clbvh import RECORDINGS
    from viewer.effects import parse_effects
    from viewer.recording import load_recording
    from viewer.renderer import Renderer
    from viewer.session import prepare_scene

    prep = prepare_scene("city", scene_size=30_000, quiet=True, bvh_builder="device")
    check_tree(prep.bvh, prep.scene.triangles[np.argsort(prep.bvh.tri_order)])
    rec = load_recording(RECORDINGS / "city-near.json")
    camera = rec.camera_for_frame(rec.frame_count() // 3)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, (160, 90), backend, parse_effects("primary,shadows,ao:2"))
    try:
        rep = r.render(camera, capture=True)
    finally:
        r.release()
    embree = EmbreeTracer(prep.scene.triangles)
    passes = 0
    for cp in rep.captured:
        act = cp.rays.active
        if not act.any():
            continue
        passes += 1
        o, d, lo, hi = cp.rays.origins[act], cp.rays.directions[act], cp.rays.tmin[act], cp.rays.tmax[act]
        rt, rtri = embree.trace(o, d, lo, hi, any_hit=cp.ray_type.any_hit)
        st = compare_hits(cp.t[act], cp.tri[act], rt, rtri, prep.scene.triangles)
        assert st["hitmiss_agree"] >= 0.999 and st["n_bad_id"] == 0, (cp.ray_type.label, st)
        if not cp.ray_type.any_hit:
            assert st["id_agree"] >= 0.999, (cp.ray_type.label, st)
    assert passes >= 3


def test_output_placement_is_disjoint_and_inside_the_regions():
    """_out_offsets (pure): the finished tree's ten arrays never overlap, each lies inside one of the
    four cluster-box regions, and None (a buffer of their own) when they cannot fit; sizes past
    2^32 words stay exact (the kernels take 64-bit offsets)."""
    from viewer.accel.bvh_device import _contiguous_offsets, _out_offsets, _out_sizes

    rng = np.random.default_rng(7)
    cases = [(1, 1), (3, 2), (5, 3), (2 * 1000 - 1, 1000), (900, 1000), (9_199_451, 10_000_004),
             (600_000_000, 700_000_000)]
    for m, n in cases:
        sizes = _out_sizes(m, n)
        for region in (4 * n, 4 * n + 31, 3 * m - 1, 3 * m):
            touched = [int(t) for t in rng.integers(0, region + 1, 4)]
            offs = _out_offsets(m, n, region, touched)
            if offs is None:
                assert sum(sizes) > 4 * region or 3 * m > region or max(sizes) > region
                continue
            spans = sorted((o, o + z) for o, z in zip(offs, sizes, strict=True))
            assert all(a_end <= b_start for (_, a_end), (b_start, _) in zip(spans, spans[1:], strict=False))
            assert all(o // region == (o + z - 1) // region < 4 for o, z in zip(offs, sizes, strict=True))
        contiguous = _contiguous_offsets(m, n)
        assert contiguous[-1] + n == sum(sizes) and contiguous[0] == 0
    assert max(_out_offsets(600_000_000, 700_000_000, 4 * 700_000_000, [0] * 4)) >= 2**32


def test_radius1_floors_pick_the_iterations():
    """Radius 1 in the first PLOC iteration from RADIUS1_FLOORS[0] triangles, in the first two from
    RADIUS1_FLOORS[1]; below, radius 8 throughout (every shared study scene)."""
    from viewer.accel.bvh_device import RADIUS1_FLOORS, device_builder

    b = device_builder()
    first, second = RADIUS1_FLOORS
    assert [b._radius1_iterations(n) for n in (first - 1, first, second - 1, second)] == [0, 1, 1, 2]

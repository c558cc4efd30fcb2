"""clbvh: the BVH4 layout (viewer.accel.bvh4) checked against the triangles with plain NumPy, and the
OpenCL tracer against independent references (float64 watertight brute force, Embree) on random
scenes and on every ray type a Renderer generates."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from viewer.accel.bvh import build_bvh
from viewer.accel.bvh4 import NODE4_DTYPE, build_bvh4
from viewer.paths import RECORDINGS
from viewer.reference import EmbreeTracer, compare_hits, trace_float64


def _cl_reason() -> str | None:
    try:
        from viewer.cl import cl_available
    except Exception as exc:  # noqa: BLE001 - any import failure means no usable OpenCL layer
        return f"viewer.cl not importable: {exc}"
    return cl_available()


CL_REASON = _cl_reason()
needs_cl = pytest.mark.skipif(CL_REASON is not None, reason=f"no OpenCL device: {CL_REASON}")


def random_tris(n, seed=0, extent=20.0, size=1.0):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0, extent, (n, 1, 3))
    return (c + rng.normal(0, size, (n, 3, 3))).astype(np.float32)


def random_rays(r, seed=0, lo=-2.0, hi=22.0):
    rng = np.random.default_rng(seed + 100)
    o = rng.uniform(lo, hi, (r, 3)).astype(np.float32)
    d = rng.normal(size=(r, 3)).astype(np.float32)
    d[rng.random(r) < 0.05, rng.integers(0, 3)] = 0.0  # some axis-parallel components
    return o, d


# ------------------------------------------------------------------------------------------------
# BVH4 layout


def check_bvh4(tris_leaf_order: np.ndarray, b4, root_is_leaf: bool) -> None:
    """Invariants of a BVH4 from its arrays and the leaf-ordered triangles only."""
    assert NODE4_DTYPE.itemsize == 128 and b4.nodes.dtype == NODE4_DTYPE
    nodes = b4.nodes
    m = len(nodes)
    lo = np.stack([nodes["minx"], nodes["miny"], nodes["minz"]], -1)  # (m, 4, 3)
    hi = np.stack([nodes["maxx"], nodes["maxy"], nodes["maxz"]], -1)
    child, count = nodes["child"], nodes["count"]
    inner = child >= 0
    leaf = (child < 0) & (count > 0)
    empty = (child < 0) & (count == 0)
    # empty slots: inverted infinite boxes, ref ~0
    assert np.all(lo[empty] == np.inf) and np.all(hi[empty] == -np.inf) and np.all(child[empty] == -1)
    assert np.all(count[inner] == 0)
    # every node but the root is referenced exactly once, always by an earlier node
    refs = np.bincount(child[inner], minlength=m)
    assert refs[0] == 0 and np.all(refs[1:] == 1)
    parent_of = np.repeat(np.arange(m), 4).reshape(m, 4)[inner]
    assert np.all(child[inner] > parent_of)
    # 2..4 children per node (a one-leaf tree: exactly one)
    per_node = (inner | leaf).sum(1)
    if root_is_leaf:
        assert m == 1 and per_node[0] == 1 and leaf[0, 0]
    else:
        assert per_node.min() >= 2 and per_node.max() <= 4
    # every triangle slot in exactly one leaf
    first = ~child[leaf]
    cnt = count[leaf]
    slots = np.repeat(first, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    assert np.array_equal(np.sort(slots), np.arange(len(tris_leaf_order)))
    # leaf boxes contain their triangles; inner slot boxes contain the child's four slot boxes
    # (so by induction every box contains its whole subtree)
    tri_lo = tris_leaf_order.min(1)
    tri_hi = tris_leaf_order.max(1)
    owner = np.repeat(np.flatnonzero(leaf.ravel()), cnt)
    assert np.all(tri_lo[slots] >= lo.reshape(-1, 3)[owner]) and np.all(tri_hi[slots] <= hi.reshape(-1, 3)[owner])
    c = child[inner]
    sub_valid = (child[c] >= 0) | (count[c] > 0)
    sub_lo = np.where(sub_valid[..., None], lo[c], np.inf).min(1)
    sub_hi = np.where(sub_valid[..., None], hi[c], -np.inf).max(1)
    assert np.all(sub_lo >= lo[inner]) and np.all(sub_hi <= hi[inner])
    # depth (by walking the references) and the stack bound the kernel is built with
    depth = np.zeros(m, np.int64)
    for i in range(m):  # small test trees only
        depth[child[i][inner[i]]] = depth[i] + 1
    assert b4.depth == int(depth.max())
    assert b4.stack_size() >= 3 * b4.depth + 1


@pytest.mark.parametrize("n", [1, 2, 3, 7, 100, 3000])
def test_bvh4_layout(n):
    tris = random_tris(n, seed=n)
    bvh = build_bvh(tris)
    b4 = build_bvh4(bvh)
    check_bvh4(bvh.triangles_in_leaf_order(tris), b4, bool(bvh.is_leaf()[0]))
    assert b4.leaves == bvh.stats.leaves


def test_bvh4_layout_degenerate_and_clustered():
    rng = np.random.default_rng(5)
    same = np.repeat(random_tris(1, seed=3), 50, axis=0)  # all centroids equal: median splits
    chain = (np.arange(200, dtype=np.float32)[:, None, None] ** 2 + rng.normal(0, 0.1, (200, 3, 3))).astype(np.float32)
    for tris in (same, chain):
        bvh = build_bvh(tris)
        check_bvh4(bvh.triangles_in_leaf_order(tris), build_bvh4(bvh), bool(bvh.is_leaf()[0]))


def test_bvh4_collapses_largest_child_first():
    """The greedy rule, checked from the binary tree: the binary nodes a BVH4 node opened (between
    its source node and its children) are never smaller than an inner child it left closed, and a
    node with fewer than 4 children has only leaf children (nothing was left to open)."""
    tris = random_tris(2000, seed=9)
    bvh = build_bvh(tris)
    b4 = build_bvh4(bvh)
    ext = bvh.node_max.astype(np.float64) - bvh.node_min
    area = ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0]
    leaf_of_first = {int(f): i for i, f in enumerate(bvh.node_first) if bvh.node_left[i] < 0}
    for i, node in enumerate(b4.nodes):  # small tree: a Python loop over its nodes is fine here
        src = int(b4.source[i])
        kids = [int(b4.source[c]) if c >= 0 else leaf_of_first[int(~c)]
                for c, n in zip(node["child"], node["count"], strict=True) if c >= 0 or n > 0]
        opened = set()
        for k in kids:
            p = int(bvh.node_parent[k])
            while p != src:
                opened.add(p)
                p = int(bvh.node_parent[p])
        assert len(opened) == len(kids) - 2
        closed_inner = [area[k] for k in kids if bvh.node_left[k] >= 0]
        if len(kids) < 4:
            assert not closed_inner
        if opened and closed_inner:
            assert max(closed_inner) <= min(area[list(opened)])


def test_leaf_blocks_hold_every_triangle_once():
    from viewer.backends.clbvh import LEAF_BLOCK_DTYPE, pack_leaves

    assert LEAF_BLOCK_DTYPE.itemsize == 160
    tris = random_tris(500, seed=4)
    bvh = build_bvh(tris, max_leaf=7, min_leaf=1)  # leaves of more than 4 triangles span blocks
    lo_tris = bvh.triangles_in_leaf_order(tris)
    b4 = build_bvh4(bvh)
    knodes, blocks = pack_leaves(b4.nodes, lo_tris)
    leaf = (b4.nodes["child"] < 0) & (b4.nodes["count"] > 0)
    assert np.array_equal(knodes["child"][~leaf], b4.nodes["child"][~leaf])
    first_blocks = ~knodes["child"][leaf]
    assert np.array_equal(blocks["first"][first_blocks], ~b4.nodes["child"][leaf])
    assert np.all((blocks["count"] >= 1) & (blocks["count"] <= 4))
    lane = np.arange(4)
    used = lane[None, :] < blocks["count"][:, None]
    slots = (blocks["first"][:, None] + lane[None, :])[used]
    assert np.array_equal(np.sort(slots), np.arange(len(tris)))
    v = blocks["v"].transpose(0, 2, 1).reshape(-1, 4, 3, 3)  # (block, lane, vertex, axis)
    assert np.array_equal(v[used], lo_tris[slots])
    assert np.isnan(v[~used]).all()


@needs_cl
@pytest.mark.parametrize("case", ["one", "two", "grid", "clustered", "one_triangle_leaves", "leaves_of_7"])
def test_device_bvh4_collapse_equals_host(case):
    """viewer.accel.bvh4_device makes the host collapse's nodes bit for bit (order, numbering,
    boxes, leaf refs, empty slots), its depth, sources and leaf count."""
    from tests.test_bvh import box_grid_tris, clustered_tris
    from viewer.accel.bvh4_device import build_bvh4_device, device_supported
    from viewer.cl import cl_context

    if not device_supported(cl_context()):
        pytest.skip("no float64 on the OpenCL device")
    bvh = {"one": lambda: build_bvh(random_tris(1, seed=1)), "two": lambda: build_bvh(random_tris(5, seed=1)),
           "grid": lambda: build_bvh(box_grid_tris(3000, seed=2)),
           "clustered": lambda: build_bvh(clustered_tris(8000, seed=3)),
           "one_triangle_leaves": lambda: build_bvh(box_grid_tris(2000, seed=5), max_leaf=1, min_leaf=1),
           "leaves_of_7": lambda: build_bvh(random_tris(3000, seed=6), max_leaf=7, min_leaf=1)}[case]()
    host = build_bvh4(bvh)
    dev, buf = build_bvh4_device(bvh)
    assert dev.nodes.dtype == NODE4_DTYPE and host.nodes.tobytes() == dev.nodes.tobytes()
    assert (dev.depth, dev.leaves) == (host.depth, host.leaves)
    assert np.array_equal(dev.source, host.source)


@needs_cl
def test_packing_from_the_device_bvh4_equals_host_packing():
    """pack_device_bvh4 (kernel nodes and leaf blocks from the BVH4 on the device) writes what the
    host packing writes, bit for bit."""
    from tests.test_bvh import clustered_tris
    from viewer.accel.bvh4_device import build_bvh4_device, device_supported
    from viewer.backends.clbvh import LEAF_BLOCK_DTYPE, pack_device_bvh4, pack_leaves
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    if not device_supported(ctx):
        pytest.skip("no float64 on the OpenCL device")
    tris = clustered_tris(6000, seed=8)
    bvh = build_bvh(tris)
    lo_tris = bvh.triangles_in_leaf_order(tris)
    b4, nodes_buf = build_bvh4_device(bvh, ctx)
    hnodes, hblocks = pack_leaves(b4.nodes, lo_tris)
    kbuf, bbuf = pack_device_bvh4(ctx, nodes_buf, len(b4.nodes), lo_tris)
    dnodes = np.empty(len(hnodes), NODE4_DTYPE)
    dblocks = np.empty(len(hblocks), LEAF_BLOCK_DTYPE)
    clio.copy(ctx.queue, dnodes, kbuf)
    clio.copy(ctx.queue, dblocks, bbuf)
    assert hnodes.tobytes() == dnodes.tobytes()
    assert hblocks.tobytes() == dblocks.tobytes()


@needs_cl
@pytest.mark.parametrize("any_hit", [False, True])
def test_device_collapse_and_packing_trace_like_host(monkeypatch, any_hit):
    """ClbvhScene on the device path (BVH4 collapse and packing on the device, used from
    DEVICE_BVH4_MIN_NODES) traces the same hits, bit for bit, as on the host path."""
    from tests.test_bvh_device import _trace_clbvh
    from viewer.backends import clbvh

    tris = random_tris(3000, seed=11, extent=20.0, size=2.0)
    o, d = random_rays(4000, seed=11, lo=-2.0, hi=22.0)
    lo = np.zeros(len(o), np.float32)
    hi = np.full(len(o), np.inf, np.float32)
    bvh = build_bvh(tris)
    host = _trace_clbvh(tris, bvh, o, d, lo, hi, any_hit)
    monkeypatch.setattr(clbvh, "DEVICE_BVH4_MIN_NODES", 0)
    dev = _trace_clbvh(tris, bvh, o, d, lo, hi, any_hit)
    assert np.array_equal(host[0], dev[0]) and np.array_equal(host[1], dev[1])
    assert (host[1] >= 0).sum() > 100


@needs_cl
@pytest.mark.parametrize("max_leaf", [4, 7])
def test_device_packed_blocks_equal_host_packed(max_leaf):
    """pack.cl writes the same leaf blocks as the host packing (one block per leaf, and leaves
    spanning blocks), NaN padding included."""
    from viewer.backends.clbvh import LEAF_BLOCK_DTYPE, pack_leaves, pack_leaves_device
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    tris = random_tris(700, seed=5)
    bvh = build_bvh(tris, max_leaf=max_leaf, min_leaf=1)
    lo_tris = bvh.triangles_in_leaf_order(tris)
    b4 = build_bvh4(bvh)
    hnodes, hblocks = pack_leaves(b4.nodes, lo_tris)
    dnodes, dbuf = pack_leaves_device(ctx, b4.nodes, lo_tris)
    dblocks = np.empty(len(hblocks), LEAF_BLOCK_DTYPE)
    clio.copy(ctx.queue, dblocks, dbuf)
    dbuf.release()
    assert np.array_equal(hnodes, dnodes)
    assert hblocks.tobytes() == dblocks.tobytes()  # bit for bit, NaN lanes too


# ------------------------------------------------------------------------------------------------
# tracing


@needs_cl
@pytest.mark.parametrize("any_hit", [False, True])
@pytest.mark.parametrize("n_tris", [1, 5, 400])
def test_trace_matches_float64(n_tris, any_hit):
    from viewer.tracing import trace_rays

    tris = random_tris(n_tris, seed=n_tris, extent=4.0 if n_tris < 10 else 20.0, size=2.0)
    o, d = random_rays(3000, seed=n_tris, lo=-2.0, hi=6.0 if n_tris < 10 else 22.0)
    rng = np.random.default_rng(7)
    lo = rng.uniform(0, 0.5, len(o)).astype(np.float32)
    hi = np.where(rng.random(len(o)) < 0.3, rng.uniform(0.5, 10, len(o)), np.inf).astype(np.float32)
    hi[:50] = lo[:50]  # inactive
    t, tri = trace_rays(tris, o, d, lo, hi, any_hit=any_hit, backend="clbvh")
    rt, rtri = trace_float64(tris, o, d, lo, hi, any_hit=any_hit)
    assert np.all(tri[:50] == -1) and np.all(np.isinf(t[:50]))
    st = compare_hits(t, tri, rt, rtri, tris)
    assert st["hitmiss_agree"] == 1.0, st
    assert st["n_bad_id"] == 0, st
    hit = tri >= 0
    assert np.all((t[hit] > lo[hit]) & (t[hit] < hi[hit]))
    if not any_hit:
        assert st["id_agree"] == 1.0, st
        assert st["max_rel_err"] < 1e-4, st
        # t is the plane-equation distance evaluated in IEEE float32 without fused multiply-adds and
        # with a correctly rounded division (as NumPy evaluates it; docs/numerics.md), the normal
        # rounded once from the exact float64 cross product of the float32 edges: bit for bit,
        # wherever the normal is not perpendicular to d
        v = tris[tri[hit]].astype(np.float32)
        e1, e2 = (v[:, 1] - v[:, 0]).astype(np.float64), (v[:, 2] - v[:, 0]).astype(np.float64)
        n = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                      e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], 1).astype(np.float32)
        a = v[:, 0] - o[hit]
        dn = n[:, 0] * d[hit, 0] + n[:, 1] * d[hit, 1] + n[:, 2] * d[hit, 2]
        t_np = (n[:, 0] * a[:, 0] + n[:, 1] * a[:, 1] + n[:, 2] * a[:, 2]) / dn
        assert np.array_equal(t[hit], t_np)


@needs_cl
@pytest.mark.parametrize("any_hit", [False, True])
def test_rays_counter_counts_active_rays(any_hit):
    """The kernel's count of active rays (the backend's `rays` counter) equals the convention's
    active rays (viewer.reference.prepare_rays, NumPy) for a batch that is not a multiple of the
    work-group size and holds every kind of inactive ray; inactive rays miss."""
    from viewer.backends.clbvh import ClbvhScene
    from viewer.cl.transfer import HitStage, RayStage
    from viewer.reference import prepare_rays

    tris = random_tris(50, seed=4, extent=6.0, size=1.5)
    size = (37, 29)  # 1,073 rays: 16 full work-groups of 64 and a partial one
    n = size[0] * size[1]
    o, d = random_rays(n, seed=5, lo=-2.0, hi=8.0)
    rng = np.random.default_rng(6)
    lo = rng.uniform(0, 0.5, n).astype(np.float32)
    hi = np.where(rng.random(n) < 0.5, rng.uniform(0.5, 10, n), np.inf).astype(np.float32)
    kind = rng.integers(0, 8, n)
    hi[kind == 1] = lo[kind == 1]                       # empty range
    hi[kind == 2] = lo[kind == 2] - 1.0                 # reversed range
    o[kind == 3, 1] = np.nan
    d[kind == 4, 2] = np.inf
    lo[kind == 5] = -np.inf
    hi[kind == 6] = np.nan
    expected = int(prepare_rays(o, d, lo, hi)[4].sum())
    assert 0 < expected < n - 300
    scene = ClbvhScene(tris, build_bvh(tris))
    rs, hs = RayStage(size, scene.ctx), HitStage(size, scene.ctx)
    try:
        rs.upload_arrays(np.c_[o, lo], np.c_[d, hi])
        scene.enqueue(rs.origin, rs.dir, hs.t, hs.tri, n, any_hit)
        assert scene.active_count() == expected
        t, tri = hs.read()
        inactive = ~prepare_rays(o, d, lo, hi)[4]
        assert np.all(tri[inactive] == -1) and np.all(np.isinf(t[inactive]))
        assert (tri[~inactive] >= 0).any()
    finally:
        rs.release()
        hs.release()
        scene.release()


@needs_cl
@pytest.mark.parametrize("any_hit", [False, True])
def test_trace_matches_embree_random_scene(any_hit):
    from viewer.tracing import trace_rays

    tris = random_tris(20000, seed=2, extent=50.0, size=0.8)
    o, d = random_rays(40000, seed=3, lo=-5.0, hi=55.0)
    lo = np.zeros(len(o), np.float32)
    hi = np.full(len(o), np.inf, np.float32)
    t, tri = trace_rays(tris, o, d, lo, hi, any_hit=any_hit, backend="clbvh")
    rt, rtri = EmbreeTracer(tris).trace(o, d, lo, hi, any_hit=any_hit)
    st = compare_hits(t, tri, rt, rtri, tris)
    assert st["hitmiss_agree"] >= 0.9999, st
    assert st["n_bad_id"] == 0, st
    if not any_hit:
        assert st["id_agree"] >= 0.9999, st


@needs_cl
def test_renderer_every_ray_type_agrees_with_embree(gl_ctx):
    """A Renderer with backend clbvh on city at 320x180: each captured pass against Embree."""
    from viewer.effects import RayType, parse_effects
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    camera = rec.camera_for_frame(rec.frame_count() // 3)
    settings = parse_effects("primary,shadows,soft:2,ao:2,diffuse:2,reflections")
    r = Renderer(gl_ctx, prep.scene, prep.bvh, (320, 180), "clbvh", settings)
    try:
        rep = r.render(camera, capture=True)
    finally:
        r.release()
    assert any(k.startswith("trace:") for k in rep.gpu_ms), rep.gpu_ms
    # the counter is the frame's active rays, summed over its passes (NumPy on the captured rays)
    assert rep.backend_stats["rays"] == sum(int(cp.rays.active.sum()) for cp in rep.captured) > 0
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
            assert st["id_agree"] >= 0.999, label
    assert {RayType.PRIMARY, RayType.SHADOW, RayType.SOFT, RayType.AO, RayType.DIFFUSE} <= seen, seen

"""Tests for viewer.accel.bvh: structure, boxes, GPU layout, SAH quality, traversal, edge cases.

Every check is computed independently from the original triangles with plain NumPy (or small
Python reference builders), never from the builder's own intermediate data.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from viewer.accel.bvh import (
    EMPTY_BOX_MAX,
    EMPTY_BOX_MIN,
    GPU_NODE_DTYPE,
    GPU_TRI_DTYPE,
    BuildStats,
    bench_build,
    build_bvh,
    gpu_triangles,
)

# ------------------------------------------------------------------------------------------------
# scenes


def random_tris(n, seed=0, extent=100.0, size=2.0):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0, extent, (n, 1, 3))
    return (c + rng.normal(0, size, (n, 3, 3))).astype(np.float32)


def clustered_tris(n, seed=0, clusters=12):
    rng = np.random.default_rng(seed)
    centers = rng.uniform(0, 100, (clusters, 3))
    which = rng.integers(0, clusters, n)
    c = centers[which] + rng.normal(0, 3, (n, 3))
    return (c[:, None, :] + rng.normal(0, 0.5, (n, 3, 3))).astype(np.float32)


def box_grid_tris(n, seed=0):
    """Axis-aligned boxes (12 triangles each) on a jittered grid, topped up with random tris."""
    rng = np.random.default_rng(seed)
    nb = n // 12
    g = int(np.ceil(max(nb, 1) ** (1 / 3)))
    cells = rng.permutation(g**3)[:nb]
    c = np.stack(np.unravel_index(cells, (g, g, g)), 1) * 10.0 + rng.uniform(-2, 2, (nb, 3))
    h = rng.uniform(0.2, 4, (nb, 3))
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    tris = (c[:, None, :] + h[:, None, :] * corners[None])[:, faces].reshape(-1, 3, 3)
    rest = n - len(tris)
    if rest:
        extra = rng.uniform(0, g * 10, (rest, 1, 3)) + rng.normal(0, 1, (rest, 3, 3))
        tris = np.concatenate([tris, extra])
    return tris.astype(np.float32)


# ------------------------------------------------------------------------------------------------
# independent checks


def half_area(lo, hi):
    e = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def check_tree(bvh, tris, max_leaf=4, min_leaf=2):
    """Validate a BVH against the original triangles; returns (leaf indices, inner indices)."""
    n = len(tris)
    m = len(bvh.node_left)
    for name, dt, shape in [
        ("node_min", np.float32, (m, 3)),
        ("node_max", np.float32, (m, 3)),
        ("node_left", np.int32, (m,)),
        ("node_right", np.int32, (m,)),
        ("node_first", np.int32, (m,)),
        ("node_count", np.int32, (m,)),
        ("node_parent", np.int32, (m,)),
        ("node_height", np.int32, (m,)),
        ("node_depth", np.int32, (m,)),
        ("tri_order", np.int32, (n,)),
    ]:
        arr = getattr(bvh, name)
        assert arr.dtype == dt, name
        assert arr.shape == shape, name

    # every triangle exactly once
    assert np.array_equal(np.sort(bvh.tri_order), np.arange(n))

    left, right = bvh.node_left.astype(np.int64), bvh.node_right.astype(np.int64)
    first, count = bvh.node_first.astype(np.int64), bvh.node_count.astype(np.int64)
    leaf = left < 0
    assert np.array_equal(leaf, right < 0)
    assert np.array_equal(bvh.is_leaf(), leaf)
    inner = np.flatnonzero(~leaf)
    leaves = np.flatnonzero(leaf)

    # root
    assert bvh.node_parent[0] == -1 and bvh.node_depth[0] == 0
    assert first[0] == 0 and count[0] == n
    assert (bvh.node_parent[1:] >= 0).all()

    # every non-root node is the child of exactly one node, stored after it
    children = np.concatenate([left[inner], right[inner]])
    assert np.array_equal(np.sort(children), np.arange(1, m))
    assert (left[inner] > inner).all() and (right[inner] > inner).all()
    assert (bvh.node_parent[left[inner]] == inner).all()
    assert (bvh.node_parent[right[inner]] == inner).all()
    # BFS order: depth never decreases along the array
    assert (np.diff(bvh.node_depth) >= 0).all()
    assert (bvh.node_depth[left[inner]] == bvh.node_depth[inner] + 1).all()
    assert (bvh.node_depth[right[inner]] == bvh.node_depth[inner] + 1).all()

    # contiguous ranges: children partition the parent's range, left first
    assert (first[left[inner]] == first[inner]).all()
    assert (first[right[inner]] == first[inner] + count[left[inner]]).all()
    assert (count[left[inner]] + count[right[inner]] == count[inner]).all()
    assert (count[left[inner]] >= 1).all() and (count[right[inner]] >= 1).all()
    # leaf ranges tile [0, n)
    order = np.argsort(first[leaves])
    lf, lc = first[leaves][order], count[leaves][order]
    assert lf[0] == 0 and (lf[1:] == lf[:-1] + lc[:-1]).all() and lf[-1] + lc[-1] == n

    # leaf sizes and leaf rules
    assert (count[leaves] >= 1).all()
    assert (count[leaves] <= max(max_leaf, 1)).all()
    assert (count[inner] > max(min_leaf, 1)).all()

    # heights
    h = bvh.node_height.astype(np.int64)
    assert (h[leaves] == 0).all()
    assert (h[inner] == 1 + np.maximum(h[left[inner]], h[right[inner]])).all()

    # boxes: leaves exact (tight and conservative) from the original float32 vertices ...
    slot_tris = tris[bvh.tri_order]
    vmin, vmax = slot_tris.min(axis=1), slot_tris.max(axis=1)
    leaf_min = np.minimum.reduceat(vmin, lf, axis=0)
    leaf_max = np.maximum.reduceat(vmax, lf, axis=0)
    assert np.array_equal(bvh.node_min[leaves][order], leaf_min)
    assert np.array_equal(bvh.node_max[leaves][order], leaf_max)
    # ... inner boxes are the exact union of the child boxes (so they contain the subtree)
    assert np.array_equal(
        bvh.node_min[inner], np.minimum(bvh.node_min[left[inner]], bvh.node_min[right[inner]])
    )
    assert np.array_equal(
        bvh.node_max[inner], np.maximum(bvh.node_max[left[inner]], bvh.node_max[right[inner]])
    )
    # every vertex inside the root box, and inside the box of its leaf
    assert (tris.reshape(-1, 3) >= bvh.node_min[0]).all() and (tris.reshape(-1, 3) <= bvh.node_max[0]).all()
    slot_leaf = np.repeat(leaves[order], lc)
    assert (slot_tris >= bvh.node_min[slot_leaf][:, None, :]).all()
    assert (slot_tris <= bvh.node_max[slot_leaf][:, None, :]).all()

    # stats
    s = bvh.stats
    assert isinstance(s, BuildStats)
    assert s.triangles == n and s.nodes == m
    assert s.inner_nodes == len(inner) and s.leaves == len(leaves)
    assert s.depth == int(bvh.node_depth[leaves].max())
    hist = {}
    for c in count[leaves]:
        hist[int(c)] = hist.get(int(c), 0) + 1
    assert s.leaf_size_histogram == hist
    assert s.memory_bytes == max(len(inner), 1) * 64 + n * 48
    a = half_area(bvh.node_min, bvh.node_max)
    root_a = a[0] if a[0] > 0 else 1.0
    sah = (a[inner].sum() + (a[leaves] * count[leaves]).sum()) / root_a
    assert s.sah_cost == pytest.approx(sah, rel=1e-6)
    json.dumps(s.to_dict())
    return leaves, inner


def check_gpu_nodes(bvh):
    """Decode gpu_nodes() by walking it from index 0 and compare with the canonical tree."""
    g = bvh.gpu_nodes()
    assert g.dtype == GPU_NODE_DTYPE and g.dtype.itemsize == 64
    leaf = bvh.is_leaf()
    idx = bvh.inner_index_of_node()
    assert idx.dtype == np.int32 and idx.shape == leaf.shape
    if leaf.all():  # single leaf wrapped in one node
        assert len(g) == 1 and idx[0] == 0
        assert g["left"][0] == ~int(bvh.node_first[0]) and g["lcount"][0] == bvh.node_count[0]
        assert np.array_equal(g["lmin"][0], bvh.node_min[0]) and np.array_equal(g["lmax"][0], bvh.node_max[0])
        assert g["rcount"][0] == 0 and g["right"][0] < 0
        assert (g["rmin"][0] == EMPTY_BOX_MIN).all() and (g["rmax"][0] == EMPTY_BOX_MAX).all()
        assert (g["rmin"][0] > g["rmax"][0]).all()
        return g
    inner = np.flatnonzero(~leaf)
    assert len(g) == len(inner)
    assert (idx[leaf] == -1).all()
    assert np.array_equal(idx[inner], np.arange(len(inner)))
    assert np.array_equal(bvh.inner_nodes(), inner)
    # walk the GPU array from the root; map gpu index -> canonical node on the way
    seen_leaves = []
    stack = [(0, 0)]  # (gpu index, canonical node)
    visited = np.zeros(len(g), bool)
    while stack:
        gi, node = stack.pop()
        assert not visited[gi]
        visited[gi] = True
        rec = g[gi]
        for side, child in (("l", bvh.node_left[node]), ("r", bvh.node_right[node])):
            ref = int(rec["left" if side == "l" else "right"])
            cnt = int(rec[side + "count"])
            assert np.array_equal(rec[side + "min"], bvh.node_min[child])
            assert np.array_equal(rec[side + "max"], bvh.node_max[child])
            if ref < 0:
                assert leaf[child]
                assert ~ref == bvh.node_first[child] and cnt == bvh.node_count[child]
                seen_leaves.append(child)
            else:
                assert not leaf[child] and cnt == 0
                assert ref > gi  # children stored after the parent
                assert ref == idx[child]
                stack.append((ref, child))
    assert visited.all()
    assert sorted(seen_leaves) == sorted(np.flatnonzero(leaf).tolist())
    return g


# ------------------------------------------------------------------------------------------------
# reference builders / costs


def median_split_cost(tris, max_leaf=4):
    """SAH cost (traversal 1, intersection 1) of a simple object-median-split tree."""
    bmin, bmax = tris.min(axis=1).astype(np.float64), tris.max(axis=1).astype(np.float64)
    cent = (bmin + bmax) / 2
    root = half_area(bmin.min(0), bmax.max(0))

    def rec(ids):
        a = half_area(bmin[ids].min(0), bmax[ids].max(0))
        if len(ids) <= max_leaf:
            return a * len(ids)
        ax = np.argmax(np.ptp(cent[ids], axis=0))
        ids = ids[np.argsort(cent[ids, ax], kind="stable")]
        h = len(ids) // 2
        return a + rec(ids[:h]) + rec(ids[h:])

    return rec(np.arange(len(tris))) / root


def best_sweep_split_cost(tris):
    """Brute force: best object split (sorted by box centre on each axis) of all triangles."""
    bmin, bmax = tris.min(axis=1).astype(np.float64), tris.max(axis=1).astype(np.float64)
    cent = (bmin + bmax) / 2
    n = len(tris)
    a = half_area(bmin.min(0), bmax.max(0))
    best = np.inf
    for ax in range(3):
        o = np.argsort(cent[:, ax], kind="stable")
        for i in range(1, n):
            lo, hi = o[:i], o[i:]
            al = half_area(bmin[lo].min(0), bmax[lo].max(0))
            ar = half_area(bmin[hi].min(0), bmax[hi].max(0))
            c = 1 + (al * i + ar * (n - i)) / a
            best = min(best, c)
    return best


def best_binned_split_cost(tris, bins=16):
    """Brute force: best split of a 16-bin SAH over the centroid bounds (Python loops)."""
    bmin, bmax = tris.min(axis=1).astype(np.float64), tris.max(axis=1).astype(np.float64)
    cent = (bmin + bmax) / 2
    a = half_area(bmin.min(0), bmax.max(0))
    cmin, cmax = cent.min(0), cent.max(0)
    best = np.inf
    for ax in range(3):
        if cmax[ax] == cmin[ax]:
            continue
        b = np.minimum(((cent[:, ax] - cmin[ax]) * (bins / (cmax[ax] - cmin[ax]))).astype(int), bins - 1)
        for s in range(bins - 1):
            lo, hi = b <= s, b > s
            if lo.sum() == 0 or hi.sum() == 0:
                continue
            al = half_area(bmin[lo].min(0), bmax[lo].max(0))
            ar = half_area(bmin[hi].min(0), bmax[hi].max(0))
            best = min(best, 1 + (al * lo.sum() + ar * hi.sum()) / a)
    return best


def root_split_cost(bvh):
    a = half_area(bvh.node_min, bvh.node_max)
    lft, rgt = bvh.node_left[0], bvh.node_right[0]
    return 1 + (a[lft] * bvh.node_count[lft] + a[rgt] * bvh.node_count[rgt]) / a[0]


# ------------------------------------------------------------------------------------------------
# float64 traversal of the GPU layout


def ray_tri(o, d, v0, v1, v2):
    """Moller-Trumbore in float64, broadcasting; returns t (inf for a miss)."""
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = (e1 * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        u = (s * p).sum(-1) * inv
        q = np.cross(s, e1)
        v = (d * q).sum(-1) * inv
        t = (e2 * q).sum(-1) * inv
    ok = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.where(ok, t, np.inf)


def brute_force(o, d, tris):
    t64 = tris.astype(np.float64)
    best_t = np.full(len(o), np.inf)
    best_i = np.full(len(o), -1)
    for c in range(0, len(o), 200):
        sl = slice(c, c + 200)
        t = ray_tri(o[sl, None], d[sl, None], t64[None, :, 0], t64[None, :, 1], t64[None, :, 2])
        i = np.argmin(t, axis=1)
        best_t[sl] = t[np.arange(len(i)), i]
        best_i[sl] = np.where(np.isfinite(best_t[sl]), i, -1)
    return best_t, best_i


def traverse_gpu(o, d, g, slot_tris):
    """Wavefront stack traversal of gpu_nodes over all rays at once (float64 slab tests)."""
    r = len(o)
    tv = slot_tris.astype(np.float64)
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    stack = np.zeros((r, 256), np.int64)
    sp = np.ones(r, np.int64)  # stack[:, 0] = 0: the root
    best_t = np.full(r, np.inf)
    best_slot = np.full(r, -1)
    steps = 0
    while (sp > 0).any():
        steps += 1
        assert steps < 10000
        act = np.flatnonzero(sp > 0)
        sp[act] -= 1
        node = g[stack[act, sp[act]]]
        oa, ia = o[act], inv[act]
        for side in ("l", "r"):
            lo = node[side + "min"].astype(np.float64)
            hi = node[side + "max"].astype(np.float64)
            with np.errstate(invalid="ignore"):
                t1, t2 = (lo - oa) * ia, (hi - oa) * ia
            tn = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf).max(1)
            tf = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(1)
            tol = 1e-9 * np.maximum(np.abs(tf), 1.0)
            hit = (tn <= tf + tol) & (tf >= -tol) & (tn <= best_t[act] + tol)
            ref = node["left" if side == "l" else "right"]
            cnt = node[side + "count"]
            # inner children: push
            push = hit & (ref >= 0)
            pa = act[push]
            stack[pa, sp[pa]] = ref[push]
            sp[pa] += 1
            assert (sp < stack.shape[1]).all()
            # leaf children: intersect their triangles now
            lf = hit & (ref < 0)
            for j in range(int(cnt[lf].max(initial=0))):
                sel = lf & (j < cnt)
                ra = act[sel]
                slot = ~ref[sel] + j
                t = ray_tri(o[ra], d[ra], tv[slot, 0], tv[slot, 1], tv[slot, 2])
                better = t < best_t[ra]
                best_t[ra[better]] = t[better]
                best_slot[ra[better]] = slot[better]
    return best_t, best_slot


def make_rays(tris, n, seed=1):
    rng = np.random.default_rng(seed)
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    pad = 0.1 * (hi - lo) + 1.0  # + 1: flat scenes need origins off their plane
    o = rng.uniform(lo - pad, hi + pad, (n, 3))
    # half the rays aim at a random triangle's centroid, half go in random directions
    target = tris[rng.integers(0, len(tris), n)].astype(np.float64).mean(axis=1)
    d = target - o
    rnd = rng.normal(size=(n, 3))
    d[n // 2 :] = rnd[n // 2 :]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


# ------------------------------------------------------------------------------------------------
# tests


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 16, 17, 33, 64, 100, 257])
def test_small_sizes(n):
    tris = random_tris(n, seed=n)
    bvh = build_bvh(tris)
    check_tree(bvh, tris)
    check_gpu_nodes(bvh)


@pytest.mark.parametrize("n", [1, 2])
def test_single_leaf_tree(n):
    tris = random_tris(n)
    bvh = build_bvh(tris)
    assert len(bvh.node_left) == 1 and bvh.is_leaf()[0]
    g = check_gpu_nodes(bvh)
    assert g["left"][0] == -1 and g["lcount"][0] == n  # ~0: slot 0
    assert bvh.stats.depth == 0 and bvh.stats.inner_nodes == 0 and bvh.stats.memory_bytes == 64 + 48 * n


@pytest.mark.parametrize(
    "scene",
    [
        "random",
        "clustered",
        "boxes",
        "flat_z0",
        "identical",
        "same_centroid",
        "huge_offset",
        "points",
        "line",
    ],
)
def test_scenes_structure(scene):
    rng = np.random.default_rng(5)
    if scene == "random":
        tris = random_tris(3000)
    elif scene == "clustered":
        tris = clustered_tris(3000)
    elif scene == "boxes":
        tris = box_grid_tris(3000)
    elif scene == "flat_z0":  # zero extent along z
        tris = random_tris(2000)
        tris[:, :, 2] = 0
    elif scene == "identical":  # all centroids coincide on all axes
        tris = np.repeat(random_tris(1), 1000, axis=0)
    elif scene == "same_centroid":  # different triangles, one shared box centre
        s = rng.uniform(0.1, 10, (500, 1, 1)).astype(np.float32)
        base = np.array([[-1, -1, -1], [1, 0, 0], [0, 1, 1]], np.float32)
        tris = (base[None] * s + 5).astype(np.float32)
    elif scene == "huge_offset":
        tris = (random_tris(2000, extent=10.0, size=0.01) + np.float32(1e5)).astype(np.float32)
    elif scene == "points":  # degenerate triangles: all three vertices equal, zero-area boxes
        p = rng.uniform(0, 10, (700, 1, 3))
        p[::7] = 3.0  # plus a pile of coincident points
        tris = np.repeat(p, 3, axis=1).astype(np.float32)
    else:  # all on one line: node boxes with zero area
        x = rng.uniform(0, 100, (600, 3, 1))
        tris = np.concatenate([x, np.zeros_like(x), np.zeros_like(x)], axis=2).astype(np.float32)
    bvh = build_bvh(tris)
    check_tree(bvh, tris)
    check_gpu_nodes(bvh)
    assert bvh.stats.depth <= 64 + int(np.ceil(np.log2(len(tris))))


def test_depth_limit_falls_back_to_median(monkeypatch):
    import viewer.accel.bvh as bvh_mod

    monkeypatch.setattr(bvh_mod, "DEPTH_LIMIT", 3)
    tris = clustered_tris(3000, seed=2)
    bvh = build_bvh(tris)
    check_tree(bvh, tris)
    check_gpu_nodes(bvh)
    # below depth 3 every node is halved: at most 3 + ceil(log2(3000 / 4)) + 1 levels
    assert bvh.stats.depth <= 3 + int(np.ceil(np.log2(3000 / 4))) + 1


def test_overflowing_areas():
    """Coordinates so large that float32 surface areas overflow: still a valid tree."""
    tris = (random_tris(500, seed=4, extent=1.0, size=0.3) * np.float32(1e25)).astype(np.float32)
    bvh = build_bvh(tris)
    check_tree(bvh, tris)
    check_gpu_nodes(bvh)


def test_identical_triangles_are_balanced():
    tris = np.repeat(random_tris(1), 1024, axis=0)
    bvh = build_bvh(tris)
    check_tree(bvh, tris)
    # median fallback halves the node every level
    assert bvh.stats.depth <= 10
    assert max(bvh.stats.leaf_size_histogram) <= 4


@pytest.mark.parametrize(
    "kw",
    [
        dict(bins=32),
        dict(bins=16, max_leaf=8, min_leaf=4),
        dict(max_leaf=1, min_leaf=1),
        dict(max_leaf=2, min_leaf=0),
        dict(traversal_cost=3.0, intersect_cost=1.0, max_leaf=8),
    ],
)
def test_parameters(kw):
    tris = clustered_tris(1500, seed=3)
    bvh = build_bvh(tris, **kw)
    check_tree(bvh, tris, max_leaf=kw.get("max_leaf", 4), min_leaf=kw.get("min_leaf", 2))
    check_gpu_nodes(bvh)


def test_higher_traversal_cost_gives_bigger_leaves():
    tris = random_tris(3000, seed=9)
    cheap = build_bvh(tris, max_leaf=8, traversal_cost=0.5)
    dear = build_bvh(tris, max_leaf=8, traversal_cost=8.0)
    mean = lambda b: b.node_count[b.is_leaf()].mean()  # noqa: E731
    assert mean(dear) > mean(cheap)


def test_invalid_input():
    with pytest.raises(ValueError):
        build_bvh(np.zeros((0, 3, 3), np.float32))
    with pytest.raises(ValueError):
        build_bvh(np.zeros((4, 3), np.float32))
    bad = random_tris(4)
    bad[1, 1, 1] = np.nan
    with pytest.raises(ValueError):
        build_bvh(bad)


def test_sah_beats_median_split():
    tris = clustered_tris(2000, seed=11)
    bvh = build_bvh(tris)
    ref = median_split_cost(tris)
    assert bvh.stats.sah_cost < ref
    # a clear margin on clustered data
    assert bvh.stats.sah_cost < 0.95 * ref


@pytest.mark.parametrize("n", [6, 20, 32])
def test_small_root_split_is_exact_sweep_optimum(n):
    """Nodes of <= 32 triangles are split by a full sweep: the root split must be optimal."""
    tris = clustered_tris(n, seed=n)
    bvh = build_bvh(tris, max_leaf=2, min_leaf=1)
    assert not bvh.is_leaf()[0]
    assert root_split_cost(bvh) == pytest.approx(best_sweep_split_cost(tris), rel=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_binned_root_split_matches_brute_force(seed):
    tris = clustered_tris(300, seed=seed, clusters=5)
    bvh = build_bvh(tris)
    got = root_split_cost(bvh)
    assert got == pytest.approx(best_binned_split_cost(tris, 16), rel=1e-4)
    assert got >= best_sweep_split_cost(tris) * (1 - 1e-6)


@pytest.mark.parametrize("scene", ["random", "flat"])
def test_traversal_matches_brute_force(scene):
    if scene == "random":
        tris = random_tris(2000, seed=21, extent=50.0, size=2.0)
        nrays = 2000
    else:
        tris = random_tris(800, seed=22, extent=20.0, size=1.0)
        tris[:, :, 2] = 0.0
        nrays = 500
    bvh = build_bvh(tris)
    g = check_gpu_nodes(bvh)
    o, d = make_rays(tris, nrays, seed=5)
    bt, bi = brute_force(o, d, tris)
    tt, slot = traverse_gpu(o, d, g, tris[bvh.tri_order])
    assert np.isfinite(bt).sum() > nrays // 3  # the test must actually hit things
    assert np.array_equal(np.isfinite(tt), np.isfinite(bt))
    hit = np.isfinite(bt)
    assert np.array_equal(tt[hit], bt[hit])
    found = bvh.tri_order[slot[hit]]
    same = found == bi[hit]
    # ties (two triangles at exactly the same t) may resolve differently
    assert same.all() or np.array_equal(tt[hit][~same], bt[hit][~same])


def test_gpu_dtypes_layout():
    assert GPU_NODE_DTYPE.itemsize == 64
    off = {k: GPU_NODE_DTYPE.fields[k][1] for k in GPU_NODE_DTYPE.names}
    assert off == dict(lmin=0, left=12, lmax=16, right=28, rmin=32, lcount=44, rmax=48, rcount=60)
    assert GPU_TRI_DTYPE.itemsize == 48
    off = {k: GPU_TRI_DTYPE.fields[k][1] for k in GPU_TRI_DTYPE.names}
    assert off == dict(v0=0, id=12, v1=16, mat=28, v2=32, pad=44)


def test_gpu_triangles():
    tris = random_tris(50)
    bvh = build_bvh(tris)
    mats = np.arange(50, dtype=np.int32) % 7
    ordered = bvh.triangles_in_leaf_order(tris)
    gt = gpu_triangles(ordered, mats[bvh.tri_order])
    assert gt.dtype == GPU_TRI_DTYPE
    assert np.array_equal(gt["id"], np.arange(50))
    assert np.array_equal(gt["v0"], tris[bvh.tri_order, 0])
    assert np.array_equal(gt["v2"], tris[bvh.tri_order, 2])
    assert np.array_equal(gt["mat"], mats[bvh.tri_order])
    assert (gt["pad"] == 0).all()


def test_progress_and_stats_dict():
    tris = box_grid_tris(5000)
    calls = []
    bvh = build_bvh(tris, progress=lambda done, total: calls.append((done, total)))
    assert len(calls) == bvh.stats.depth + 1 == int(bvh.node_depth.max()) + 1
    assert all(t == 5000 for _, t in calls)
    done = [c for c, _ in calls]
    assert done == sorted(done) and done[-1] == 5000
    d = json.loads(json.dumps(bvh.stats.to_dict()))
    assert d["triangles"] == 5000 and d["nodes"] == bvh.stats.nodes
    assert sum(d["leaf_size_histogram"].values()) == bvh.stats.leaves
    b = bench_build(tris)
    assert b["triangles"] == 5000 and b["mtris_per_s"] > 0
    assert b["throughput_mtris_per_s"] == b["mtris_per_s"] and b["gpu_pack_time_s"] >= 0
    json.dumps(b)


def test_build_200k_boxes():
    tris = box_grid_tris(200_000, seed=3)
    t0 = time.perf_counter()
    bvh = build_bvh(tris)
    dt = time.perf_counter() - t0
    print(f"\n200k box-grid triangles: build {dt:.2f} s, {bvh.stats.nodes} nodes, depth {bvh.stats.depth}, "
          f"SAH {bvh.stats.sah_cost:.1f}")  # fmt: skip
    check_tree(bvh, tris)
    g = bvh.gpu_nodes()
    assert len(g) == bvh.stats.inner_nodes


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("RTWALK_BVH_1M"), reason="set RTWALK_BVH_1M=1 for the 1M build")
def test_build_1m_boxes():
    tris = box_grid_tris(1_000_000, seed=4)
    d = bench_build(tris)
    print(f"\n1M box-grid triangles: build {d['build_time_s']:.2f} s ({d['mtris_per_s']:.2f} Mtris/s)")

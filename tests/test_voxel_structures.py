"""Voxel BVH, KD-tree and octree against NumPy invariants: every voxel in exactly one leaf of at
most 8, boxes / cells / cubes contain what lies under them, the build rules (midpoint of the
longest axis, best of the 32-bin SAH planes by brute force, octants) hold at every node."""

from __future__ import annotations

import numpy as np
import pytest

from viewer.accel.voxel_bvh import NODE_DTYPE as BVH_NODE
from viewer.accel.voxel_bvh import build_voxel_bvh
from viewer.accel.voxel_kd import NODE_DTYPE as KD_NODE
from viewer.accel.voxel_kd import build_voxel_kd
from viewer.accel.voxel_leaves import EMPTY, LEAF_DTYPE
from viewer.accel.voxel_octree import NODE_DTYPE as OCT_NODE
from viewer.accel.voxel_octree import build_voxel_octree
from viewer.accel.voxelize import voxel_keys, voxelize


@pytest.fixture(scope="module")
def vox():
    rng = np.random.default_rng(7)
    base = rng.random((60, 1, 3)) * 10
    tris = (base + rng.normal(size=(60, 3, 3)) * rng.choice([0.3, 2.0], size=(60, 1, 1))).astype(np.float32)
    return voxelize(tris, 64)


def leaf_voxels(s, ref):
    leaf = s.leaves[~ref]
    k = int(leaf["count"])
    assert 1 <= k <= 8
    return leaf["vox"][:k].astype(np.int64), s.voxel_tri[leaf["first"]:leaf["first"] + k]


def check_leaves_cover(s, vox, seen_leaves):
    assert sorted(seen_leaves) == list(range(len(s.leaves)))  # every leaf reached exactly once
    allv = np.concatenate([s.leaves["vox"][i, :s.leaves["count"][i]] for i in range(len(s.leaves))])
    keys = voxel_keys(allv, vox.grid.resolution)
    assert len(keys) == vox.count and np.array_equal(np.sort(keys), vox.keys)
    # representative triangles travel with their voxels
    tri = np.concatenate([s.voxel_tri[s.leaves["first"][i]:s.leaves["first"][i] + s.leaves["count"][i]]
                          for i in range(len(s.leaves))])
    assert np.array_equal(tri[np.argsort(keys)], vox.tri)
    assert np.all(s.leaves["vox"][np.arange(8)[None, :] >= s.leaves["count"][:, None]] == 0)


def test_sizes():
    assert BVH_NODE.itemsize == 36 and KD_NODE.itemsize == 12 and OCT_NODE.itemsize == 20
    assert LEAF_DTYPE.itemsize == 56


def test_bvh(vox):
    s = build_voxel_bvh(vox)
    seen, depths = [], []

    def walk(ref, lo, hi, depth):
        if ref < 0:
            v, _ = leaf_voxels(s, ref)
            assert np.array_equal(v.min(0), lo) and np.array_equal(v.max(0) + 1, hi)  # tight box
            seen.append(~ref)
            depths.append(depth)
            return v
        nd = s.nodes[ref]
        ext = hi - lo
        axis = int(nd["axis"])
        assert ext[axis] == ext.max()  # longest axis
        mid = (lo[axis] + hi[axis]) // 2
        out = []
        for k in range(2):
            v = walk(int(nd["child"][k]), nd["lo"][k].astype(np.int64), nd["hi"][k].astype(np.int64), depth + 1)
            assert np.all(v[:, axis] < mid) if k == 0 else np.all(v[:, axis] >= mid)
            out.append(v)
        v = np.concatenate(out)
        assert len(v) > 8
        assert np.array_equal(v.min(0), lo) and np.array_equal(v.max(0) + 1, hi)
        return v

    walk(s.root, s.root_lo.astype(np.int64), s.root_hi.astype(np.int64), 0)
    check_leaves_cover(s, vox, seen)
    assert np.array_equal(np.sort(depths), np.sort(s.leaf_depth))
    assert s.stats["mean_leaf_depth"] == pytest.approx(np.mean(depths))
    assert s.stats["var_leaf_depth"] == pytest.approx(np.var(depths))


def test_kd(vox):
    s = build_voxel_kd(vox)
    seen = []
    checked = [0]

    def walk(ref, lo, hi, depth):
        if ref == EMPTY:
            return np.zeros((0, 3), np.int64)
        if ref < 0:
            v, _ = leaf_voxels(s, ref)
            assert np.all((v >= lo) & (v < hi))
            seen.append(~ref)
            assert s.leaf_depth[~ref] == depth
            return v
        nd = s.nodes[ref]
        a, p = int(nd["axis"]), int(nd["plane"])
        assert lo[a] < p < hi[a]
        hl, lr = hi.copy(), lo.copy()
        hl[a] = p
        lr[a] = p
        v = np.concatenate([walk(int(nd["child"][0]), lo, hl, depth + 1), walk(int(nd["child"][1]), lr, hi, depth + 1)])
        assert len(v) > 8 and np.all((v >= lo) & (v < hi))
        if checked[0] < 40:  # the chosen plane is the cheapest 32-bin SAH plane (brute force)
            checked[0] += 1
            best = np.inf
            ext = hi - lo
            for ax in range(3):
                area = np.prod(np.delete(ext, ax))
                for k in range(1, 32):
                    q = lo[ax] + (ext[ax] * k) // 32
                    if lo[ax] < q < hi[ax]:
                        nl = np.sum(v[:, ax] < q)
                        best = min(best, (q - lo[ax]) * area * nl + (hi[ax] - q) * area * (len(v) - nl))
            nl = np.sum(v[:, a] < p)
            area = np.prod(np.delete(ext, a))
            assert (p - lo[a]) * area * nl + (hi[a] - p) * area * (len(v) - nl) == best
        return v

    walk(s.root, s.root_lo.astype(np.int64), s.root_hi.astype(np.int64), 0)
    check_leaves_cover(s, vox, seen)
    assert checked[0] > 10


def test_octree(vox):
    s = build_voxel_octree(vox)
    R = vox.grid.resolution
    seen = []

    def walk(ni, origin, level):
        nd = s.nodes[ni]
        assert np.array_equal(nd["origin"], origin) and nd["level"] == level
        assert (int(nd["child_mask"]) & int(nd["leaf_mask"])) == 0
        half = R >> (level + 1)
        total = 0
        for o in range(8):
            co = origin + half * np.array([o & 1, (o >> 1) & 1, (o >> 2) & 1])
            below = (1 << o) - 1
            if nd["child_mask"] >> o & 1:
                total += walk(int(nd["first_child"]) + bin(int(nd["child_mask"]) & below).count("1"), co, level + 1)
            elif nd["leaf_mask"] >> o & 1:
                li = int(nd["first_leaf"]) + bin(int(nd["leaf_mask"]) & below).count("1")
                v, _ = leaf_voxels(s, ~li)
                assert np.all((v >= co) & (v < co + half))
                assert s.leaf_depth[li] == level + 1
                seen.append(li)
                total += len(v)
        assert total > 8
        return total

    assert walk(0, np.zeros(3, np.int64), 0) == vox.count
    check_leaves_cover(s, vox, seen)
    # leaves are runs of the Morton-sorted voxels: ordered by `first`, the codes increase throughout
    from viewer.accel.voxel_octree import morton3

    by_first = np.argsort(s.leaves["first"])
    allv = np.concatenate([s.leaves["vox"][i, :s.leaves["count"][i]] for i in by_first])
    code = morton3(allv, 6)
    assert np.all(np.diff(code) > 0)


def test_tiny_sets_are_one_leaf():
    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32)
    vox = voxelize(tris, 2)
    for build in (build_voxel_bvh, build_voxel_kd, build_voxel_octree):
        s = build(vox)
        if vox.count <= 8 and build is not build_voxel_octree:
            assert s.root == -1 and len(s.leaves) == 1

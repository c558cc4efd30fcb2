"""Voxel BVH (Chajdas & Westermann): top-down midpoint split of the longest axis, leaves <= 8 voxels.

Why midpoint and not SAH: voxels are unit cubes on a grid, so a spatial midpoint split is cheap
and gives children separated by a plane; the traversal can then order children by the sign of
the ray direction on the split axis alone (strictly front to back, no distance sort).

NODE_DTYPE (36 bytes, interior buffer, breadth-first order, root = 0):
  lo    uint16 (2, 3)  child boxes, inclusive voxel coordinates (child 0, child 1)
  hi    uint16 (2, 3)  exclusive upper corners
  child int32 (2,)     child references (voxel_leaves: >= 0 interior, < 0 leaf ~ref)
  axis  uint32         split axis; child 0 holds the voxels with coordinate < the split plane
Leaves: voxel_leaves.LEAF_DTYPE, separate buffer.
"""

from __future__ import annotations

import time

import numpy as np

from viewer.accel.voxel_leaves import LEAF_SIZE, VoxelStructure, build_start, finish, segment_ids
from viewer.accel.voxelize import Voxels

NODE_DTYPE = np.dtype([("lo", "<u2", (2, 3)), ("hi", "<u2", (2, 3)), ("child", "<i4", (2,)), ("axis", "<u4")])
assert NODE_DTYPE.itemsize == 36


def build_voxel_bvh(vox: Voxels) -> VoxelStructure:
    """Level by level, vectorised over the nodes of a level."""
    t0 = time.perf_counter()
    b = build_start(vox.coords)
    c = b.coords.astype(np.int32)
    n = len(c)
    perm = np.arange(n)
    lo0 = c.min(axis=0) if n else np.zeros(3, np.int32)
    hi0 = c.max(axis=0) + 1 if n else np.zeros(3, np.int32)
    levels: list[np.ndarray] = []
    leaf_s, leaf_c, leaf_d, start, count = b.leaf_starts, b.leaf_counts, b.leaf_depths, b.start, b.count
    lo = lo0[None].astype(np.int64)
    hi = hi0[None].astype(np.int64)
    next_interior, depth = 1, 0
    while len(start):
        J = len(start)
        axis = np.argmax(hi - lo, axis=1)
        rows = np.arange(J)
        mid = (lo[rows, axis] + hi[rows, axis]) // 2
        seg, pos = segment_ids(start, count)
        el = perm[pos]
        side = (c[el, axis[seg]] >= mid[seg]).astype(np.int64)
        order = np.lexsort((side, seg))
        el = el[order]
        perm[pos] = el
        lcount = count - np.bincount(seg, weights=side, minlength=J).astype(np.int64)
        assert np.all((lcount > 0) & (lcount < count))
        first = np.cumsum(count) - count  # segment starts inside the level's element list
        bounds = np.stack([first, first + lcount], axis=1).ravel()
        ce = c[el]
        clo = np.minimum.reduceat(ce, bounds, axis=0).reshape(J, 2, 3)
        chi = np.maximum.reduceat(ce, bounds, axis=0).reshape(J, 2, 3) + 1
        ccount = np.stack([lcount, count - lcount], axis=1)
        cstart = np.stack([start, start + lcount], axis=1)
        inner = ccount > LEAF_SIZE
        nodes = np.zeros(J, NODE_DTYPE)
        nodes["lo"] = clo
        nodes["hi"] = chi
        nodes["axis"] = axis
        ref = np.zeros((J, 2), np.int64)
        ni = int(inner.sum())
        ref[inner] = next_interior + np.arange(ni)
        next_interior += ni
        leaf_ids = len(leaf_s) + np.arange(int((~inner).sum()))
        ref[~inner] = ~leaf_ids
        nodes["child"] = ref
        levels.append(nodes)
        leaf_s += cstart[~inner].tolist()
        leaf_c += ccount[~inner].tolist()
        leaf_d += [depth + 1] * int((~inner).sum())
        start, count = cstart[inner], ccount[inner]
        lo, hi = clo[inner].astype(np.int64), chi[inner].astype(np.int64)
        depth += 1
    nodes = np.concatenate(levels) if levels else np.zeros(0, NODE_DTYPE)
    return finish("bvh", vox.grid.resolution, nodes, c[perm], vox.tri[perm], leaf_s, leaf_c, leaf_d,
                  lo0, hi0, time.perf_counter() - t0)

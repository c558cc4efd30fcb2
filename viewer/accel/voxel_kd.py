"""Voxel KD-tree (Chajdas & Westermann): binned SAH with 32 bins, leaves <= 8 voxels.

Cost of a split = volume(left cell) * voxels(left) + volume(right cell) * voxels(right), over
the 31 planes lo + floor(extent * k / 32) (k = 1..31) of each axis strictly inside the cell;
split planes lie on voxel boundaries, so no voxel straddles one and cells never overlap. A node
is split while it holds more than 8 voxels (the leaf size of the paper); empty cells are not
stored (child reference EMPTY).

NODE_DTYPE (12 bytes, interior buffer, breadth-first order, root = 0):
  child int32 (2,)  child references (voxel_leaves: >= 0 interior, < 0 leaf ~ref, EMPTY)
  plane uint16      split plane, absolute grid coordinate (child 0: coordinate < plane)
  axis  uint16      split axis
The root cell is the voxels' bounding box (VoxelStructure.root_lo/root_hi); a node's cell is
implicit (traversal clips the ray interval at the planes, Horn et al. 2007).
Leaves: voxel_leaves.LEAF_DTYPE, separate buffer.
"""

from __future__ import annotations

import time

import numpy as np

from viewer.accel.voxel_leaves import EMPTY, LEAF_SIZE, VoxelStructure, build_start, finish, segment_ids
from viewer.accel.voxelize import Voxels

NODE_DTYPE = np.dtype([("child", "<i4", (2,)), ("plane", "<u2"), ("axis", "<u2")])
assert NODE_DTYPE.itemsize == 12
BINS = 32


def sah_planes(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """int64 (J, 3, BINS - 1): candidate planes per node and axis (may repeat or touch the cell)."""
    k = np.arange(1, BINS)
    return lo[:, :, None] + ((hi - lo)[:, :, None] * k) // BINS


def sah_costs(coords: np.ndarray, seg: np.ndarray, lo: np.ndarray, hi: np.ndarray, count: np.ndarray):
    """(planes (J, 3, 31), costs (J, 3, 31) with inf for planes not strictly inside the cell)."""
    J = len(lo)
    planes = sah_planes(lo, hi)
    ext = (hi - lo).astype(np.float64)
    costs = np.empty(planes.shape)
    big = np.int64(1 << 17)
    for a in range(3):
        p = planes[:, a, :]
        keyed = (np.arange(J)[:, None] * big + p).ravel()
        b = np.searchsorted(keyed, seg * big + coords[:, a], side="right") - seg * (BINS - 1)
        hist = np.bincount(seg * BINS + b, minlength=J * BINS).reshape(J, BINS)
        nleft = np.cumsum(hist, axis=1)[:, : BINS - 1]
        area = np.prod(np.delete(ext, a, axis=1), axis=1)[:, None]
        vl = (p - lo[:, a:a + 1]) * area
        vr = (hi[:, a:a + 1] - p) * area
        cost = vl * nleft + vr * (count[:, None] - nleft)
        valid = (p > lo[:, a:a + 1]) & (p < hi[:, a:a + 1])
        costs[:, a, :] = np.where(valid, cost, np.inf)
    return planes, costs


def build_voxel_kd(vox: Voxels) -> VoxelStructure:
    """Level by level, vectorised over the nodes of a level."""
    t0 = time.perf_counter()
    b = build_start(vox.coords)
    c = b.coords
    n = len(c)
    perm = np.arange(n)
    lo0 = c.min(axis=0) if n else np.zeros(3, np.int64)
    hi0 = c.max(axis=0) + 1 if n else np.zeros(3, np.int64)
    levels: list[np.ndarray] = []
    leaf_s, leaf_c, leaf_d, start, count = b.leaf_starts, b.leaf_counts, b.leaf_depths, b.start, b.count
    lo, hi = lo0[None], hi0[None]
    next_interior, depth = 1, 0
    while len(start):
        J = len(start)
        rows = np.arange(J)
        seg, pos = segment_ids(start, count)
        el = perm[pos]
        planes, costs = sah_costs(c[el], seg, lo, hi, count)
        best = costs.reshape(J, -1).argmin(axis=1)
        axis, kbest = best // (BINS - 1), best % (BINS - 1)
        plane = planes[rows, axis, kbest]
        assert np.all(np.isfinite(costs.reshape(J, -1)[rows, best]))
        side = (c[el, axis[seg]] >= plane[seg]).astype(np.int64)
        order = np.lexsort((side, seg))
        perm[pos] = el[order]
        lcount = count - np.bincount(seg, weights=side, minlength=J).astype(np.int64)
        ccount = np.stack([lcount, count - lcount], axis=1)
        cstart = np.stack([start, start + lcount], axis=1)
        clo = np.repeat(lo[:, None, :], 2, axis=1)
        chi = np.repeat(hi[:, None, :], 2, axis=1)
        chi[rows, 0, axis] = plane
        clo[rows, 1, axis] = plane
        inner = ccount > LEAF_SIZE
        leaf = (ccount > 0) & ~inner
        ref = np.full((J, 2), EMPTY, np.int64)
        ni = int(inner.sum())
        ref[inner] = next_interior + np.arange(ni)
        next_interior += ni
        ref[leaf] = ~(len(leaf_s) + np.arange(int(leaf.sum())))
        nodes = np.zeros(J, NODE_DTYPE)
        nodes["child"] = ref
        nodes["plane"] = plane
        nodes["axis"] = axis
        levels.append(nodes)
        leaf_s += cstart[leaf].tolist()
        leaf_c += ccount[leaf].tolist()
        leaf_d += [depth + 1] * int(leaf.sum())
        start, count = cstart[inner], ccount[inner]
        lo, hi = clo[inner], chi[inner]
        depth += 1
    nodes = np.concatenate(levels) if levels else np.zeros(0, NODE_DTYPE)
    s = finish("kd", vox.grid.resolution, nodes, c[perm], vox.tri[perm], leaf_s, leaf_c, leaf_d,
               lo0, hi0, time.perf_counter() - t0)
    s.stats["empty_cells"] = int(np.sum(nodes["child"] == EMPTY))
    return s

"""Voxel octree (Chajdas & Westermann): Morton order, recursive subdivision of the grid cube;
a child holding <= 8 voxels becomes a leaf at whatever level it is (so leaves sit at any level).

Why Morton order: the voxels under any octree node are one contiguous run of the Morton-sorted
voxel array, so the build is a sort plus per-level bit extraction, and leaves store voxels in
Morton order.

NODE_DTYPE (20 bytes, interior buffer, breadth-first order, root = 0 = the cube [0, R)^3):
  origin      uint16 (3,)  node cube's lower corner, grid units
  level       uint16       depth; edge = R >> level
  first_child int32        interior index of the node's first interior child; its interior
                           children follow consecutively in octant order
  first_leaf  int32        leaf index of its first leaf child; leaf children consecutive likewise
  child_mask  uint8        bit o: octant o holds an interior child (o = x | y << 1 | z << 2, the
                           bit is set for the upper half of that axis)
  leaf_mask   uint8        bit o: octant o is a leaf
  pad         uint16
Child of octant o: interior first_child + popcount(child_mask & ((1 << o) - 1)), or leaf
first_leaf + popcount(leaf_mask & ((1 << o) - 1)). Leaves: voxel_leaves.LEAF_DTYPE.
"""

from __future__ import annotations

import time

import numpy as np

from viewer.accel.voxel_leaves import LEAF_SIZE, VoxelStructure, build_start, finish
from viewer.accel.voxelize import Voxels

NODE_DTYPE = np.dtype([("origin", "<u2", (3,)), ("level", "<u2"), ("first_child", "<i4"), ("first_leaf", "<i4"),
                       ("child_mask", "u1"), ("leaf_mask", "u1"), ("pad", "<u2")])
assert NODE_DTYPE.itemsize == 20


def morton3(coords: np.ndarray, bits: int) -> np.ndarray:
    """int64 Morton codes: bit i of x, y, z at bits 3i, 3i + 1, 3i + 2."""
    c = np.asarray(coords, np.int64)
    code = np.zeros(len(c), np.int64)
    for i in range(bits):
        for a in range(3):
            code |= ((c[:, a] >> i) & 1) << (3 * i + a)
    return code


def build_voxel_octree(vox: Voxels) -> VoxelStructure:
    """Level by level over the Morton-sorted voxels, vectorised over the nodes of a level."""
    t0 = time.perf_counter()
    R = vox.grid.resolution
    D = R.bit_length() - 1
    code = morton3(vox.coords, D)
    order = np.argsort(code, kind="stable")
    code = code[order]
    b = build_start(vox.coords[order])
    c = b.coords
    tri = vox.tri[order]
    levels: list[np.ndarray] = []
    leaf_s, leaf_c, leaf_d, start, count = b.leaf_starts, b.leaf_counts, b.leaf_depths, b.start, b.count
    origin = np.zeros((len(start), 3), np.int64)
    next_interior, level = 1, 0
    while len(start):
        J = len(start)
        shift = 3 * (D - level - 1)
        seg = np.repeat(np.arange(J), count)
        first = np.cumsum(count) - count
        pos = start[seg] + (np.arange(len(seg)) - first[seg])
        octant = (code[pos] >> shift) & 7
        cnt = np.bincount(seg * 8 + octant, minlength=J * 8).reshape(J, 8)
        cstart = start[:, None] + np.cumsum(cnt, axis=1) - cnt  # Morton order: octants contiguous
        inner = cnt > LEAF_SIZE
        leaf = (cnt > 0) & ~inner
        bit = (1 << np.arange(8))[None, :]
        nodes = np.zeros(J, NODE_DTYPE)
        nodes["origin"] = origin
        nodes["level"] = level
        nodes["child_mask"] = (inner * bit).sum(axis=1)
        nodes["leaf_mask"] = (leaf * bit).sum(axis=1)
        ni = inner.sum(axis=1)
        nodes["first_child"] = next_interior + np.cumsum(ni) - ni
        nl = leaf.sum(axis=1)
        nodes["first_leaf"] = len(leaf_s) + np.cumsum(nl) - nl
        next_interior += int(ni.sum())
        levels.append(nodes)
        leaf_s += cstart[leaf].tolist()
        leaf_c += cnt[leaf].tolist()
        leaf_d += [level + 1] * int(leaf.sum())
        half = R >> (level + 1)
        o = np.arange(8)
        offs = np.stack([o & 1, (o >> 1) & 1, (o >> 2) & 1], axis=1) * half  # (8, 3)
        corigin = origin[:, None, :] + offs[None]
        start, count, origin = cstart[inner], cnt[inner], corigin[inner]
        level += 1
    nodes = np.concatenate(levels) if levels else np.zeros(0, NODE_DTYPE)
    return finish("octree", R, nodes, c, tri, leaf_s, leaf_c, leaf_d, np.zeros(3), np.full(3, R),
                  time.perf_counter() - t0)

"""What the three voxel structures (voxel_bvh, voxel_kd, voxel_octree) share: the leaf layout,
the container handed to the traversal kernels, and the statistics the study reports.

Leaves hold the voxel positions themselves (Chajdas & Westermann: a leaf test reads no other
buffer): LEAF_DTYPE = 8 x (x, y, z) uint16 voxel coordinates, then `first` (index of the leaf's
first voxel in the structure's leaf-ordered `voxel_tri`, for the representative triangle) and
`count` (1..8; unused slots are zero). Interior nodes live in a separate buffer whose layout
each structure documents. A child reference is an int32: >= 0 an interior node, < 0 the leaf
~ref, EMPTY (INT32_MIN, KD-tree only) an empty cell.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LEAF_SIZE = 8
LEAF_DTYPE = np.dtype([("vox", "<u2", (LEAF_SIZE, 3)), ("first", "<i4"), ("count", "<i4")])
assert LEAF_DTYPE.itemsize == 56
EMPTY = np.int32(np.iinfo(np.int32).min)


@dataclass
class VoxelStructure:
    """A linearised voxel structure: interior nodes, leaves, and the root reference and box."""

    kind: str  # "bvh" | "kd" | "octree"
    resolution: int
    nodes: np.ndarray  # the structure's NODE_DTYPE
    leaves: np.ndarray  # LEAF_DTYPE
    voxel_tri: np.ndarray  # int32, representative triangle of each voxel in leaf order
    root: int  # child reference of the root (0, or ~0 when the whole set fits one leaf)
    root_lo: np.ndarray  # uint16 (3,), root box, grid units, inclusive
    root_hi: np.ndarray  # uint16 (3,), exclusive
    leaf_depth: np.ndarray  # int32 per leaf, root = depth 0
    voxel_coords: np.ndarray | None = None  # uint16 (n, 3) in leaf order (host side, for checks)
    stats: dict = field(default_factory=dict)

    @property
    def memory_bytes(self) -> int:
        return int(self.nodes.nbytes + self.leaves.nbytes + self.voxel_tri.nbytes)


def pack_leaves(coords: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """LEAF_DTYPE leaves; leaf i holds coords[starts[i] : starts[i] + counts[i]] (leaf order)."""
    starts = np.asarray(starts, np.int64)
    counts = np.asarray(counts, np.int64)
    assert np.all((counts >= 1) & (counts <= LEAF_SIZE))
    leaves = np.zeros(len(starts), LEAF_DTYPE)
    leaves["first"] = starts
    leaves["count"] = counts
    slot = np.arange(LEAF_SIZE)
    valid = slot[None, :] < counts[:, None]
    src = np.where(valid, starts[:, None] + slot[None, :], 0)
    vox = np.asarray(coords, np.uint16)[src]  # (L, 8, 3)
    leaves["vox"] = np.where(valid[:, :, None], vox, 0)
    return leaves


def finish(kind: str, resolution: int, nodes: np.ndarray, coords: np.ndarray, tri: np.ndarray,
           starts: list, counts: list, depths: list, root_lo, root_hi, seconds: float) -> VoxelStructure:
    """Leaves packed, root reference chosen, statistics filled (node sizes, depth mean/variance, memory)."""
    starts_a = np.asarray(starts, np.int64)
    counts_a = np.asarray(counts, np.int64)
    depth = np.asarray(depths, np.int32)
    leaves = pack_leaves(coords, starts_a, counts_a)
    root = 0 if len(nodes) else -1
    s = VoxelStructure(kind, resolution, nodes, leaves, np.asarray(tri, np.int32), root,
                       np.asarray(root_lo, np.uint16), np.asarray(root_hi, np.uint16), depth,
                       np.asarray(coords, np.uint16))
    s.stats = {
        "structure": kind, "resolution": resolution, "voxels": int(counts_a.sum()),
        "interior_nodes": int(len(nodes)), "leaves": int(len(leaves)),
        "node_bytes": int(nodes.dtype.itemsize), "leaf_bytes": int(LEAF_DTYPE.itemsize),
        "memory_bytes": s.memory_bytes,
        "mean_leaf_depth": float(depth.mean()) if len(depth) else 0.0,
        "var_leaf_depth": float(depth.var()) if len(depth) else 0.0,
        "max_leaf_depth": int(depth.max()) if len(depth) else 0,
        "voxels_per_leaf": float(counts_a.mean()) if len(counts_a) else 0.0,
        "build_seconds": seconds,
    }
    return s


@dataclass
class BuildStart:
    """Where every level-by-level voxel build begins: the voxels' int64 coordinates, the leaf lists
    (a structure of at most LEAF_SIZE voxels is one leaf at depth 0) and the first level's node
    segments (start, count) over the voxel list (empty when the root is a leaf)."""

    coords: np.ndarray  # int64 (N, 3)
    leaf_starts: list = field(default_factory=list)
    leaf_counts: list = field(default_factory=list)
    leaf_depths: list = field(default_factory=list)
    start: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    count: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def build_start(coords: np.ndarray) -> BuildStart:
    c = np.asarray(coords).astype(np.int64)
    n = len(c)
    b = BuildStart(c)
    if 0 < n <= LEAF_SIZE:
        b.leaf_starts, b.leaf_counts, b.leaf_depths = [0], [n], [0]
    elif n > LEAF_SIZE:
        b.start = np.array([0], np.int64)
        b.count = np.array([n], np.int64)
    return b


def segment_ids(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segment id, element position) of every element of the segments [start, start + count)."""
    counts = np.asarray(counts, np.int64)
    seg = np.repeat(np.arange(len(counts)), counts)
    first = np.cumsum(counts) - counts
    pos = np.asarray(starts, np.int64)[seg] + (np.arange(len(seg)) - first[seg])
    return seg, pos

"""4-wide BVH collapsed from the binned-SAH binary BVH (viewer.accel.bvh), for CPU-side SIMD.

Why: on a CPU OpenCL device (PoCL) traversal is not vectorised across work-items, so the SIMD
has to come from inside one work-item: one float4 slab test checks the four children of a node
at once (about 2x a binary BVH in a prototype on this machine).

Collapse
--------
Greedy, top down, one BVH4 level at a time with vectorised NumPy (no loop over nodes): a BVH4
node starts from the two children of a binary inner node and, twice, replaces the inner child
with the largest surface area by its two children, so it ends with 2-4 children. Binary leaves
stay leaves (same triangle ranges), so triangles keep the binary BVH's leaf order and a triangle
id is its leaf-order slot (`bvh.tri_order`), as for every other backend. A binary tree that is a
single leaf becomes one BVH4 node with that leaf in slot 0.

Layout (`NODE4_DTYPE`, 128 bytes, float4-aligned; kernels read it as 8 float4 per node)
------------------------------------------------------------------------------------------
    float4 minx, maxx, miny, maxy, minz, maxz;  // child boxes, structure of arrays over 4 slots
    int4   child;                               // >= 0: BVH4 node index; < 0: leaf ~first_slot
    int4   count;                               // leaf triangle count; 0 for inner / empty slots
An empty slot has the box min = +inf, max = -inf and child = ~0, count = 0: a slab test that
picks the near plane by the ray direction's sign gets entry = +inf > exit = -inf, so it never
hits. Nodes are in breadth-first order (children after parents, root = 0).

Stack bound: a traversal pushes at most 3 nodes per level, so `stack_size()` = 3 * depth + 1
entries always suffice (depth = BVH4 levels below the root).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from viewer.accel.bvh import BVH

NODE4_DTYPE = np.dtype(
    [
        ("minx", "<f4", 4),
        ("maxx", "<f4", 4),
        ("miny", "<f4", 4),
        ("maxy", "<f4", 4),
        ("minz", "<f4", 4),
        ("maxz", "<f4", 4),
        ("child", "<i4", 4),
        ("count", "<i4", 4),
    ]
)
assert NODE4_DTYPE.itemsize == 128

_BOX_FIELDS = (("minx", "maxx"), ("miny", "maxy"), ("minz", "maxz"))


@dataclass
class BVH4:
    """The collapsed tree. `source[i]` is the binary node each BVH4 node was made from."""

    nodes: np.ndarray  # NODE4_DTYPE (M4,)
    depth: int  # levels below the root (a one-node tree has depth 0)
    source: np.ndarray  # int32 (M4,) binary BVH node of each BVH4 node
    leaves: int  # number of leaf slots (binary leaves)

    def stack_size(self) -> int:
        """Traversal stack entries that always suffice (3 pushes per level at most)."""
        return 3 * self.depth + 1

    @property
    def memory_bytes(self) -> int:
        return self.nodes.nbytes


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    e = hi.astype(np.float64) - lo.astype(np.float64)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _open_children(bvh: BVH, frontier: np.ndarray, is_leaf: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(k, 4) binary child ids of the BVH4 nodes made from binary inner nodes `frontier` (-1: empty)."""
    k = len(frontier)
    rows = np.arange(k)
    ch = np.full((k, 4), -1, np.int64)
    ch[:, 0] = bvh.node_left[frontier]
    ch[:, 1] = bvh.node_right[frontier]
    filled = np.full(k, 2, np.int64)
    for _ in range(2):
        safe = np.maximum(ch, 0)
        openable = (ch >= 0) & ~is_leaf[safe]
        a = np.where(openable, area[safe], -np.inf)
        j = np.argmax(a, axis=1)
        ok = np.isfinite(a[rows, j])
        r, jj = rows[ok], j[ok]
        c = ch[r, jj]
        ch[r, jj] = bvh.node_left[c]
        ch[r, filled[ok]] = bvh.node_right[c]
        filled[ok] += 1
    return ch


def _child_table(bvh: BVH, is_leaf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per binary node (plus a last row for "no child", index -1): the six NODE4 box values
    (minx, maxx, miny, maxy, minz, maxz; the empty box in the last row) and (leaf ref ~first or 0,
    count) for a leaf (0, 0 for inner nodes). One gather per BVH4 level then fills a whole node
    (why: six gathers and selects per level took most of the collapse at 10 M triangles)."""
    m = len(is_leaf)
    box = np.empty((m + 1, 6), np.float32)
    box[:m, 0::2] = bvh.node_min
    box[:m, 1::2] = bvh.node_max
    box[m, 0::2] = np.inf
    box[m, 1::2] = -np.inf
    ref = np.zeros((m + 1, 2), np.int32)
    ref[:m, 0] = np.where(is_leaf, ~bvh.node_first, 0)
    ref[:m, 1] = np.where(is_leaf, bvh.node_count, 0)
    ref[m] = (~0, 0)
    return box, ref


def build_bvh4(bvh: BVH) -> BVH4:
    """Collapse `bvh` (see the module docstring); vectorised per BVH4 level."""
    is_leaf = bvh.is_leaf()
    area = _half_area(bvh.node_min, bvh.node_max)
    box, ref = _child_table(bvh, is_leaf)
    m = len(is_leaf)
    # every BVH4 node is made from a distinct binary inner node (or the single-leaf root): an upper
    # bound on the count, so the levels are written in place (no concatenation)
    cap = max(int((~is_leaf).sum()), 1)
    out = np.empty(cap, NODE4_DTYPE)
    out_words = out.view(np.float32).reshape(cap, 8, 4)
    out_src = np.empty(cap, np.int32)
    n_leaves = 0
    if is_leaf[0]:
        frontier = np.zeros(0, np.int64)
        ch = np.full((1, 4), -1, np.int64)
        ch[0, 0] = 0
        chunks = [(np.zeros(1, np.int64), ch)]
    else:
        frontier = np.zeros(1, np.int64)
        chunks = []
    base = 0
    levels = 0
    while True:
        if chunks:
            src, ch = chunks.pop()
        elif len(frontier):
            src, ch = frontier, _open_children(bvh, frontier, is_leaf, area)
        else:
            break
        k = len(src)
        row = np.where(ch >= 0, ch, m)  # the "no child" row for empty slots
        leaf = is_leaf[np.minimum(row, m - 1)] & (ch >= 0)
        inner = (ch >= 0) & ~leaf
        words = out_words[base:base + k]
        words[:, :6, :] = box[row].transpose(0, 2, 1)  # (k, 6 fields, 4 slots)
        refs = ref[row]  # (k, 4, 2): leaf ref / count; "no child" ~0, 0; inner 0, 0 (set below)
        child = refs[:, :, 0]
        # inner children become the next level's nodes, numbered in row-major order
        next_index = base + k + np.cumsum(inner.ravel()).reshape(k, 4) - 1
        child[inner] = next_index[inner]
        ints = words.view(np.int32)
        ints[:, 6, :] = child
        ints[:, 7, :] = refs[:, :, 1]
        out_src[base:base + k] = src
        n_leaves += int(leaf.sum())
        base += k
        levels += 1
        frontier = ch[inner]
    # views: the rows never written were never touched (no memory behind them in practice)
    return BVH4(out[:base], levels - 1, out_src[:base], n_leaves)

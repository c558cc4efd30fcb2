"""Binned SAH BVH over a triangle soup, built one tree level at a time with vectorised NumPy.

Build
-----
The builder works on triangle bounding boxes and box centres (float32).  All nodes of one
depth are processed together; there is no Python loop over nodes or triangles, only over
levels, a fixed number of size classes and the 3 axes.  Per level:

* node boxes (exact float32 min/max of the vertices, so they are conservative) and centroid
  bounds come from `np.minimum.reduceat` over the node's contiguous triangle range;
* nodes with more than `min(bins, 32)` triangles are split with a binned SAH: `bins` bins over the
  node's centroid bounds on each of the 3 axes, per-(node, axis, bin) boxes and counts via
  `np.minimum.at` / `np.bincount`, prefix/suffix sweeps over the bins;
* nodes with at most `min(bins, 32)` triangles (but more than `min_leaf`) use an exact full-sweep SAH
  (triangles sorted by centroid on each axis, every object split evaluated).  This is the
  limit of binning with infinitely many bins, so it is never worse than `bins` bins, and it
  avoids allocating `3 * bins` bins for nodes of 3 triangles;
* the SAH cost of a split is `traversal_cost + intersect_cost * (A_L*N_L + A_R*N_R) / A`, a
  leaf costs `intersect_cost * N`.  A node is a leaf if `N <= min_leaf`, or if `N <= max_leaf`
  and the leaf is not dearer than the best split.  Nodes with `N > max_leaf` always split;
  when no SAH split exists (all centroids coincide, or every bin split is one-sided) they are
  split at the median by index (first half / second half of the current order);
* a stable partition (counting: rank among the left or right triangles of the node via a
  cumulative sum) moves the triangles of split nodes into the children's contiguous ranges.
  Triangles of leaves drop out of the working set, so a level costs O(triangles still in
  inner nodes).  Every node (inner ones too) owns the contiguous slot range
  `[node_first, node_first + node_count)` of `tri_order`.
* beyond depth `DEPTH_LIMIT` (pathological inputs only) nodes are split at the median by
  index, so the depth is at most `DEPTH_LIMIT + ceil(log2(N))`.

Node order
----------
Canonical nodes are stored level by level (breadth first): all nodes of depth d come before
all nodes of depth d+1, so children are always stored after their parent and node 0 is the
root.  Within a level nodes are grouped by size class (large binned nodes first, small ones
later); the two children of a node are therefore not necessarily adjacent; use node_left and
node_right.  `gpu_nodes()` keeps the same relative order for the inner nodes.

GPU layout
----------
`gpu_nodes()` is an Aila-Laine style array of inner nodes only (64 bytes each, std430):
    struct Node { vec3 lmin; int left; vec3 lmax; int right; vec3 rmin; int lcount; vec3 rmax; int rcount; };
A child reference >= 0 indexes another inner node in this array; a leaf child is encoded as
`~first_triangle_slot` (negative) and its triangle count is in lcount/rcount (0 for inner
children).  Triangles are addressed by slot, i.e. in leaf order (`triangles[tri_order]`).
A tree that is a single leaf becomes one GPU node: left = that leaf, right = an empty leaf
(count 0, inverted box EMPTY_BOX_MIN / EMPTY_BOX_MAX).  Traversal starts at GPU node 0; a
subtree root is `inner_index_of_node()[node]`.  The traversal stack never needs more than
`stats.depth` entries.

Cost: about 320 bytes of scratch per triangle at peak; roughly 3-4 s for 1M triangles on 2
cores (NumPy, single-threaded).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import numpy as np

GPU_NODE_DTYPE = np.dtype(
    [
        ("lmin", "<f4", 3),
        ("left", "<i4"),
        ("lmax", "<f4", 3),
        ("right", "<i4"),
        ("rmin", "<f4", 3),
        ("lcount", "<i4"),
        ("rmax", "<f4", 3),
        ("rcount", "<i4"),
    ]
)
GPU_TRI_DTYPE = np.dtype(
    [("v0", "<f4", 3), ("id", "<i4"), ("v1", "<f4", 3), ("mat", "<i4"), ("v2", "<f4", 3), ("pad", "<i4")]
)
assert GPU_NODE_DTYPE.itemsize == 64 and GPU_TRI_DTYPE.itemsize == 48

#: Box of the empty right child of a single-leaf tree (min > max).  A slab test that orders the
#: two plane distances per axis (min/max swap) reports a *hit* on this inverted box; that is
#: harmless because the child is a leaf with 0 triangles.
EMPTY_BOX_MIN = np.float32(3.4e38)
EMPTY_BOX_MAX = np.float32(-3.4e38)

#: Below this depth nodes are split by SAH; deeper nodes (pathological inputs) by median.
DEPTH_LIMIT = 64

#: Nodes of at most min(bins, _SWEEP_MAX) triangles use the exact full-sweep SAH.
_SWEEP_MAX = 32
_LEAF_CLASS = 1 << 30  # size class of nodes with count <= min_leaf (sorted last in a level)


@dataclass
class BuildStats:
    build_time_s: float
    triangles: int
    nodes: int
    inner_nodes: int
    leaves: int
    depth: int  # max leaf depth, root = 0
    sah_cost: float  # SAH cost of the tree / root surface area (traversal 1, intersection 1 per tri)
    leaf_size_histogram: dict[int, int]  # leaf triangle count -> number of leaves
    memory_bytes: int  # bytes of gpu_nodes() + 48 bytes per GPU triangle

    def to_dict(self) -> dict:
        """JSON-able dict; histogram keys become strings (as JSON would make them)."""
        d = asdict(self)
        d["leaf_size_histogram"] = {str(k): int(v) for k, v in sorted(self.leaf_size_histogram.items())}
        return d


@dataclass
class BVH:
    """Canonical tree: all nodes, leaves included. Node 0 is the root.

    Nodes are in breadth-first level order (see the module docstring): children after parents.
    """

    node_min: np.ndarray  # float32 (M, 3) box min
    node_max: np.ndarray  # float32 (M, 3) box max
    node_left: np.ndarray  # int32 (M,) child index, -1 for leaves
    node_right: np.ndarray  # int32 (M,) child index, -1 for leaves
    node_first: np.ndarray  # int32 (M,) first triangle slot (in leaf order) of the subtree
    node_count: np.ndarray  # int32 (M,) number of triangles in the subtree
    node_parent: np.ndarray  # int32 (M,) -1 for the root
    node_height: np.ndarray  # int32 (M,) subtree height, leaves = 0
    node_depth: np.ndarray  # int32 (M,) root = 0
    tri_order: np.ndarray  # int32 (N,) slot i holds original triangle tri_order[i]
    stats: BuildStats

    def is_leaf(self) -> np.ndarray:
        return self.node_left < 0

    def inner_nodes(self) -> np.ndarray:
        """int32: canonical index of each gpu_nodes() entry (the root for a single-leaf tree)."""
        inner = np.flatnonzero(~self.is_leaf()).astype(np.int32)
        return inner if len(inner) else np.zeros(1, np.int32)

    def inner_index_of_node(self) -> np.ndarray:
        """int32 (M,): gpu_nodes() index of each canonical node, -1 for leaves.

        Exception: for a single-leaf tree the root (a leaf) maps to 0, the synthetic GPU node
        that wraps it, so traversal can always start at inner_index_of_node()[0] == 0.
        """
        leaf = self.is_leaf()
        idx = np.full(len(leaf), -1, np.int32)
        inner = ~leaf
        idx[inner] = np.arange(int(inner.sum()), dtype=np.int32)
        if not inner.any():
            idx[0] = 0
        return idx

    def gpu_nodes(self) -> np.ndarray:
        """Inner nodes with both child boxes (GPU_NODE_DTYPE, root at index 0)."""
        leaf = self.is_leaf()
        inner = np.flatnonzero(~leaf)
        if len(inner) == 0:  # single leaf: wrap it in one node whose right child is empty
            g = np.zeros(1, GPU_NODE_DTYPE)
            g["lmin"][0] = self.node_min[0]
            g["lmax"][0] = self.node_max[0]
            g["left"][0] = ~int(self.node_first[0])
            g["lcount"][0] = self.node_count[0]
            g["rmin"][0] = EMPTY_BOX_MIN
            g["rmax"][0] = EMPTY_BOX_MAX
            g["right"][0] = ~0
            g["rcount"][0] = 0
            return g
        idx = self.inner_index_of_node()
        g = np.zeros(len(inner), GPU_NODE_DTYPE)
        for side, child in (("l", self.node_left[inner]), ("r", self.node_right[inner])):
            cl = leaf[child]
            g[side + "min"] = self.node_min[child]
            g[side + "max"] = self.node_max[child]
            g["left" if side == "l" else "right"] = np.where(cl, ~self.node_first[child], idx[child])
            g[side + "count"] = np.where(cl, self.node_count[child], 0)
        return g

    def triangles_in_leaf_order(self, triangles: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(triangles, np.float32)[self.tri_order])


def gpu_triangles(triangles_in_leaf_order: np.ndarray, material_ids: np.ndarray) -> np.ndarray:
    """GPU_TRI_DTYPE array; material_ids must be in the same (leaf) order; id = slot index."""
    t = np.asarray(triangles_in_leaf_order, np.float32)
    n = len(t)
    out = np.zeros(n, GPU_TRI_DTYPE)
    out["v0"] = t[:, 0]
    out["v1"] = t[:, 1]
    out["v2"] = t[:, 2]
    out["id"] = np.arange(n, dtype=np.int32)
    out["mat"] = np.asarray(material_ids, np.int32)
    return out


# ----------------------------------------------------------------------------------------------
# Build helpers.  The working set is structure-of-arrays: rows 0-2 of `work` hold the box min,
# rows 3-5 the *negated* box max (so one np.minimum reduction yields a whole box; negation is
# exact), row 6 the triangle id (int32 bits).  Column n (one past the last triangle) is a
# sentinel with +inf boxes, used for padding.


def _half_area(b: np.ndarray) -> np.ndarray:
    """Half surface area of boxes given as rows [min x, min y, min z, -max x, -max y, -max z] (axis 0).

    float32; empty boxes (+inf rows) give +inf.  (min - max is the negated extent; the sign
    cancels in the products.)
    """
    with np.errstate(invalid="ignore", over="ignore"):
        ex = b[0] + b[3]
        ey = b[1] + b[4]
        ez = b[2] + b[5]
        r = ex * ey
        ey *= ez
        r += ey
        ez *= ex
        r += ez
        return r


def _prefix_min(x: np.ndarray, axis: int, reverse: bool = False, out: np.ndarray | None = None) -> np.ndarray:
    """Cumulative minimum along a short axis (one vectorised np.minimum per step)."""
    x = np.moveaxis(x, axis, 0)
    o = np.empty_like(x) if out is None else np.moveaxis(out, axis, 0)
    idx = range(len(x) - 1, -1, -1) if reverse else range(len(x))
    prev = None
    for i in idx:
        if prev is None:
            o[i] = x[i]
        else:
            np.minimum(o[prev], x[i], out=o[i])
        prev = i
    return np.moveaxis(o, 0, axis)


def _size_class(count: np.ndarray, bins: int, min_leaf: int) -> np.ndarray:
    """0 for binned nodes, ceil(log2(count)) for full-sweep nodes, _LEAF_CLASS for leaves."""
    exp = np.frexp((count - 1).astype(np.float64))[1].astype(np.int64)  # ceil(log2(count))
    return np.where(count <= min_leaf, _LEAF_CLASS, np.where(count > min(bins, _SWEEP_MAX), 0, exp))


class _Pool:
    """Reusable scratch buffers: fresh multi-megabyte arrays cost page faults on every level."""

    def __init__(self):
        self._bufs: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        size = int(np.prod(shape))
        buf = self._bufs.get(name)
        if buf is None or buf.size < size or buf.dtype != dtype:
            buf = np.empty(max(size, 1), dtype)
            self._bufs[name] = buf
        return buf[:size].reshape(shape)


def _binned_split(pool, cols, cent, cmin, cmax, kr, cnt, narea, bins, ct, ci):
    """Binned SAH for k nodes whose triangles are columns [0, n) of cols/cent, grouped by node.

    cols: float32 (6, n) box rows; cent: float32 (3, n) centroids; cmin/cmax: (3, k) centroid
    bounds; kr: node of each triangle.  Returns (best cost per node, go-left per triangle).
    """
    k = len(cnt)
    n = len(kr)
    ext = (cmax - cmin).astype(np.float64)
    with np.errstate(divide="ignore"):
        scale = bins / ext
    scale[~(scale < 1e30)] = 0.0  # zero extent -> everything in bin 0 (no valid split)
    scale = scale.astype(np.float32)
    # bin coordinate per triangle and axis: (cent - cmin) * scale, >= 0
    b = pool.get("bin_f", (3, n), np.float32)
    tmp = pool.get("bin_tmp", (3, n), np.float32)
    np.take(cmin, kr, axis=1, out=tmp, mode="clip")
    np.subtract(cent, tmp, out=b)
    np.take(scale, kr, axis=1, out=tmp, mode="clip")
    b *= tmp
    # key of (node, axis, bin) in a (k, 3, bins) array; per box component j the bounds live in
    # slab j of a (6, k, 3, bins) array
    keys = pool.get("bin_keys", (3, n), np.intp)
    np.copyto(keys, b, casting="unsafe")  # truncation = floor, b >= 0
    np.minimum(keys, bins - 1, out=keys)
    krb = pool.get("bin_kr", (n,), np.intp)
    np.multiply(kr, 3 * bins, out=krb)
    keys += krb
    keys[1] += bins
    keys[2] += 2 * bins
    slab = 3 * bins * k
    counts = np.bincount(keys.ravel(), minlength=slab).reshape(k, 3, bins)
    bnd = pool.get("bin_bnd", (6 * slab,), np.float32)
    bnd.fill(np.inf)
    for j in range(6):
        view = bnd[j * slab :]
        for a in range(3):
            np.minimum.at(view, keys[a], cols[j])
    # bins-major copy so the sweeps over bins run on contiguous slabs
    bt = pool.get("bin_bt", (bins, 6 * 3 * k), np.float32)
    np.copyto(bt, bnd.reshape(6 * 3 * k, bins).T)
    bt = bt.reshape(bins, 6, 3 * k)
    al = _half_area(_prefix_min(bt[:-1], 0).transpose(1, 0, 2))  # (bins-1, 3k)
    ar = _half_area(_prefix_min(bt[1:], 0, reverse=True).transpose(1, 0, 2))
    nl = np.cumsum(counts, axis=2)[:, :, :-1].reshape(k * 3, bins - 1).T  # (bins-1, 3k)
    nr = np.repeat(cnt, 3)[None, :] - nl
    with np.errstate(invalid="ignore", over="ignore"):
        cost = al * nl.astype(np.float32)
        cost += ar * nr.astype(np.float32)
        cost *= np.float32(ci) / np.repeat(narea, 3)
        cost += np.float32(ct)
    cost[(nl == 0) | (nr == 0)] = np.inf
    flat = cost.reshape(bins - 1, k, 3).transpose(1, 0, 2).reshape(k, -1)  # (k, (bins-1)*3)
    best = np.argmin(flat, axis=1)
    best_cost = flat[np.arange(k), best]
    axis = best % 3
    pos = best // 3
    # go left iff floor(b) <= pos  <=>  b < pos + 1  (also right for b clipped to the last bin)
    chosen = np.choose(axis[kr], b)
    go_left = chosen < (pos + 1).astype(np.float32)[kr]
    return best_cost, go_left


def _sweep_split(pool, cols, cent, sentinel, off, cnt, narea, size, ct, ci):
    """Exact full-sweep SAH for g nodes of at most `size` triangles each.

    Node i owns columns [off[i], off[i] + cnt[i]) of cols (6, *) / cent (3, *); column
    `sentinel` holds +inf and pads every node to `size`.  Returns like _binned_split, go-left
    for the nodes' triangles in column order.
    """
    g = len(off)
    j = np.arange(size)
    valid = j < cnt[:, None]
    rows = np.where(valid, off[:, None] + j, sentinel)  # (g, size)
    nl = (j[:-1] + 1)[:, None].astype(np.float32)
    nr = (cnt - nl).astype(np.float32)  # (size-1, g)
    invalid = nr <= 0
    ci_a = np.float32(ci) / narea
    best_cost = np.full(g, np.inf, np.float32)
    best_axis = np.zeros(g, np.intp)
    best_pos = np.zeros(g, np.intp)
    orders = []
    ar_g = np.arange(g)
    sb = pool.get("sw_sb", (6, size, g), np.float32)
    pre = pool.get("sw_pre", (6, size - 1, g), np.float32)
    for a in range(3):
        order = np.argsort(cent[a][rows], axis=1, kind="stable")
        np.take(cols, np.take_along_axis(rows, order, axis=1).T, axis=1, out=sb, mode="clip")  # (6, size, g)
        with np.errstate(invalid="ignore", over="ignore"):
            _prefix_min(sb[:, :-1], 1, out=pre)
            cost = _half_area(pre)  # (size-1, g)
            cost *= nl
            _prefix_min(sb[:, 1:], 1, reverse=True, out=pre)
            ar = _half_area(pre)
            ar *= nr
            cost += ar
            cost *= ci_a
            cost += np.float32(ct)
        cost[invalid] = np.inf
        pos = np.argmin(cost, axis=0)
        c = cost[pos, ar_g]
        better = c < best_cost
        best_cost[better] = c[better]
        best_axis[better] = a
        best_pos[better] = pos[better]
        orders.append(order)
    order = np.stack(orders)[best_axis, ar_g]  # (g, size)
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(j, order.shape), axis=1)
    go_left = (rank <= best_pos[:, None])[valid]
    return best_cost, go_left


NON_FINITE = "triangles contain non-finite coordinates"


def _validate(triangles: np.ndarray, check_finite: bool = True) -> np.ndarray:
    """The triangles as contiguous float32 (N, 3, 3), N > 0, finite (check_finite=False: the
    caller checks that itself, e.g. the device build while it reads them anyway)."""
    tri = np.ascontiguousarray(triangles, dtype=np.float32)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (N, 3, 3), got {tri.shape}")
    if len(tri) == 0:
        raise ValueError("cannot build a BVH over 0 triangles")
    if check_finite and not np.isfinite(tri).all():
        raise ValueError(NON_FINITE)
    return tri


def tree_stats(node_min: np.ndarray, node_max: np.ndarray, node_left: np.ndarray, node_count: np.ndarray,
               node_depth: np.ndarray, n_tri: int, build_time_s: float = 0.0) -> BuildStats:
    """BuildStats of a canonical tree (shared by every builder, so their SAH costs compare).

    The SAH cost is reported with traversal 1 and intersection 1 whatever the build costs."""
    is_leaf = node_left < 0
    ext = (node_max.astype(np.float64) - node_min).T
    area = ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0]
    root_area = area[0] if area[0] > 0 else 1.0
    sah = (area[~is_leaf].sum() + (area[is_leaf] * node_count[is_leaf]).sum()) / root_area
    freq = np.bincount(node_count[is_leaf])  # leaf sizes are small: no sort (np.unique) needed
    sizes = np.flatnonzero(freq)
    freq = freq[sizes]
    n_inner = int((~is_leaf).sum())
    m = len(node_left)
    return BuildStats(
        build_time_s=build_time_s,
        triangles=n_tri,
        nodes=m,
        inner_nodes=n_inner,
        leaves=m - n_inner,
        depth=int(node_depth[is_leaf].max()),
        sah_cost=float(sah),
        leaf_size_histogram={int(s): int(f) for s, f in zip(sizes, freq, strict=True)},
        memory_bytes=max(n_inner, 1) * GPU_NODE_DTYPE.itemsize + n_tri * GPU_TRI_DTYPE.itemsize,
    )


def build_bvh(
    triangles: np.ndarray,
    bins: int = 16,
    max_leaf: int = 4,
    min_leaf: int = 2,
    traversal_cost: float = 1.0,
    intersect_cost: float = 1.0,
    progress: Callable[[int, int], None] | None = None,
) -> BVH:
    """Build a SAH BVH over float32 triangles (N, 3, 3); see the module docstring.

    progress(triangles_placed_in_leaves, total) is called once per level.
    """
    t_start = time.perf_counter()
    if bins < 2:
        raise ValueError("bins must be >= 2")
    if max_leaf < 1 or min_leaf > max_leaf:
        raise ValueError("need 1 <= max_leaf and min_leaf <= max_leaf")
    bins = int(bins)
    min_leaf = max(int(min_leaf), 1)
    ct = float(traversal_cost)
    ci = float(intersect_cost)
    tri = _validate(triangles)
    n_tri = len(tri)

    # working set: triangles still in unfinished nodes, grouped by node (see helpers above)
    work_bufs = [np.empty((7, n_tri + 1), np.float32), None]  # ping-pong
    work = work_bufs[0]
    all_idx = np.arange(n_tri, dtype=np.intp)
    work[0:3, :n_tri] = tri.min(axis=1).T
    work[3:6, :n_tri] = tri.max(axis=1).T
    np.negative(work[3:6], out=work[3:6])
    work.view(np.int32)[6, :n_tri] = np.arange(n_tri, dtype=np.int32)
    work[:, n_tri] = np.inf
    tri_order = np.empty(n_tri, np.int32)

    # current level; its nodes are grouped by size class (binned, sweeps by size, leaves)
    start = np.zeros(1, np.int64)
    cnt = np.full(1, n_tri, np.int64)
    parent = np.full(1, -1, np.int64)
    cls = _size_class(cnt, bins, min_leaf)

    pool = _Pool()
    levels = []  # per level: dict of node arrays
    base = 0
    depth = 0
    placed = 0
    while len(cnt):
        k = len(cnt)
        n = work.shape[1] - 1
        off = np.zeros(k, np.int64)
        np.cumsum(cnt[:-1], out=off[1:])
        kr = np.repeat(np.arange(k), cnt)
        cols = work[:6]
        box = np.minimum.reduceat(cols[:, :n], off, axis=1)  # (6, k)
        narea = _half_area(box)
        narea = np.where(narea > 0, narea, np.float32(1))

        # --- choose splits ---------------------------------------------------------------------
        best_cost = np.full(k, np.inf, np.float32)
        go_left = pool.get("go_left", (n,), bool)
        go_left.fill(False)
        k_nl = int(np.searchsorted(cls, _LEAF_CLASS))  # nodes [0, k_nl) are not forced leaves
        n_nl = int(off[k_nl]) if k_nl < k else n
        if k_nl and depth < DEPTH_LIMIT:
            cent = pool.get("cent", (3, n + 1), np.float32)
            np.subtract(cols[0:3, :n_nl], cols[3:6, :n_nl], out=cent[:, :n_nl])
            cent[:, :n_nl] *= 0.5
            cent[:, n] = np.inf
            cmin = np.minimum.reduceat(cent[:, :n_nl], off[:k_nl], axis=1)
            cmax = np.maximum.reduceat(cent[:, :n_nl], off[:k_nl], axis=1)
            k_b = int(np.searchsorted(cls, 1))  # binned nodes [0, k_b)
            if k_b:
                n_b = int(off[k_b]) if k_b < k else n
                bc, gl = _binned_split(
                    pool, cols[:, :n_b], cent[:, :n_b], cmin[:, :k_b], cmax[:, :k_b], kr[:n_b], cnt[:k_b],
                    narea[:k_b], bins, ct, ci,
                )  # fmt: skip
                best_cost[:k_b] = bc
                go_left[:n_b] = gl
            k0 = k_b
            while k0 < k_nl:  # one full-sweep pass per size class
                c = int(cls[k0])
                k1 = int(np.searchsorted(cls, c, side="right"))
                p0 = int(off[k0])
                p1 = int(off[k1]) if k1 < k else n
                bc, gl = _sweep_split(
                    pool, cols, cent, n, off[k0:k1], cnt[k0:k1], narea[k0:k1], 1 << c, ct, ci
                )
                best_cost[k0:k1] = bc
                go_left[p0:p1] = gl
                k0 = k1
            # all centroids coincide: no meaningful SAH split; NaN: areas overflowed float32
            best_cost[:k_nl][(cmin == cmax).all(axis=0)] = np.inf
            best_cost[np.isnan(best_cost)] = np.inf
        leaf = (cnt <= min_leaf) | ((cnt <= max_leaf) & (ci * cnt <= best_cost))
        median = ~leaf & ~(best_cost < np.inf)
        split = ~leaf

        # --- stable partition -----------------------------------------------------------------------
        idx = all_idx[:n]
        if median.any():
            m = median[kr]
            go_left[m] = (idx - off[kr])[m] < (cnt // 2)[kr][m]
        cs = np.cumsum(go_left, out=pool.get("cs", (n,), np.intp))
        cs -= go_left  # lefts before each triangle (global, exclusive)
        at_off = cs[off]
        last = off + cnt - 1
        n_left = cs[last] + go_left[last] - at_off  # per node

        ks = np.flatnonzero(split)
        n_split = len(ks)
        ch_cnt = np.empty(2 * n_split, np.int64)
        ch_cnt[0::2] = n_left[ks]
        ch_cnt[1::2] = cnt[ks] - n_left[ks]
        ch_start = np.empty(2 * n_split, np.int64)
        ch_start[0::2] = start[ks]
        ch_start[1::2] = start[ks] + n_left[ks]
        ch_parent = np.repeat(base + ks, 2)
        ch_cls = _size_class(ch_cnt, bins, min_leaf)
        ch_order = np.argsort(ch_cls, kind="stable")
        ch_pos = np.empty_like(ch_order)
        ch_pos[ch_order] = np.arange(2 * n_split)
        new_cnt = ch_cnt[ch_order]
        n_next = int(new_cnt.sum())
        new_off = np.zeros(2 * n_split, np.int64)
        np.cumsum(new_cnt[:-1], out=new_off[1:])

        node_left = np.full(k, -1, np.int64)
        node_right = np.full(k, -1, np.int64)
        node_left[ks] = base + k + ch_pos[0::2]
        node_right[ks] = base + k + ch_pos[1::2]

        # leaves: their triangles are final
        drop = None
        if not split.all():
            drop = ~split[kr]
            slots = (start - off)[kr][drop] + idx[drop]
            tri_order[slots] = work.view(np.int32)[6, :n][drop]
            placed += len(slots)
        # split nodes: move triangles to the children's compact ranges (leaf triangles -> trash
        # column n_next, which is reset to the sentinel afterwards)
        if n_split:
            # new position = child offset + rank among the node's left (right) triangles
            dst_l = np.zeros(k, np.int64)
            dst_r = np.zeros(k, np.int64)
            dst_l[ks] = new_off[ch_pos[0::2]] - at_off[ks]
            dst_r[ks] = new_off[ch_pos[1::2]] - off[ks] + at_off[ks]
            new_pos = np.take(dst_r, kr, out=pool.get("pos_r", (n,), np.intp), mode="clip")
            new_pos += idx
            new_pos -= cs
            pos_l = np.take(dst_l, kr, out=pool.get("pos_l", (n,), np.intp), mode="clip")
            pos_l += cs
            np.copyto(new_pos, pos_l, where=go_left)
            if drop is not None:
                new_pos[drop] = n_next
            if work_bufs[1] is None:
                work_bufs[1] = np.empty_like(work_bufs[0])
            work_bufs.reverse()
            new_work = work_bufs[0][:, : n_next + 1]
            for r in range(7):
                new_work[r][new_pos] = work[r, :n]
            new_work[:, n_next] = np.inf
            work = new_work

        levels.append(
            dict(
                min=box[0:3].T.copy(),
                max=-box[3:6].T,
                left=node_left.astype(np.int32),
                right=node_right.astype(np.int32),
                first=start.astype(np.int32),
                count=cnt.astype(np.int32),
                parent=parent.astype(np.int32),
                depth=np.full(k, depth, np.int32),
            )
        )
        if progress is not None:
            progress(placed, n_tri)
        base += k
        depth += 1
        start = ch_start[ch_order]
        cnt = new_cnt
        parent = ch_parent[ch_order]
        cls = ch_cls[ch_order]

    def cat(key, dtype):
        return np.concatenate([lv[key] for lv in levels]).astype(dtype, copy=False)

    bvh_left = cat("left", np.int32)
    bvh_right = cat("right", np.int32)
    count = cat("count", np.int32)
    node_min = cat("min", np.float32)
    node_max = cat("max", np.float32)
    node_depth = cat("depth", np.int32)
    m = len(bvh_left)
    height = np.zeros(m, np.int32)
    lv_end = m
    for lv in reversed(levels):
        lv_begin = lv_end - len(lv["count"])
        ids = np.arange(lv_begin, lv_end)
        inner = ids[bvh_left[ids] >= 0]
        height[inner] = 1 + np.maximum(height[bvh_left[inner]], height[bvh_right[inner]])
        lv_end = lv_begin

    stats = tree_stats(node_min, node_max, bvh_left, count, node_depth, n_tri)
    bvh = BVH(
        node_min=node_min,
        node_max=node_max,
        node_left=bvh_left,
        node_right=bvh_right,
        node_first=cat("first", np.int32),
        node_count=count,
        node_parent=cat("parent", np.int32),
        node_height=height,
        node_depth=node_depth,
        tri_order=tri_order,
        stats=stats,
    )
    stats.build_time_s = time.perf_counter() - t_start
    return bvh


def bench_build(triangles: np.ndarray, **kwargs) -> dict:
    """Build once; stats.to_dict() plus throughput in million triangles per second.

    The throughput is under both "throughput_mtris_per_s" (used by `rtwalk bench-bvh`) and
    "mtris_per_s"; "gpu_pack_time_s" times gpu_nodes().
    """
    bvh = build_bvh(triangles, **kwargs)
    t0 = time.perf_counter()
    bvh.gpu_nodes()
    d = bvh.stats.to_dict()
    d["gpu_pack_time_s"] = time.perf_counter() - t0
    d["throughput_mtris_per_s"] = d["mtris_per_s"] = (
        bvh.stats.triangles / max(bvh.stats.build_time_s, 1e-9) / 1e6
    )
    return d


def refit_bvh(bvh: BVH, triangles_in_leaf_order: np.ndarray) -> BVH:
    """The same tree (topology, tri_order, node ranges) with boxes recomputed for moved triangles.

    Used for animated scenes whose triangle count and order stay fixed: keeping the topology keeps
    every triangle id (leaf-order slot) and every node id valid, so per-node temporal state (the
    chcrt fronts) still maps onto the tree. Leaf boxes come from one `np.minimum.reduceat` over the
    leaves' slot ranges (the leaves partition the slots); inner boxes are merged level by level,
    deepest first (children are always deeper than their parent). Boxes are exact float32 min/max
    of the vertices, as in the build, so they stay conservative. Quality (SAH cost) degrades as
    objects move far from where the tree was built; the renderer rebuilds instead when that
    matters (see Renderer.set_scene_time)."""
    t = np.asarray(triangles_in_leaf_order, np.float32)
    n = len(t)
    if n != len(bvh.tri_order):
        raise ValueError(f"refit: {n} triangles for a tree over {len(bvh.tri_order)}")
    tmin = t.min(axis=1)
    tmax = t.max(axis=1)
    node_min = np.empty_like(bvh.node_min)
    node_max = np.empty_like(bvh.node_max)
    leaves = np.flatnonzero(bvh.node_left < 0)
    nonempty = leaves[bvh.node_count[leaves] > 0]
    order = nonempty[np.argsort(bvh.node_first[nonempty], kind="stable")]
    starts = bvh.node_first[order].astype(np.int64)
    node_min[order] = np.minimum.reduceat(tmin, starts, axis=0)
    node_max[order] = np.maximum.reduceat(tmax, starts, axis=0)
    empty = leaves[bvh.node_count[leaves] <= 0]
    node_min[empty], node_max[empty] = EMPTY_BOX_MIN, EMPTY_BOX_MAX
    inner = np.flatnonzero(bvh.node_left >= 0)
    depth = bvh.node_depth[inner]
    for d in np.unique(depth)[::-1]:
        nodes = inner[depth == d]
        left, right = bvh.node_left[nodes], bvh.node_right[nodes]
        node_min[nodes] = np.minimum(node_min[left], node_min[right])
        node_max[nodes] = np.maximum(node_max[left], node_max[right])
    return replace(bvh, node_min=node_min, node_max=node_max)

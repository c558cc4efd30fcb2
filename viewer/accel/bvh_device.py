"""BVH built on the OpenCL device: Morton order, PLOC clustering, SAH leaf collapse.

Why: the binned SAH build (viewer.accel.bvh) is NumPy on one core: a 10 M-triangle city took
80 s on a 16-core host and 260-340 s on the loaded 2-core machine, and its first frame waited for
it. This builder produces the same `BVH` (canonical nodes in breadth-first order, node ranges,
`tri_order`, `BuildStats`), so every backend, `gpu_nodes()` and `build_bvh4()` use it unchanged;
the SAH build stays the quality reference. Measured figures: docs/bvh-device.md.

Algorithm (kernels in bvh_device.cl)
------------------------------------
1. The triangles are read in place (USE_HOST_PTR). The bounds of the box centres (per block on
   the device, one read; no centre arrays: 120 MB of fresh pages at 10 M) span a cubic 1024^3
   grid; 30-bit Morton codes of the centres are sorted with the project's radix sort
   (viewer.cl.primitives, 4 digit passes, its other halves in cluster-box pages the first PLOC
   iteration writes anyway); the dead keys then hold the nearest neighbours.
2. PLOC (Meister & Bittner 2018): the clusters (one per triangle at first, boxes recomputed from
   the triangles) stay in Morton order; each finds the cluster within `radius` positions whose
   merged box has the least surface area (ties to the lower index: the closest pair overall is
   always mutual, so every iteration merges). For radius <= 8 `nearest_vec` does it eight pairs
   at a time (a float8 window of the next clusters' boxes, the same float operations, so the same
   neighbours). In builds of 2 M triangles or more (`radius1_floors`) the first iteration, from
   8 M the first two (`radius1_iterations`), search radius 1 (`nearest_r1`: one area a cluster
   instead of eight; on the Morton-ordered triangles nearly every radius-8 choice of the first
   iteration is an adjacent triangle: 99.996% on the city, whose SAH cost moves by 0.01% for the
   first, 0.1% at 10 M for both; scanned meshes lose up to 1.7%, docs/bvh-device.md, hence the size
   floors); the first of them runs straight from the triangles (`nearest_r1_leaves`,
   `merge_leaves`: no array of all n leaf clusters is written and read twice, only the merged
   clusters are written). Mutual pairs merge into a new inner node
   in the lower slot. An iteration is 3
   launches: nearest with per-block counts of kept clusters and merges (`nearest_vec` runs from
   2 RADIUS clusters before its block to RADIUS after it, so it knows every neighbour its
   clusters' mutual checks read; the other searches have a `count_blocks` launch of their own);
   one scan of both (node ids are numbered in cluster order from the node counter: no atomics);
   merge + compaction (a cluster is its box, the node id in the min's spare lane). The cluster
   count lives on the device, every kernel reads it there, and the host reads it back
   only every `check_every` iterations (to shrink the launch sizes and to stop).
3. While merging, each node gets the SAH cost of its best subtree (dynamic programme: the cheaper
   of a leaf and the split, traversal 1, intersection 1 per triangle, as BuildStats reports):
   a node of at most `max_leaf` triangles becomes a leaf when that is not dearer (always when
   it holds at most `min_leaf`). Leaves are the topmost such nodes; nodes below them are dropped.
   Inner node records are 48 bytes (counts, height and leaf flag, cost in one 16-byte piece: what a
   merge reads of a child; box min + left; box max + right).
4. Layout, breadth first, one level at a time (3 launches a level, the levels being the root's
   height + 1), straight into the finished tree's buffer: a node's parent writes it from its record
   (one random record read a node; its own links kept in its right/depth fields until its level
   is placed); per level the inner nodes are counted per block, one scan places their children at
   the next level in order (the order of a stable sort of the preorder by depth, so the same trees
   as the earlier place + depth sort + emit layout, which made about 4 random reads a node), and
   leaves write their triangles' Morton indices to `tri_order`; one `tri_ids` pass then maps them
   through the sort's permutation in slot order (nearly Morton order: perm read almost in order,
   where reading it leaf by leaf in level order missed the cache). That buffer is the cluster-box
   buffer when the tree fits, which the BVH keeps and maps (zero-copy on a CPU device); its ten
   arrays are placed (`_out_offsets`) over the pages PLOC's clusters already touched (the first two
   iterations' cluster counts come back with the root's read), fewer fresh pages than one after
   the other. BuildStats are summed on the device (float64 per block of nodes; tree_stats on a
   device without float64).
On a CPU device `merge_scatter` and `level_place` prefetch the random node records they will read
PREFETCH clusters / nodes ahead (the out-of-order core then overlaps those misses; level_place asks
for both cache lines a 48-byte record can span).
Host round trips: the centre bounds, one count read every `check_every` PLOC iterations, one read
of the root, kept-node count, height and the first two cluster counts, one finish per timed phase
(5), the stats' block sums, and the map of the finished tree. Page faults dominate a cold build on
a CPU device (about 1 s per fresh GiB on the 2-core machine), hence the buffer reuse above.

Numerics: every box is an exact float32 min/max of the triangles' float32 vertices or of child
boxes (never rounded, so never shrunk); the Morton grid only orders the triangles.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.bvh import BVH, GPU_NODE_DTYPE, GPU_TRI_DTYPE, NON_FINITE, BuildStats, _validate, tree_stats
from viewer.cl import io as clio
from viewer.cl.limits import new_buffer
from viewer.cl.pool import BufferPool
from viewer.cl.primitives import WG as PWG

KERNEL = Path(__file__).resolve().parent / "bvh_device.cl"
WG = 64
RADIUS = 8
CHECK_EVERY = 4
#: PLOC iterations at the start that search radius 1 (nearest_r1; with nearest_vec only): one area a
#: cluster instead of eight, where the Morton-ordered triangles nearly all pair with an adjacent one.
#: Two (bvhfast4): city 10 M SAH 104.121 -> 104.240 (+0.11%), 72 -> 68 iterations, the build about
#: 0.8-0.85x its CPU time, clbvh trace time 0.90x / 1.005x of the old tree's (traced second / first: the
#: same within the noise); three cost +0.9% SAH for no further gain
RADIUS1_ITERATIONS = 2
#: ... iteration k of them only in builds of at least RADIUS1_FLOORS[k] triangles (the last floor for
#: the later ones), where the build's time is what counts: scanned meshes pay up to 1.7% SAH cost for
#: the first (bunny 1.087 -> 1.104 of the binned SAH build, beyond the 10% bound), so every shared
#: study scene (up to 1.1 M triangles) keeps radius 8; the second costs the city +1.33% SAH at 2.5 M
#: (clbvh trace 1.02-1.08x), +0.93% at 4 M, +0.43% at 6 M, +0.11% at 10 M (trace the same)
RADIUS1_FLOORS = (2_000_000, 8_000_000)
#: on a CPU device, merge_scatter and level_place prefetch the random records they will read this
#: many clusters / nodes ahead (level_place 0.80-0.83x, merge_scatter about 0.9x its time at 10 M)
PREFETCH = 8
#: device bytes per triangle of the buffers build() allocates (bounds: only the pages a build writes
#: are ever touched): input (the host array itself on a CPU device), keys (later the nearest
#: neighbours) + perm (the sort's other halves are in the cluster boxes), inner node records (48
#: bytes), cluster boxes x 2 (with the node ids), and the finished tree (13 words a kept node,
#: m <= 2n - 1 (about 0.9 n in practice), and tri_order: in the cluster-box buffer when it fits,
#: which the BVH then keeps; else a buffer of its own)
OUT_BYTES_PER_TRIANGLE = 2 * 13 * 4 + 4
BYTES_PER_TRIANGLE = 36 + 8 + 48 + 2 * 32 + OUT_BYTES_PER_TRIANGLE
_KERNELS = ("centre_bounds", "morton", "init_leaves", "nearest", "nearest_block", "nearest_vec", "nearest_r1",
            "nearest_r1_leaves", "merge_leaves", "count_blocks",
            "scan_blocks", "merge_scatter", "root_count", "layout_root", "level_count", "level_scan", "level_place",
            "tri_ids", "stats_blocks")


class DeviceBvhBuilder:
    """Kernels and reusable buffers for one context (see the module docstring)."""

    def __init__(self, ctx: Any = None, radius: int = RADIUS, max_leaf: int = 4, min_leaf: int = 2,
                 check_every: int = CHECK_EVERY):
        from viewer.cl import build, cl_context
        from viewer.cl.primitives import primitives

        if not 1 <= radius <= 63:
            raise ValueError("radius must be in 1..63")
        if max_leaf < 1 or min_leaf > max_leaf:
            raise ValueError("need 1 <= max_leaf and min_leaf <= max_leaf")
        self.ctx = ctx or cl_context()
        self.prims = primitives(self.ctx)
        self.max_leaf, self.min_leaf = int(max_leaf), max(int(min_leaf), 1)
        self.check_every = max(int(check_every), 1)
        self.block_nearest = True  # per block of clusters (each pair once) rather than nearest (per cluster)
        self.vector_nearest = radius <= 8  # the block search eight pairs at a time (nearest_vec)
        self.radius1_iterations = RADIUS1_ITERATIONS  # the first iterations search radius 1 (nearest_r1)
        self.radius1_floors = RADIUS1_FLOORS  # ... each in builds of at least this many triangles
        defs = {"WG": WG, "RADIUS": int(radius), "MAX_LEAF": self.max_leaf, "MIN_LEAF": self.min_leaf}
        if self.ctx.is_cpu:  # clang's __builtin_prefetch (PoCL); a GPU has no cache lines to ask for
            defs["PREFETCH"] = PREFETCH
        prog = build(KERNEL, defs, self.ctx)
        fp64 = "cl_khr_fp64" in self.ctx.device.extensions
        self._k = clio.kernels(prog, [k for k in _KERNELS if (k != "nearest_vec" or radius <= 8)
                                      and (k != "stats_blocks" or fp64)])
        self._bufs = BufferPool(self.ctx)
        self.phases: dict[str, float] = {}
        self.iterations = 0

    # -- helpers ----------------------------------------------------------------------------
    def _run(self, name: str, n: int, *args: Any) -> None:
        if n:
            self._k[name](self.ctx.queue, (-(-n // WG) * WG,), (WG,), *args)

    def _task(self, name: str, n: int, *args: Any) -> None:
        """Block kernels: one work-item per block, n a multiple of the primitives' WG or 1 (a fixed
        local size: PoCL compiles a work-group function per local size)."""
        local = min(n, PWG)
        self._k[name](self.ctx.queue, (-(-n // local) * local,), (local,), *args)

    def _buf(self, name: str, nbytes: int) -> Any:
        return self._bufs.get(name, nbytes)

    def _read(self, buf: Any, count: int, dtype: Any, offset: int = 0) -> np.ndarray:
        out = np.empty(count, dtype)
        if count:
            clio.copy(self.ctx.queue, out, buf, src_offset=offset)
        return out

    def _stats(self, out: Any, offs: Any, m: int, n: int, *tree: np.ndarray) -> BuildStats:
        """BuildStats of the finished tree: tree_stats' sums made on the device in float64 per block
        of nodes (one read of the block sums; the host pass over every node took 0.5 s at 10 M
        triangles), or tree_stats itself on a device without float64."""
        if "stats_blocks" not in self._k:
            return tree_stats(*tree, n)
        nb = min(PWG * 8, -(-m // 4096) * PWG) if m > 4096 else PWG
        w = self.max_leaf + 5
        part = self._buf("stats", 8 * w * nb)
        self._task("stats_blocks", nb, np.uint32(m), np.uint32(nb), out, offs, part)
        sums = self._read(part, w * nb, np.float64).reshape(nb, w)
        inner, leaf, n_inner = sums[:, 0].sum(), sums[:, 1].sum(), int(sums[:, 2].sum())
        hist = sums[:, 4:].sum(axis=0).astype(np.int64)
        node_min, node_max = tree[0], tree[1]
        e = node_max[0].astype(np.float64) - node_min[0]
        root_area = e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
        sah = (inner + leaf) / (root_area if root_area > 0 else 1.0)
        return BuildStats(build_time_s=0.0, triangles=n, nodes=m, inner_nodes=n_inner, leaves=m - n_inner,
                          depth=int(sums[:, 3].max()), sah_cost=float(sah),
                          leaf_size_histogram={int(c): int(f) for c, f in enumerate(hist) if f},
                          memory_bytes=max(n_inner, 1) * GPU_NODE_DTYPE.itemsize + n * GPU_TRI_DTYPE.itemsize)

    def _radius1_iterations(self, n: int) -> int:
        """PLOC iterations at the start of a build of n triangles that search radius 1 (RADIUS1_FLOORS)."""
        floors = self.radius1_floors
        if n >= floors[-1]:
            return self.radius1_iterations
        return min(self.radius1_iterations, sum(1 for f in floors if n >= f))

    def _phase(self, name: str, t0: float) -> float:
        """Wall time of a phase (`phases`, seconds): one finish per phase, 5 per build."""
        clio.finish(self.ctx.queue)
        t = time.perf_counter()
        self.phases[name] = self.phases.get(name, 0.0) + (t - t0)
        return t

    def release(self) -> None:
        """Free the device buffers (BYTES_PER_TRIANGLE per triangle of the largest build)."""
        self._bufs.release()

    def check_memory(self, n: int) -> None:
        """RtwalkError before allocating when the device cannot hold the build's buffers."""
        from viewer.errors import RtwalkError

        dev = self.ctx.device
        largest = OUT_BYTES_PER_TRIANGLE * n  # the finished tree
        total = BYTES_PER_TRIANGLE * n
        if largest > dev.max_mem_alloc_size or total > dev.global_mem_size:
            raise RtwalkError(f"device BVH build of {n:,} triangles needs {total / 2**30:.1f} GiB of device memory "
                              f"(buffers up to {largest / 2**20:.0f} MiB); {dev.name.strip()} has "
                              f"{dev.global_mem_size / 2**30:.1f} GiB (buffers up to "
                              f"{dev.max_mem_alloc_size / 2**20:.0f} MiB): use --bvh-builder sah")

    # -- build ------------------------------------------------------------------------------
    def build(self, triangles: np.ndarray) -> BVH:
        """The BVH of float32 triangles (N, 3, 3); same contract as viewer.accel.bvh.build_bvh."""
        t_start = time.perf_counter()
        self.phases = {}
        tri = _validate(triangles, check_finite=False)  # centre_bounds checks on the device
        n = len(tri)
        if n >= 2**30:
            raise ValueError("at most 2**30 triangles")
        q = self.ctx.queue
        u = np.uint32
        self.check_memory(n)
        b = self._buf
        # the triangles in place (USE_HOST_PTR: no copy and no fresh pages on a CPU device)
        tri_buf = clio.upload(self.ctx, tri, what="device BVH triangles", use_host=True)
        nbc = self.prims.nblocks(n)
        part = b("bounds", 32 * nbc)
        self._task("centre_bounds", nbc, tri_buf, u(n), u(nbc), part)
        part = self._read(part, 8 * nbc, np.float32).reshape(nbc, 2, 4)
        if part[:, 0, 3].any():
            tri_buf.release()
            raise ValueError(NON_FINITE)
        t = self._phase("upload+boxes", t_start)

        # -- Morton codes, sorted ---------------------------------------------------------------
        lo, hi = part[:, 0, :3].min(axis=0), part[:, 1, :3].max(axis=0)
        # one scale for all axes (a cube around the centres): per-axis scales would stretch a flat
        # scene's thin axis over the whole code and order it worse
        ext = float((hi.astype(np.float64) - lo).max())
        scale = np.full(3, 1024.0 / ext if ext > 0 else 0.0)
        keys, perm = b("keys", 4 * n), b("perm", 4 * n)
        # the cluster boxes (min, max) x 2 in one buffer: the finished tree is written there later
        region = self.ctx.align_up(16 * n)  # sub-buffer origins aligned for this device
        cbox = b("cbox", 4 * region)
        cmin = [cbox.get_sub_region(0, region), cbox.get_sub_region(2 * region, region)]
        cmax = [cbox.get_sub_region(region, region), cbox.get_sub_region(3 * region, region)]
        self._run("morton", n, tri_buf, u(n), np.append(lo, 0).astype(np.float32),
                  np.append(scale, 0).astype(np.float32), keys, perm)
        # the sort's other halves in the first 4n bytes of cmin[1] / cmax[1]: pages the first PLOC
        # iteration writes anyway (about n / 2 clusters there), so no fresh 8n bytes for the sort
        self.prims.sort_pairs(keys, perm, n, key_bits=30, temp=(cmin[1], cmax[1]))
        t = self._phase("morton+sort", t)

        # -- PLOC ---------------------------------------------------------------------------------
        ni = max(n - 1, 1)  # inner nodes (ids n .. 2n - 2, stored at id - n)
        node = b("node", 48 * ni)  # inner node records (NODE_F4 float4 each, bvh_device.cl)
        nn = keys  # the sort keys are dead: their pages serve the nearest neighbours
        cnt = b("cnt", 8)
        next_node = b("next_node", 4)
        marks = b("marks", 20)  # root id, kept nodes, root height (root_count); clusters after iterations 0, 1
        clio.copy(q, cnt, np.array([n, n], np.uint32), is_blocking=False)
        clio.copy(q, marks, np.zeros(5, np.uint32), is_blocking=False)
        clio.copy(q, next_node, np.array([n], np.uint32), is_blocking=False)
        # the first iteration at radius 1 straight from the triangles (nearest_r1_leaves, merge_leaves):
        # no cluster array of all n triangles is written and read twice, only the merged clusters
        r1_iters = self._radius1_iterations(n)
        fused = self.block_nearest and self.vector_nearest and r1_iters > 0 and n > 1
        if not fused:
            self._run("init_leaves", n, tri_buf, perm, u(n), cmin[0], cmax[0])  # node ids in cmin's w
        node_args = (u(n), node)
        p = 0  # cnt[p] is the current cluster count; cluster arrays [p] are current
        n_host = n
        iters = 0
        while n_host > 1:
            nb = self.prims.nblocks(n_host)
            nbn = max(PWG, min(-(-n_host // 256), 8 * self.prims.max_blocks) // PWG * PWG)
            vec = self.block_nearest and self.vector_nearest  # nearest_vec counts the blocks too
            nbm = nbn if vec else nb  # blocks of the count, scan and merge
            bsum = b("bsum", 8 * nbm)
            for _ in range(self.check_every):
                s = p
                if fused and iters == 0:
                    self._task("nearest_r1_leaves", nbn, tri_buf, perm, u(n), u(nbn), nn, bsum)
                    self._task("scan_blocks", 1, bsum, u(nbm), cnt, u(p), next_node, u(iters), marks)
                    self._task("merge_leaves", nbm, tri_buf, perm, u(n), nn, u(nbm), bsum, cmin[1 - s], cmax[1 - s],
                               node)
                    p = 1 - p
                    iters += 1
                    continue
                if vec:
                    near = "nearest_r1" if iters < r1_iters else "nearest_vec"
                    self._task(near, nbn, cnt, u(p), cmin[s], cmax[s], u(nbn), nn, bsum)
                else:
                    if self.block_nearest:
                        self._task("nearest_block", nbn, cnt, u(p), cmin[s], cmax[s], u(nbn), nn)
                    else:
                        self._run("nearest", n_host, cnt, u(p), cmin[s], cmax[s], nn)
                    self._task("count_blocks", nb, cnt, u(p), nn, u(nb), bsum)
                self._task("scan_blocks", 1, bsum, u(nbm), cnt, u(p), next_node, u(iters), marks)
                self._task("merge_scatter", nbm, cnt, u(p), nn, u(nbm), bsum, cmin[s], cmax[s],
                           cmin[1 - s], cmax[1 - s], *node_args)
                p = 1 - p
                iters += 1
            n_host = int(self._read(cnt, 2, np.uint32)[p])
        self.iterations = iters
        t = self._phase("ploc", t)

        # -- layout: breadth first, one level at a time, straight into the finished tree -------
        self._task("root_count", 1, cmin[p], u(n), node, marks)
        _, m, height, c1, c2 = (int(x) for x in self._read(marks, 5, np.uint32))
        # the finished tree goes to a buffer the BVH keeps, mapped (not copied) for the host: its
        # arrays are views of it (zero-copy on a CPU device). That is the cluster-box buffer when
        # the tree fits, its arrays where the clusters already touched the pages (the pool makes a
        # new one for the next build).
        del cmin, cmax
        # bytes of each cluster region written: the first iteration's (or init_leaves') clusters
        # and the sort's other halves (4n bytes at the start of cmin[1] / cmax[1])
        e0 = 16 * (c2 if fused else n)
        e1 = max(16 * c1, 4 * n)
        offs = _out_offsets(m, n, region // 4, [e0 // 4, e0 // 4, e1 // 4, e1 // 4])
        if offs is not None:
            out = self._bufs.take("cbox")
        else:
            offs = _contiguous_offsets(m, n)
            out = new_buffer(self.ctx, self.ctx.cl.mem_flags.READ_WRITE, 4 * (13 * m + n), "device BVH tree")
        offs_buf = b("offs", 8 * len(offs))  # 64-bit: 13m + n words pass 2^32 from ~330 M triangles
        clio.copy(q, offs_buf, np.array(offs, np.uint64), is_blocking=False)
        lev = b("lev", 4 * (height + 3))
        self._task("layout_root", 1, marks, u(m), u(n), node, tri_buf, perm, lev, out, offs_buf)
        for d in range(height + 1):  # level d has at most min(2^d, m) nodes
            nbl = self.prims.nblocks(min(1 << min(d, 31), m))
            bsum = b("bsum", 8 * nbl)
            self._task("level_count", nbl, u(d), lev, u(nbl), out, offs_buf, bsum)
            self._task("level_scan", 1, u(d), u(nbl), bsum, lev)
            self._task("level_place", nbl, u(d), lev, u(nbl), u(n), node, tri_buf, perm, bsum, out, offs_buf)
        nbt = self.prims.nblocks(n)
        self._task("tri_ids", nbt, u(n), u(nbt), perm, out, offs_buf)  # the leaves' Morton indices -> triangle ids
        t = self._phase("layout", t)

        cl = self.ctx.cl
        sizes = _out_sizes(m, n)
        words = max(o + z for o, z in zip(offs, sizes, strict=True))
        flat, _ = clio.map_buffer(q, out, cl.map_flags.READ | cl.map_flags.WRITE, 0, (words,), np.int32)
        fl = flat.view(np.float32)
        ints = [flat[offs[i]:offs[i] + m] for i in range(2, 9)]
        node_left, node_right, node_first, node_count, node_parent, node_depth, node_height = ints
        node_min = fl[offs[0]:offs[0] + 3 * m].reshape(m, 3)
        node_max = fl[offs[1]:offs[1] + 3 * m].reshape(m, 3)
        stats = self._stats(out, offs_buf, m, n, node_min, node_max, node_left, node_count, node_depth)
        bvh = BVH(node_min=node_min, node_max=node_max, node_left=node_left, node_right=node_right,
                  node_first=node_first, node_count=node_count, node_parent=node_parent,
                  node_height=node_height, node_depth=node_depth, tri_order=flat[offs[9]:offs[9] + n], stats=stats)
        self._phase("read-back", t)
        tri_buf.release()
        stats.build_time_s = time.perf_counter() - t_start
        return bvh


def _out_sizes(m: int, n: int) -> list[int]:
    """Words of the finished tree's arrays: min, max, left, right, first, count, parent, depth,
    height (m nodes), tri_order (n triangles)."""
    return [3 * m, 3 * m] + [m] * 7 + [n]


def _contiguous_offsets(m: int, n: int) -> list[int]:
    """The arrays one after the other (a buffer of their own)."""
    return [int(x) for x in np.concatenate([[0], np.cumsum(_out_sizes(m, n))[:-1]])]


def _out_offsets(m: int, n: int, region: int, touched: list[int]) -> list[int] | None:
    """Word offsets of the finished tree's arrays in the cluster-box buffer (4 regions of `region`
    words, the first `touched[r]` words of region r already written by PLOC), or None when they do
    not fit. Why: a fresh page costs about 1 us on the 2-core VM and the tree is 52 bytes a node;
    one after the other the arrays cover the written prefixes of only some regions. Largest first,
    each array goes (from the region's fill point) where it covers the most written words not yet
    covered, ties to the lower region: at 10 M 283 -> 241 MB of fresh pages in the layout."""
    sizes = _out_sizes(m, n)
    fill = [0, 0, 0, 0]
    offs = [0] * len(sizes)
    for i in sorted(range(len(sizes)), key=lambda i: -sizes[i]):
        z = sizes[i]
        best = None
        for r in range(4):
            if fill[r] + z > region:
                continue
            gain = min(fill[r] + z, touched[r]) - min(fill[r], touched[r])
            if best is None or gain > best[0]:
                best = (gain, r)
        if best is None:
            return None
        r = best[1]
        offs[i] = r * region + fill[r]
        fill[r] += z
    return offs


_builders: dict[tuple, DeviceBvhBuilder] = {}


def device_builder(ctx: Any = None, radius: int = RADIUS, max_leaf: int = 4, min_leaf: int = 2) -> DeviceBvhBuilder:
    """The cached builder for a context and parameters (kernels compiled once, buffers reused)."""
    from viewer.cl import cl_context

    ctx = ctx or cl_context()
    key = (id(ctx), radius, max_leaf, min_leaf)
    if key not in _builders:
        _builders[key] = DeviceBvhBuilder(ctx, radius, max_leaf, min_leaf)
    return _builders[key]


def build_bvh_device(triangles: np.ndarray, radius: int = RADIUS, max_leaf: int = 4, min_leaf: int = 2,
                     ctx: Any = None) -> BVH:
    """Build on the default OpenCL device with the cached builder (see device_builder)."""
    return device_builder(ctx, radius, max_leaf, min_leaf).build(triangles)

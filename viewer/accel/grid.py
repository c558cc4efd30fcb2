"""Uniform grid built on the OpenCL device by sorting triangle-cell pairs (Kalojanov & Slusallek 2009).

Shared by the grid backends (ugrid, pgrid's rays without a preferred direction, voxel walks).
Per build: one work-item per triangle counts the cells it meets, an exclusive scan gives
each triangle its place, the (cell, triangle) pairs are written, radix-sorted by cell
(viewer.cl.primitives), and each cell's range is read off the segment boundaries of the sorted
keys. Kernels: grid_build.cl beside this file; the layout and the 3D-DDA walk:
viewer/cl/kernels/grid.cl (include it from a trace kernel).

Binning is triangle/cell and conservative: a triangle is listed in every cell whose box, grown by
`eps` cells per axis, the triangle meets (grid_build.cl clips it row by row), not in every cell
of its bounding box: a long diagonal triangle costs its cells, not its box's. Build and walk work
in coordinates local to the grid (vertex or ray origin minus the grid's float32 corner `lo`: exact
for nearby points by Sterbenz, else rounded at the local magnitude), so rounding is relative to
the grid's extent and the ray's distance, never to how far the scene lies from the origin. The
margin is therefore 1e-3 cells plus 32 float32 ulps of the grid's extent in cell units (the same
handful of cells' thousandths at the origin and at 1e6), so a 3D-DDA whose float32 boundary
distances are off by rounding still finds every hit in a cell it visits.

Memory is bounded (viewer.cl.limits): the pair count of a resolution is counted first, and the
build's buffers (keys, values and sort scratch 16 bytes per pair, segments, blocks, cells) must
fit the device's per-buffer limit and the structure budget (a share of its global memory). An
automatic resolution over either is coarsened (GridStats.coarsened counts the steps); a fixed
`resolution` over it, or a grid that cannot fit even coarse, stops with one RtwalkError line.

Resolution (`grid_resolution`): cells per axis = extent_axis * cbrt(density * N / volume), i.e.
about `density` cells per triangle, shaped like the scene's box (Wald/Kalojanov's rule); each
axis in [1, max_axis] and the total at most max_cells. `resolution` > 0 instead fixes the cells
along the longest axis (the others by extent). An automatic resolution whose triangles meet more
than GridSpec.max_cells_per_triangle cells each on average (long thin triangles, which the rule does not
foresee) is coarsened like one over the memory bound.

Layouts (device buffers, all little-endian):
  header : GRID_DTYPE, one record (96 bytes; float4 lo, hi, cell, inv, eps; int4 res, res.w =
           total cells)
  cells  : uint32 (ncells, 2): first ref, ref count; cell id = x + rx * (y + ry * z)
  refs   : uint32 (pairs,): triangle slots, grouped by cell in cell order
  tris   : float32 (n, 3, 4): the triangles' vertices as float4 (w = 0); `triangles_f4`
  blocks : GRID_BLOCK_DTYPE (nblocks,): each cell's triangles four at a time in SoA form for the
           float4 triangle test (rt_intersect_triangle4); cell c's ceil(count / 4) blocks start
           at cell_blocks[c] (uint32 (ncells,))
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer.cl import io as clio
from viewer.cl.limits import DeviceLimits, check_alloc, check_total, device_limits
from viewer.cl.pool import BufferPool
from viewer.errors import RtwalkError

KERNEL = Path(__file__).resolve().parent / "grid_build.cl"
WG = 64
MAX_PAIRS = 2**31  # pairs in one build (uint32 offsets); memory limits usually bind first
PAIR_BYTES = 16  # keys + values + the radix sort's keys + values scratch, per pair

GRID_DTYPE = np.dtype([("lo", "<f4", 4), ("hi", "<f4", 4), ("cell", "<f4", 4), ("inv", "<f4", 4),
                       ("eps", "<f4", 4), ("res", "<i4", 4)])
assert GRID_DTYPE.itemsize == 96

#: Four triangles of one cell: v[3 * vertex + axis, lane] (NaN padding), their slots (-1 padding).
GRID_BLOCK_DTYPE = np.dtype([("v", "<f4", (9, 4)), ("slot", "<i4", 4)])
assert GRID_BLOCK_DTYPE.itemsize == 160


@dataclass
class GridSpec:
    """How fine a grid is: ~density cells per triangle, or `resolution` cells on the longest axis."""

    density: float = 2.0
    resolution: int = 0
    max_axis: int = 512
    max_cells: int = 2**24
    # an automatic resolution whose triangles meet more cells than this each, on average, is too
    # fine for them (the density rule assumes small triangles; a fan of long needles met 325
    # each) and is coarsened; 0: no such bound
    max_cells_per_triangle: float = 32.0


@dataclass
class GridStats:
    res: tuple[int, int, int]
    cells: int
    pairs: int
    nonempty: int
    build_ms: float
    coarsened: int = 0  # resolution steps taken down (device memory, or triangles meeting too many cells; 0: as asked)
    nbytes: int = 0  # device bytes of the build's buffers (estimate before allocation)

    def as_dict(self) -> dict[str, float]:
        return {"grid_cells": float(self.cells), "grid_pairs": float(self.pairs),
                "grid_nonempty": float(self.nonempty), "grid_build_ms": self.build_ms,
                "grid_coarsened": float(self.coarsened), "grid_mib": self.nbytes / 2**20}


def build_bytes(pairs: int, ncells: int, n_tris: int) -> tuple[int, int]:
    """(total bytes, largest buffer bytes) a build with `pairs` pairs over ncells cells needs:
    pairs (PAIR_BYTES each), segments (12 bytes per non-empty cell), blocks (at most
    pairs / 4 + non-empty cells of GRID_BLOCK_DTYPE), cells and block starts (12 bytes per cell),
    per-triangle counts."""
    seg = min(pairs, ncells)
    nblocks = pairs // 4 + seg
    blocks = GRID_BLOCK_DTYPE.itemsize * nblocks
    largest = max(4 * pairs, blocks, 8 * ncells)
    return PAIR_BYTES * pairs + 12 * seg + blocks + 12 * ncells + 4 * n_tris, largest


def triangles_f4(triangles: np.ndarray) -> np.ndarray:
    """(n, 3, 4) float32: the vertices as float4 (the kernels' triangle layout)."""
    t = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
    out = np.zeros((len(t), 3, 4), np.float32)
    out[:, :, :3] = t
    return out


def scene_box(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the finite vertices (a unit box at the origin when there are none)."""
    v = np.asarray(triangles, np.float32).reshape(-1, 3)
    v = v[np.isfinite(v).all(1)]
    if len(v) == 0:
        return np.zeros(3, np.float32), np.ones(3, np.float32)
    return v.min(0), v.max(0)


def _f32_down(x: np.ndarray) -> np.ndarray:
    """The largest float32 values <= x (float64 in, float64 out)."""
    f = np.asarray(x, np.float64).astype(np.float32)
    f = np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)
    return f.astype(np.float64)


def _f32_up(x: np.ndarray) -> np.ndarray:
    f = np.asarray(x, np.float64).astype(np.float32)
    f = np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)
    return f.astype(np.float64)


def _padded_extent(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds grown so that no axis is flat and the boundary vertices sit inside (float64; the
    corners are float32 values: the kernels subtract the float32 `lo`). The pad is relative to
    the extent only: far from the origin the grid stays as tight as at it."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    ext = hi - lo
    big = max(float(ext.max()), 1e-30)
    mag = max(float(np.abs(np.concatenate([lo, hi])).max()), 1e-30)
    big = max(big, 1e-6 * mag, 1e-6 if mag < 1 else 0.0)  # a point-like scene: some extent
    pad = 1e-5 * big
    ext_min = 1e-3 * big
    grow = np.maximum(ext_min - ext, 0.0) / 2
    return _f32_down(lo - pad - grow), _f32_up(hi + pad + grow)


def grid_resolution(lo: np.ndarray, hi: np.ndarray, n_tris: int, spec: GridSpec) -> np.ndarray:
    """Cells per axis (int64 (3,)) for a box holding n_tris triangles (see the module docstring)."""
    lo, hi = _padded_extent(lo, hi)
    ext = hi - lo
    if spec.resolution > 0:
        res = np.round(ext / ext.max() * spec.resolution)
    else:
        k = np.cbrt(max(spec.density, 1e-6) * max(n_tris, 1) / float(np.prod(ext)))
        res = np.ceil(ext * k)
    res = np.clip(res, 1, spec.max_axis).astype(np.int64)
    while int(np.prod(res)) > spec.max_cells:
        res = np.maximum(1, np.floor(res * 0.9)).astype(np.int64)
    return res


def grid_header(lo: np.ndarray, hi: np.ndarray, res: np.ndarray) -> np.ndarray:
    """The GRID_DTYPE record of a grid over the (padded) box lo..hi with res cells."""
    plo, phi = _padded_extent(lo, hi)
    res = np.asarray(res, np.int64)
    cell = (phi - plo) / res
    h = np.zeros(1, GRID_DTYPE)
    h["lo"][0, :3] = plo  # float32 exactly (_padded_extent)
    h["hi"][0, :3] = _f32_up(plo + cell * res)
    h["cell"][0, :3] = cell
    h["inv"][0, :3] = 1.0 / cell
    # local coordinates (see the module docstring): rounding relative to the grid's extent
    ext = float((phi - plo).max())
    h["eps"][0, :3] = 1e-3 + 32 * float(np.spacing(np.float32(ext))) / cell
    h["res"][0, :3] = res
    h["res"][0, 3] = int(np.prod(res))
    return h


class UniformGrid:
    """A uniform grid on the device, rebuilt by `build` (buffers reused when large enough)."""

    def __init__(self, ctx: Any = None, prims: Any = None):
        from viewer.cl import build, cl_context
        from viewer.cl.primitives import primitives

        self.ctx = ctx or cl_context()
        self.prims = prims or primitives(self.ctx)
        prog = build(KERNEL, {"WG": WG}, self.ctx)
        self._k = {name: clio.kernel(prog, name) for name in ("grid_count", "grid_write", "grid_ranges", "grid_clamp",
                                                             "grid_block_counts", "grid_blocks")}
        self._bufs = BufferPool(self.ctx, "uniform grid")
        self.header_host = np.zeros(1, GRID_DTYPE)
        self.header = self._buf("header", GRID_DTYPE.itemsize)
        self._count_hosts: dict[str, np.ndarray] = {}
        self._last: tuple[tuple, int] | None = None  # ((resolution, triangles), pairs) of the last exact-size build
        self.stats: GridStats | None = None

    def _buf(self, name: str, nbytes: int) -> Any:
        return self._bufs.get(name, nbytes)

    @property
    def cells(self) -> Any:
        return self._bufs["cells"]

    @property
    def refs(self) -> Any:
        return self._bufs["vals"]

    @property
    def blocks(self) -> Any:
        return self._bufs["blocks"]

    @property
    def cell_blocks(self) -> Any:
        return self._bufs["cell_blocks"]

    def _run(self, name: str, n: int, *args: Any) -> None:
        if n:
            self._k[name](self.ctx.queue, (-(-n // WG) * WG,), (WG,), *args)

    def build(self, tris: Any, n: int, lo: np.ndarray, hi: np.ndarray, spec: GridSpec | None = None,
              limits: DeviceLimits | None = None) -> GridStats:
        """Bin n triangles (device buffer in the `tris` layout) into a grid over lo..hi; `limits`
        (default: the device's, viewer.cl.limits) bound its memory (module docstring)."""
        spec = spec or GridSpec()
        lim = limits or device_limits(self.ctx)
        cl, q, u = self.ctx.cl, self.ctx.queue, np.uint32
        t0 = time.perf_counter()
        res = grid_resolution(lo, hi, n, spec)
        key = (tuple(int(r) for r in res), int(n))
        if self._last is not None and self._last[0] == key:  # a rebuild: buffers sized from the last one
            st = self._build_sized(tris, n, lo, hi, res, self._last[1], lim, t0)
            if st is not None:
                self._last = (key, st.pairs)
                return st
        counts = self._buf("counts", 4 * max(n, 1))
        coarsened = 0
        while True:
            self.header_host = grid_header(lo, hi, res)  # kept (a new array per round) until it lands
            clio.copy(q, self.header, self.header_host, is_blocking=False)
            self._run("grid_count", n, self.header, tris, u(n), counts)
            pairs = self._pair_total(counts, n)
            ncells = int(np.prod(res))
            total, largest = build_bytes(pairs, ncells, n)
            fits = pairs <= MAX_PAIRS and largest <= lim.max_alloc and total <= lim.budget
            per_tri = spec.max_cells_per_triangle
            coarse_enough = per_tri <= 0 or pairs <= per_tri * max(n, 1)
            if (fits and coarse_enough) or spec.resolution > 0 or int(res.max()) == 1:
                break
            # automatic resolution: coarser by a root of the excess (pairs shrink about with the
            # cell count for big triangles, with the cells per axis for long thin ones, slower for
            # small ones: at most a few rounds)
            over = max(pairs / MAX_PAIRS, largest / lim.max_alloc, total / lim.budget)
            dense = pairs / (per_tri * max(n, 1)) if per_tri > 0 else 0.0
            f = min(0.8, float(over) ** (-1 / 3)) if over > 1 else 0.8
            if dense > 1:
                f = min(f, max(0.25, float(dense) ** (-1 / 2)))
            res = np.maximum(1, np.floor(res * f)).astype(np.int64)
            coarsened += 1
        what = f"uniform grid {tuple(int(r) for r in res)} ({pairs:,} triangle-cell pairs)"
        if pairs > MAX_PAIRS:
            raise RtwalkError(f"{what}: at most {MAX_PAIRS:,} pairs; choose a lower resolution")
        if spec.resolution > 0 and (largest > lim.max_alloc or total > lim.budget):
            what = f"{what} (choose a lower resolution)"
        check_alloc(largest, what, limits=lim)
        check_total(total, what, limits=lim)
        keys = self._buf("keys", 4 * pairs)
        vals = self._buf("vals", 4 * pairs)
        cells = self._buf("cells", 8 * ncells)
        cl.enqueue_fill_buffer(q, cells, np.uint32(0), 0, 8 * ncells)
        self._run("grid_write", n, self.header, tris, u(n), counts, keys, vals, u(pairs))
        nonempty = 0
        if pairs:
            self.prims.sort_pairs(keys, vals, pairs, key_bits=max(1, (ncells - 1).bit_length()))
            # segments and blocks on device counts (launched for bounds): no wait until the end
            seg = self.prims.segments_dev(keys, self._count_buf("pairs", pairs), pairs, None,
                                          self._chunks(min(pairs, ncells)), self._count_buf("nonempty"))
            self._run("grid_ranges", min(pairs, ncells), seg.key, seg.start, seg.length,
                      self._bufs["count_nonempty"], cells)
        cell_blocks = self._buf("cell_blocks", 4 * ncells)
        self._run("grid_block_counts", ncells, cells, u(ncells), cell_blocks)
        self.prims.exclusive_scan_dev(cell_blocks, cell_blocks, self._count_buf("ncells", ncells), ncells,
                                      self._count_buf("nblocks"))
        # at most pairs / 4 + one partial block per non-empty cell (build_bytes counts this bound)
        blocks = self._buf("blocks", GRID_BLOCK_DTYPE.itemsize * max(pairs // 4 + min(pairs, ncells), 1))
        if pairs:
            self._run("grid_blocks", ncells, cells, cell_blocks, vals, tris, u(ncells), blocks)
        self._before_last_wait(tris, pairs, max(pairs, 1), ncells)
        got = np.zeros(1, np.uint32)
        if pairs:
            clio.copy(q, got, self._bufs["count_nonempty"])  # the build's one wait (statistics, timing)
        else:
            clio.finish(q)
        nonempty = int(got[0])
        self.stats = GridStats(tuple(int(r) for r in res), ncells, int(pairs), int(nonempty),
                               (time.perf_counter() - t0) * 1e3, coarsened, int(total))
        self._last = (key, int(pairs)) if coarsened == 0 else None
        return self.stats

    def _build_sized(self, tris: Any, n: int, lo: np.ndarray, hi: np.ndarray, res: np.ndarray, last_pairs: int,
                     lim: DeviceLimits, t0: float) -> GridStats | None:
        """A rebuild at the last build's resolution with one wait: the pair buffers are sized
        from the last build's pairs (+25%), every count stays on the device, and the pair total
        read at the end says whether they sufficed. None when they did not (or the 32-bit scan
        could have wrapped, or the bound does not fit the device): the caller builds exactly."""
        q, u = self.ctx.queue, np.uint32
        ncells = int(np.prod(res))
        cap = int(last_pairs * 1.25) + 1024
        nbytes, largest = build_bytes(cap, ncells, n)
        if cap > MAX_PAIRS or largest > lim.max_alloc or nbytes > lim.budget or n == 0:
            return None
        self.header_host = grid_header(lo, hi, res)
        clio.copy(q, self.header, self.header_host, is_blocking=False)
        counts = self._buf("counts", 4 * n)
        self._run("grid_count", n, self.header, tris, u(n), counts)
        self.prims.reduce_dev(counts, n, "max", np.uint32, self._count_buf("cmax"))
        self.prims.exclusive_scan_dev(counts, counts, self._count_buf("n_tris", n), n, self._count_buf("total"))
        used = self._count_buf("pairs")
        self._run("grid_clamp", 1, self._bufs["count_total"], u(cap), used)
        keys, vals = self._buf("keys", 4 * cap), self._buf("vals", 4 * cap)
        cells = self._buf("cells", 8 * ncells)
        self.ctx.cl.enqueue_fill_buffer(q, cells, np.uint32(0), 0, 8 * ncells)
        self._run("grid_write", n, self.header, tris, u(n), counts, keys, vals, u(cap))
        self.prims.sort_pairs_dev(keys, vals, used, cap, max(1, (ncells - 1).bit_length()))
        seg = self.prims.segments_dev(keys, used, cap, None, self._chunks(min(cap, ncells)),
                                      self._count_buf("nonempty"))
        self._run("grid_ranges", min(cap, ncells), seg.key, seg.start, seg.length, self._bufs["count_nonempty"], cells)
        cell_blocks = self._buf("cell_blocks", 4 * ncells)
        self._run("grid_block_counts", ncells, cells, u(ncells), cell_blocks)
        self.prims.exclusive_scan_dev(cell_blocks, cell_blocks, self._count_buf("ncells", ncells), ncells,
                                      self._count_buf("nblocks"))
        blocks = self._buf("blocks", GRID_BLOCK_DTYPE.itemsize * max(cap // 4 + min(cap, ncells), 1))
        self._run("grid_blocks", ncells, cells, cell_blocks, vals, tris, u(ncells), blocks)
        self._before_last_wait(tris, used, cap, ncells)
        got = np.zeros(3, np.uint32)  # pair total, largest count, non-empty cells: the build's one wait
        for k, name in ((1, "count_cmax"), (2, "count_nonempty")):
            clio.copy(q, got[k:k + 1], self._bufs[name], is_blocking=False)
        clio.copy(q, got[0:1], self._bufs["count_total"])
        pairs, cmax, nonempty = (int(x) for x in got)
        if cmax * n >= 2**32 or pairs > cap:
            return None  # overflow (rare: the scene grew): build again with exact buffers
        self.stats = GridStats(tuple(int(r) for r in res), ncells, pairs, nonempty,
                               (time.perf_counter() - t0) * 1e3, 0, int(build_bytes(pairs, ncells, n)[0]))
        return self.stats

    def _before_last_wait(self, tris: Any, n_pairs: Any, bound: int, ncells: int) -> None:
        """Work a subclass enqueues on the finished cells and sorted pairs (n_pairs of them: an int,
        or a uint32 device count; at most `bound`) before the build's last wait, so that its counts
        come back with that wait (viewer.accel.grid2); nothing here."""

    def _count_buf(self, name: str, value: int | None = None) -> Any:
        """A uint32 device count (a device-count primitive's input or output); `value` is written
        to it without a wait."""
        buf = self._buf(f"count_{name}", 4)
        if value is not None:
            host = np.array([value], np.uint32)
            self._count_hosts[name] = host  # kept alive for the asynchronous write
            clio.copy(self.ctx.queue, buf, host, is_blocking=False)
        return buf

    def _pair_total(self, counts: Any, n: int) -> int:
        """Exclusive scan of the per-triangle counts in place; the exact total even past 2**32
        (the device scan wraps: then the counts are summed on the host, a rare large build)."""
        if not n:
            return 0
        # the largest count and the scan's total in one wait (the scan is redone below when it wrapped)
        got = np.zeros(2, np.uint32)
        self.prims.reduce_dev(counts, n, "max", np.uint32, self._count_buf("cmax"))
        self.prims.exclusive_scan_dev(counts, self._buf("offsets_tmp", 4 * n), self._count_buf("n_tris", n), n,
                                      self._count_buf("total"))
        clio.copy(self.ctx.queue, got[0:1], self._bufs["count_cmax"], is_blocking=False)
        clio.copy(self.ctx.queue, got[1:2], self._bufs["count_total"])
        cmax = int(got[0])
        if cmax * n < 2**32:
            clio.copy(self.ctx.queue, counts, self._bufs["offsets_tmp"], byte_count=4 * n)
            return int(got[1])
        host = np.empty(n, np.uint32)
        clio.copy(self.ctx.queue, host, counts)
        total = int(host.sum(dtype=np.int64))
        if total < 2**32:
            self.prims.exclusive_scan(counts, counts, n)
        return total

    def _chunks(self, pairs: int) -> Any:
        from viewer.cl.primitives import Chunks

        return Chunks(0, self._buf("seg_key", 4 * pairs), self._buf("seg_start", 4 * pairs),
                      self._buf("seg_len", 4 * pairs))

    def to_numpy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(header record, cells (ncells, 2) uint32, refs (pairs,) uint32) copied from the device."""
        assert self.stats is not None, "build first"
        cells = np.empty((self.stats.cells, 2), np.uint32)
        refs = np.empty(self.stats.pairs, np.uint32)
        q = self.ctx.queue
        clio.copy(q, cells, self.cells)
        if self.stats.pairs:
            clio.copy(q, refs, self.refs)
        return self.header_host.copy(), cells, refs

    def blocks_to_numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """(cell_blocks (ncells,) uint32, blocks GRID_BLOCK_DTYPE) copied from the device."""
        assert self.stats is not None, "build first"
        cb = np.empty(self.stats.cells, np.uint32)
        q = self.ctx.queue
        clio.copy(q, cb, self.cell_blocks)
        counts = self.to_numpy()[1][:, 1].astype(np.int64)
        nb = int(((counts + 3) // 4).sum())
        blocks = np.empty(nb, GRID_BLOCK_DTYPE)
        if nb:
            clio.copy(q, blocks, self.blocks)
        return cb, blocks

    def release(self) -> None:
        self._bufs.release()


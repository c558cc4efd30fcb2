"""The voxel-walk tracer on the device, without GL: IVW and EC over the shared uniform grid (or
the two-level grid of viewer.accel.grid2, whose sub-grids IVW and the one-launch EC walk).

`VoxelWalker.trace(origin, dir, n, any_hit, mode)` traces n rays held in device buffers (the
viewer/cl/transfer.py layout) into (t, tri) device buffers; kernels ivw.cl and ec.cl beside this
file. With `stats` on, each pass also records what the study and the overlays need
(`PassStats`): per-ray iterations and first non-empty cell, and for EC per iteration the active
rays, ray-cell pairs, work-groups after compaction, resolved rays and the distinct cells per
screen tile; rays per cell at the first iteration. The per-iteration host statistics read small
device arrays back, so they cost time: timing runs leave `stats` off. Without them IVW and the
one-launch EC (ec_sort "tile", ec_tile.cl: 5 launches per pass) do not wait on the host at all, and
the global-sort EC (ec.cl) waits once per batch of iterations (usually once). With `skip`, IVW
and/or the one-launch EC skip empty 8^3 blocks of cells (walk.cl VW_SKIP; the occupancy is rebuilt
after each grid build; off by default: measured slower).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.grid import UniformGrid
from viewer.cl import io as clio
from viewer.cl.limits import device_limits, local_mem, new_buffer
from viewer.errors import RtwalkError

HERE = Path(__file__).resolve().parent
WG_IVW = 64
WG_SMALL = 64  # local size of the one-per-ray EC kernels
SKIP_SHIFTS = (3, 0)  # walk.cl empty-space skipping: blocks of 8^3 cells, no coarse level (VW_SHIFT_FINE, _COARSE)
TILE = 8  # screen tile edge for the divergence statistics (pixels)
EC_BATCH = 8  # EC iterations enqueued before the first look at the active count (at least)
EC_GROUPS_PER_CU = 64  # persistent ec_process work-groups per compute unit (each takes chunks in turn)
EC_SORTS = ("tile", "global")
SKIPS = ("none", "ivw", "ec", "all")
EC_STAGE_MIN = 8  # ec_tile: cells with at least this many of a partition's rays get their triangles staged
EC_TAIL = 0  # ec_tile: a partition down to fewer active rays finishes them walking alone (0: never; see the docs)
EC_INLINE_MAX = 4  # ec_tile: units of at most this many triangles (one SoA block) are tested in the walk, not sorted
TILE_TOTALS = 6  # ec_tile.cl ECT_TOTALS: per work-group iterations, units, chunks, rays, units and rays sorted
TILE_BYTES_PER_RAY = 76  # ec_tile.cl's local arrays per partition ray (24 ray state + 16 lists + 24 table + 12 chunks)


def tile_partition(local_mem: int, wg: int) -> int:
    """Rays per ec_tile work-group: the largest power of two <= 1024 whose local arrays (and the
    staged triangle blocks and scan partials, 172 bytes per work-item) fit half the device's local
    memory (a partition larger than the work-group keeps chunks full; half: the compiler's own)."""
    p = 1024
    while p > wg and TILE_BYTES_PER_RAY * p + 172 * wg > local_mem // 2:
        p //= 2
    return max(p, wg)


CHUNKS = (16, 32, 64, 128, 256)  # the chunk sizes (work-group sizes) the EC kernels accept


def largest_chunk(local_bytes: int) -> int | None:
    """The largest chunk whose smallest ec_tile partition fits `local_bytes` of local memory (None:
    not even 16)."""
    fits = [c for c in CHUNKS if (TILE_BYTES_PER_RAY + 172) * c <= local_bytes]
    return fits[-1] if fits else None


def check_tile_local(local_bytes: int, wg: int) -> None:
    """RtwalkError (one line) when even the smallest ec_tile partition (one ray per work-item) does
    not fit the device's local memory: chunk=256 needs 62 KiB, NVIDIA's OpenCL offers 48 KiB (the
    build would fail with "too much shared data"; PoCL has megabytes)."""
    need = TILE_BYTES_PER_RAY * wg + 172 * wg
    if need > local_bytes:
        fits = largest_chunk(local_bytes)
        hint = f"choose chunk <= {fits}" if fits else "this device cannot run it"
        raise RtwalkError(f"voxelwalk chunk={wg}: the EC tile kernel needs {need / 1024:.1f} KiB of local memory "
                          f"per work-group, the OpenCL device has {local_bytes / 1024:.1f} KiB; {hint}")


def check_int64_atomics(extensions: str) -> None:
    """RtwalkError (one line) without cl_khr_int64_extended_atomics: EC keeps each ray's nearest hit
    as a 64-bit atom_min key (walk.cl vw_pack). PoCL and NVIDIA have it."""
    if "cl_khr_int64_extended_atomics" not in str(extensions).split():
        raise RtwalkError("voxelwalk needs the OpenCL extension cl_khr_int64_extended_atomics (64-bit atom_min), "
                          "which this device lacks")


def tile_order(size: tuple[int, int], n: int, p: int) -> np.ndarray:
    """Ray indices 0..n-1 (row-major pixels of `size`) in screen-tile order: square tiles of p
    pixels (or the nearest 2:1 rectangle), then the rays past the image."""
    w, h = int(size[0]), int(size[1])
    tw = 1 << ((p.bit_length() - 1 + 1) // 2)
    th = max(1, p // tw)
    pix = np.arange(min(n, w * h), dtype=np.int64)
    x, y = pix % w, pix // w
    tile = (y // th) * (-(-w // tw)) + x // tw
    order = np.lexsort((pix, tile))
    return np.concatenate([pix[order], np.arange(w * h, n, dtype=np.int64)]).astype(np.uint32)


@dataclass
class PassStats:
    """What one pass did. Arrays are per ray of the batch (row-major pixels)."""

    mode: str
    rays: int = 0  # active rays
    pairs: int = 0  # ray-unit pairs (units tested) over all iterations (EC), sorted or tested in the walk
    sorted_pairs: int = 0  # EC (sort=tile): the pairs that went through the sort (the others: units of <= inline)
    sorted_rays: int = 0  # EC (sort=tile): the rays that reached a unit to sort
    workgroups: int = 0  # chunks after compaction over all iterations (EC)
    iterations: int = 0  # EC iterations (IVW: the largest per-ray iteration count)
    reorder_ms: float = 0.0  # EC: pair enumeration, sort, chunks, resolve (host-timed, queue finished)
    trace_ms: float = 0.0  # EC: the chunk kernels; IVW: the walk kernel
    iters: np.ndarray | None = None  # int32 per ray: non-empty cells visited
    first_cell: np.ndarray | None = None  # uint32 per ray: first non-empty cell (0xffffffff: none)
    per_iter: list[dict[str, float]] = field(default_factory=list)  # EC: per iteration
    rays_per_cell: np.ndarray | None = None  # rays of each non-empty cell at the first iteration

    def resolved_fraction(self) -> np.ndarray:
        """Fraction of the active rays resolved at iteration k (index k-1), from the per-ray counts."""
        if self.iters is None or self.rays == 0:
            return np.zeros(0)
        it = self.iters[self.iters > 0]
        return np.bincount(it)[1:] / float(self.rays)


def tile_divergence(cells: np.ndarray, size: tuple[int, int], tile: int = TILE) -> tuple[np.ndarray, np.ndarray]:
    """Distinct cells per tile x tile pixel tile. `cells`: uint32 per pixel (0xffffffff = none).

    Returns (per-pixel value of its tile, per-tile values of the tiles holding at least one cell)."""
    w, h = int(size[0]), int(size[1])
    cells = np.asarray(cells, np.uint32).reshape(-1)[: w * h]
    tx = -(-w // tile)
    pix = np.arange(w * h, dtype=np.int64)
    tile_of = (pix % w) // tile + tx * ((pix // w) // tile)
    ok = cells != 0xFFFFFFFF
    ntiles = tx * (-(-h // tile))
    if not ok.any():
        return np.zeros(w * h, np.int32), np.zeros(0, np.int64)
    pair = np.unique(tile_of[ok] * (1 << 32) + cells[ok].astype(np.int64))
    per_tile = np.bincount(pair >> 32, minlength=ntiles)
    return per_tile[tile_of].astype(np.int32), per_tile[per_tile > 0]


class VoxelWalker:
    """IVW and EC kernels over a UniformGrid and its triangles (device buffers)."""

    def __init__(self, ctx: Any, grid: UniformGrid, chunk: int = 64, window: int = 1, ec_sort: str = "tile",
                 skip: str = "none", inline: int = EC_INLINE_MAX, tail: int = EC_TAIL):
        """`skip`: which walks skip empty 8^3 blocks of top cells whole (walk.cl VW_SKIP): none, ivw,
        ec or all (the same cells are visited either way). `inline`: the one-launch EC tests units
        of at most this many triangles in the walk instead of sorting them (0: every unit sorted)."""
        from viewer.cl import build

        if ec_sort not in EC_SORTS:
            raise ValueError(f"ec_sort must be one of {EC_SORTS}")
        if skip not in SKIPS:
            raise ValueError(f"skip must be one of {SKIPS}")
        self.ctx, self.grid, self.chunk, self.window = ctx, grid, int(chunk), int(window)
        self.ec_sort = ec_sort
        self.prims = grid.prims
        self.skip_shifts = SKIP_SHIFTS
        shifts = {"VW_SHIFT_FINE": SKIP_SHIFTS[0], "VW_SHIFT_COARSE": SKIP_SHIFTS[1]}
        self.skip = skip
        from viewer.accel.grid2 import TwoLevelGrid

        self.two_level = isinstance(grid, TwoLevelGrid)  # IVW and the one-launch EC walk its sub-grids
        two = {"TWO_LEVEL": None} if self.two_level else {}
        ivw_skip = {"VW_SKIP": None} if skip in ("ivw", "all") else {}
        ec_skip = {"VW_SKIP": None} if skip in ("ec", "all") else {}
        check_int64_atomics(ctx.device.extensions)
        check_tile_local(local_mem(ctx), self.chunk)
        ivw = build(HERE / "ivw.cl", {"WG": WG_IVW, **shifts, **ivw_skip, **two}, ctx)
        ec = build(HERE / "ec.cl", {"WG": self.chunk}, ctx)
        self.partition = tile_partition(local_mem(ctx), self.chunk)
        self.inline, self.tail = int(inline), int(tail)
        ect = build(HERE / "ec_tile.cl", {"WG": self.chunk, "P": self.partition, "STAGE_MIN": EC_STAGE_MIN,
                                          "INLINE_MAX": self.inline, "TAIL": self.tail, **shifts, **ec_skip, **two},
                    ctx)
        self.k = {"ivw": clio.kernel(ivw, "ivw_trace"), "macro": clio.kernel(ivw, "vw_macro_build")}
        self._macro_of: Any = None  # the GridStats whose macro cells are built
        for name in ("ec_init", "ec_count", "ec_write", "ec_process", "ec_resolve", "ec_finish"):
            self.k[name] = clio.kernel(ec, name)
        for name in ("ec_tile", "ec_tile_first"):
            self.k[name] = clio.kernel(ect, name)
        self._perm_key: tuple | None = None
        self._pending: list[tuple[np.ndarray, Any, Any]] = []  # one-launch EC totals on their way back
        self._last_totals: tuple[int, ...] = (0, 0, 0, 0, 0, 0)
        self._last_ms = 0.0
        self._bufs: dict[str, Any] = {}
        self._host_n = np.zeros(1, np.uint32)  # kept alive for its asynchronous write
        self._last_iterations = 0  # the last EC pass's iterations: the next pass's first batch

    def _buf(self, name: str, nbytes: int) -> Any:
        buf = self._bufs.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = new_buffer(self.ctx, self.ctx.cl.mem_flags.READ_WRITE, int(nbytes), f"voxelwalk {name}")
            self._bufs[name] = buf
        return buf

    def _macro(self) -> tuple[Any, Any]:
        """Block occupancy of the current grid at both levels of walk.cl's empty-space skipping:
        rebuilt (one launch per level) when the grid was built again (a new GridStats)."""
        st = self.grid.stats
        if self._macro_of is not st:
            fine = self.skip_shifts[0]
            for shift in self.skip_shifts:
                shift = shift or fine  # one level: the coarse buffer is the fine one again
                br = [-(-int(r) // (1 << shift)) for r in st.res]
                n = br[0] * br[1] * br[2]
                buf = self._buf(f"occ{shift}", max(16, n))
                self._run("macro", n, self.grid.header, self.grid.cells, np.int32(shift), buf)
            self._macro_of = st
        return tuple(self._bufs[f"occ{s or self.skip_shifts[0]}"] for s in self.skip_shifts)

    def _run(self, name: str, n: int, *args: Any, wg: int = WG_SMALL) -> None:
        if n:
            self.k[name](self.ctx.queue, (-(-n // wg) * wg,), (wg,), *args)

    def _read(self, buf: Any, n: int, dtype: Any) -> np.ndarray:
        out = np.empty(n, dtype)
        if n:
            clio.copy(self.ctx.queue, out, buf)
        return out

    # -- IVW ------------------------------------------------------------------------------
    def trace_ivw(self, tris: Any, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int, any_hit: bool,
                  stats: bool = False) -> PassStats:
        g, q = self.grid, self.ctx.queue
        iters, first = self._buf("iters", 4 * n), self._buf("first", 4 * n)
        t0 = time.perf_counter()
        macro = self._macro()
        sub = (g.sub_of, g.subs, g.scells, g.sblocks, g.scb, g.bblocks) if self.two_level else ()
        self._run("ivw", n, g.header, g.cells, g.blocks, g.cell_blocks, *sub, ray_o, ray_d, out_t, out_id, np.int32(n),
                  np.int32(bool(any_hit)), iters, first, *macro, wg=WG_IVW)
        ps = PassStats("ivw")
        if stats:  # timed only with statistics (a wait; frames leave the kernel in flight)
            clio.finish(q)
            ps.trace_ms = (time.perf_counter() - t0) * 1e3
            ps.iters = self._read(iters, n, np.int32)
            ps.first_cell = self._read(first, n, np.uint32)
            ps.rays = self._active(ray_o, ray_d, n)
            ps.iterations = int(ps.iters.max()) if n else 0
            fc = ps.first_cell[ps.first_cell != 0xFFFFFFFF]
            ps.rays_per_cell = np.unique(fc, return_counts=True)[1] if len(fc) else np.zeros(0, np.int64)
        return ps

    def _active(self, ray_o: Any, ray_d: Any, n: int) -> int:
        from viewer.cl import mapped

        with mapped(self.ctx, ray_o, (n, 4), np.float32) as o, mapped(self.ctx, ray_d, (n, 4), np.float32) as d:
            return int(np.count_nonzero(d[:, 3] > o[:, 3]))

    # -- EC -------------------------------------------------------------------------------
    def _count_bufs(self) -> dict[str, Any]:
        """Device-side counts of the EC loop (uint32 each; totals: iterations, pairs, chunks)."""
        return {name: self._buf(f"count_{name}", 4 * k) for name, k in
                (("n", 1), ("m0", 1), ("m1", 1), ("p", 1), ("chunks", 1), ("totals", 4))}

    def _ray_gsize(self, n: int) -> tuple[int]:
        """Work-items of the per-ray EC kernels (they stride over the device's active count)."""
        cap = WG_SMALL * 64 * max(1, int(self.ctx.compute_units))
        return (min(-(-n // WG_SMALL) * WG_SMALL, cap),)

    def trace_ec(self, tris: Any, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int,
                 stats: bool = False, size: tuple[int, int] | None = None) -> PassStats:
        """EC over rays 0..n-1: the one-launch tile loop (ec_sort "tile", one non-empty cell per
        iteration), else the thesis's global sort per iteration (ec_sort "global", or `window` != 1)."""
        if self.ec_sort == "tile" and self.window == 1:
            return self._trace_ec_tile(ray_o, ray_d, out_t, out_id, n, stats, size)
        return self._trace_ec_global(tris, ray_o, ray_d, out_t, out_id, n, stats, size)

    def _perm(self, size: tuple[int, int] | None, n: int) -> tuple[Any, Any]:
        """The rays' screen-tile order on the device and its inverse (each ray's position in it),
        uploaded once per size: ec_tile_first walks the rays in their own order (IVW's: a
        work-group's rays are neighbours in memory; in tile order the dragon's walks measured
        1.24x slower) and puts each flag at the ray's tile-order position for the compaction."""
        key = (tuple(size) if size is not None else None, n, self.partition)
        if self._perm_key != key:
            order = tile_order(size, n, self.partition) if size is not None else np.arange(n, dtype=np.uint32)
            inv = np.empty(n, np.uint32)
            inv[order] = np.arange(n, dtype=np.uint32)
            clio.copy(self.ctx.queue, self._buf("perm", 4 * n), order, is_blocking=False)
            clio.copy(self.ctx.queue, self._buf("perm_inv", 4 * n), inv, is_blocking=False)
            self._perm_host, self._perm_key = (order, inv), key  # kept alive for the asynchronous writes
        return self._bufs["perm"], self._bufs["perm_inv"]

    def _first_acc(self) -> Any:
        """ec_tile_first's totals (rays walked, units tested), zero between passes: ec_tile's first
        work-group moves them into its own totals and clears them."""
        if "first_acc" not in self._bufs:
            self._acc_zero = np.zeros(2, np.uint32)  # kept alive for the asynchronous write
            clio.copy(self.ctx.queue, self._buf("first_acc", 8), self._acc_zero, is_blocking=False)
        return self._bufs["first_acc"]

    def _harvest(self, force: bool = False) -> None:
        """Takes the per-group totals of the one-launch EC passes that have come back (all of them,
        waiting, with `force`): iterations (the largest), pairs, chunks, rays, sorted pairs and
        rays; the loop kernel's ms."""
        cl = self.ctx.cl
        while self._pending:
            host, copy_ev, kernel_ev = self._pending[0]
            if not force and copy_ev.command_execution_status != cl.command_execution_status.COMPLETE:
                break
            self._pending.pop(0)
            self._last_ms = max(0, kernel_ev.profile.end - kernel_ev.profile.start) / 1e6
            self._last_totals = (int(host[:, 0].max()), *(int(x) for x in host[:, 1:].sum(0)))

    def _trace_ec_tile(self, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int, stats: bool,
                       size: tuple[int, int] | None) -> PassStats:
        """EC with every iteration on the device (ec_tile.cl): rays entering the grid are compacted
        in screen-tile order, then one work-group per partition of them loops over its iterations
        (walk, counting sort by cell, chunks with staged triangles, resolve). A fixed 5 launches
        per pass whatever the iteration count and no wait: the per-group totals (iterations, pairs,
        chunks) come back with a later wait and are reported by a later pass (with `stats`: this
        pass's own, after one wait)."""
        g, q, u = self.grid, self.ctx.queue, np.uint32
        ps = PassStats("ec")
        if n == 0:
            return ps
        iters, first = self._buf("iters", 4 * n), self._buf("first", 4 * n)
        flags, act = self._buf("flags", 4 * n), self._buf("act", 4 * n)
        cb = self._count_bufs()
        perm, perm_inv = self._perm(size, n)
        macro = self._macro()
        self._host_n[0] = n
        clio.copy(q, cb["n"], self._host_n, is_blocking=False)
        unit, top = self._buf("unit", 4 * n), self._buf("top", 4 * n)
        acc = self._first_acc()
        sub = (g.sub_of, g.subs, g.scells, g.sblocks, g.scb, g.bblocks, u(g.stats.subcells)) if self.two_level else ()
        self._run("ec_tile_first", n, g.header, g.cells, g.blocks, g.cell_blocks, *sub, ray_o, ray_d, perm_inv, u(n),
                  flags, unit, top, out_t, out_id, iters, first, acc, *macro)
        self.prims.compact_dev(cb["n"], n, cb["m0"], flags=flags, src=perm, dst=act)
        groups = -(-n // self.partition)
        totals = self._buf("tile_totals", 4 * TILE_TOTALS * groups)
        ev = self.k["ec_tile"](q, (groups * self.chunk,), (self.chunk,), g.header, g.cells, g.blocks, g.cell_blocks,
                               *sub, ray_o, ray_d, act, cb["m0"], unit, top, out_t, out_id, iters, totals, acc, *macro)
        host = np.empty((groups, TILE_TOTALS), np.uint32)
        self._pending.append((host, clio.copy(q, host, totals, is_blocking=stats), ev))
        if stats:  # the study's run: this pass's own figures (one wait)
            self._harvest(force=True)
        else:  # no wait: the last pass whose totals are back (usually the previous pass of the frame)
            self._harvest()
        ps.iterations, ps.pairs, ps.workgroups, ps.rays, ps.sorted_pairs, ps.sorted_rays = self._last_totals
        ps.trace_ms = self._last_ms
        ps.reorder_ms = 0.0  # the sort runs inside the one kernel (trace_ms)
        if stats:
            ps.iters = self._read(iters, n, np.int32)
            fc = self._read(first, n, np.uint32)
            ps.first_cell = fc if size is not None else None
            fc = fc[fc != 0xFFFFFFFF]
            ps.rays_per_cell = np.unique(fc, return_counts=True)[1] if len(fc) else np.zeros(0, np.int64)
            walked = ps.iters[ps.iters > 0]
            # derived per iteration: one cell per active ray (on the two-level grid an iteration's
            # unit may be a sub-cell or a big list, while iters counts top cells: an approximation)
            for k in range(1, int(walked.max()) + 1 if len(walked) else 1):
                active = float(np.count_nonzero(walked >= k))
                ps.per_iter.append({"active": active, "pairs": active,
                                    "resolved": float(np.count_nonzero(walked == k))})
        return ps

    def _trace_ec_global(self, tris: Any, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int,
                         stats: bool = False, size: tuple[int, int] | None = None) -> PassStats:
        """EC over rays 0..n-1 with the thesis's global sort. Iterations are enqueued in batches with no host round trip
        between them: the active count, the pair count and the chunk count live on the device
        (kernels read them; launches are sized for bounds: n rays, n * window pairs), and after a
        batch one read of the active count says whether to go on. A batch is as long as the last
        pass's iteration count (at least EC_BATCH), then doubles, so a steady pass waits once.
        Iterations past the end find no active rays and do nothing. `window` 0 (every cell at
        once), or a window whose bound does not fit the device, reads its pair count each
        iteration to size the pair buffers.
        With `stats`, every iteration is read back (the study's per-iteration rows)."""
        g, q, u = self.grid, self.ctx.queue, np.uint32
        ps = PassStats("ec")
        if n == 0:
            return ps
        keys, nxt = self._buf("keys", 8 * n), self._buf("next", 4 * n)
        iters, first = self._buf("iters", 4 * n), self._buf("first", 4 * n)
        win_exit = self._buf("win_exit", 4 * n)
        act, act2, flags = self._buf("act", 4 * n), self._buf("act2", 4 * n), self._buf("flags", 4 * n)
        counts = self._buf("counts", 4 * n)
        cb = self._count_bufs()
        cl = self.ctx.cl
        t0 = time.perf_counter()
        self._host_n[0] = n
        clio.copy(q, cb["n"], self._host_n, is_blocking=False)
        cl.enqueue_fill_buffer(q, cb["totals"], u(0), 0, 16)
        self._run("ec_init", n, g.header, ray_o, ray_d, u(n), keys, nxt, iters)
        m_cur, m_nxt = cb["m0"], cb["m1"]
        self.prims.compact_dev(cb["n"], n, m_cur, predicate="x != 0xffffffffu", src=nxt, dst_index=act)
        host = np.zeros(5, np.uint32)  # initial active rays, then totals (iterations, pairs, chunks), active left
        clio.copy(q, host[0:1], m_cur, is_blocking=False)
        if stats and size is not None:
            ps.first_cell = np.full(n, 0xFFFFFFFF, np.uint32)  # no active ray: no cell anywhere
        key_bits = max(1, (int(g.stats.cells) - 1).bit_length())
        limit = int(sum(g.stats.res)) + 8  # a 3D-DDA visits at most rx + ry + rz - 2 cells
        gs = self._ray_gsize(n)
        groups = max(1, min(n * max(self.window, 1), EC_GROUPS_PER_CU * max(1, int(self.ctx.compute_units))))
        # pairs per iteration: at most window per active ray, and a walk crosses at most rx+ry+rz cells;
        # without a bound that fits (window 0, or a wide window) the pair count is read each iteration
        pcap = n * min(self.window, limit)
        read_pairs = self.window == 0 or 5 * 4 * pcap > device_limits(self.ctx).budget
        events = []
        it = 0
        batch = 1 if stats else max(EC_BATCH, self._last_iterations)
        m_prev = int(self._read(m_cur, 1, np.uint32)[0]) if stats else n
        while True:
            for _ in range(batch):
                k = self.k
                k["ec_count"](q, gs, (WG_SMALL,), g.header, g.cells, ray_o, ray_d, keys, nxt, act, m_cur,
                              u(self.window), counts)
                self.prims.exclusive_scan_dev(counts, counts, m_cur, n, cb["p"])
                if read_pairs:  # no usable bound on the pairs: read their count (one wait per iteration)
                    pcap = max(1, int(self._read(cb["p"], 1, np.uint32)[0]))
                pk, pv = self._buf("pkeys", 4 * pcap), self._buf("pvals", 4 * pcap)
                k["ec_write"](q, gs, (WG_SMALL,), g.header, g.cells, ray_o, ray_d, keys, nxt, act, m_cur,
                              u(self.window), counts, pk, pv, win_exit, first, iters)
                self.prims.sort_pairs_dev(pk, pv, cb["p"], pcap, key_bits)
                from viewer.cl.primitives import Chunks

                ch = Chunks(0, self._buf("ck", 4 * pcap), self._buf("cs", 4 * pcap), self._buf("cl", 4 * pcap))
                self.prims.segments_dev(pk, cb["p"], pcap, self.chunk, ch, cb["chunks"])
                events.append(k["ec_process"](q, (groups * self.chunk,), (self.chunk,), g.cells, g.refs, tris,
                                              ray_o, ray_d, ch.key, ch.start, ch.length, pv, keys, cb["chunks"]))
                k["ec_resolve"](q, gs, (WG_SMALL,), keys, nxt, win_exit, act, m_cur, flags, cb["p"],
                                cb["chunks"], cb["totals"])
                self.prims.compact_dev(m_cur, n, m_nxt, flags=flags, src=act, dst=act2)
                if stats:
                    self._stats_row(ps, it, m_prev, cb, m_nxt, ch, act, first, n, size)
                act, act2 = act2, act
                m_cur, m_nxt = m_nxt, m_cur
                it += 1
            clio.copy(q, host[1:4], cb["totals"], is_blocking=False)
            clio.copy(q, host[4:5], m_cur)  # the one wait of a batch
            m_prev = int(host[4])
            if m_prev == 0:
                break
            if it > limit:
                raise RtwalkError(f"voxelwalk EC did not converge in {limit} iterations ({m_prev} rays left)")
            batch = 1 if stats else max(EC_BATCH, it)
        self._bufs["act"], self._bufs["act2"] = act, act2
        self._run("ec_finish", n, keys, u(n), out_t, out_id)
        wall_ms = (time.perf_counter() - t0) * 1e3
        ps.rays = self._active(ray_o, ray_d, n) if stats else int(host[0])
        ps.iterations, ps.pairs, ps.workgroups = int(host[1]), int(host[2]), int(host[3])
        self._last_iterations = ps.iterations
        ps.trace_ms = sum(max(0, e.profile.end - e.profile.start) for e in events) / 1e6
        ps.reorder_ms = max(0.0, wall_ms - ps.trace_ms)
        if stats:
            ps.iters = self._read(iters, n, np.int32)
        return ps

    def _stats_row(self, ps: PassStats, it: int, m: int, cb: dict, m_next_buf: Any, ch: Any, act: Any,
                   first: Any, n: int, size: tuple[int, int] | None) -> None:
        """The study's per-iteration row (reads the iteration's counts back: stats runs only)."""
        p = int(self._read(cb["p"], 1, np.uint32)[0])
        chunks = int(self._read(cb["chunks"], 1, np.uint32)[0]) if p else 0
        m_next = int(self._read(m_next_buf, 1, np.uint32)[0])
        if it == 0 and chunks:
            ch.count = chunks
            ck, _, cl_ = ch.to_numpy(self.ctx)
            ps.rays_per_cell = np.bincount(np.searchsorted(np.unique(ck), ck), weights=cl_).astype(np.int64)
        row = {"active": float(m), "pairs": float(p), "workgroups": float(chunks), "resolved": float(m - m_next)}
        if size is not None:
            a = self._read(act, m, np.uint32)
            fc = np.full(n, 0xFFFFFFFF, np.uint32)
            fc[a] = self._read(first, n, np.uint32)[a]
            _, per_tile = tile_divergence(fc, size)
            row["tile_cells_mean"] = float(per_tile.mean()) if len(per_tile) else 0.0
            row["tiles"] = float(len(per_tile))
            if it == 0:
                ps.first_cell = fc
        ps.per_iter.append(row)

    def release(self) -> None:
        for buf in self._bufs.values():
            buf.release()
        self._bufs.clear()

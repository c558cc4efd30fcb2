"""The voxel-walk tracer on the device, without GL: IVW and EC over the shared uniform grid.

`VoxelWalker.trace(origin, dir, n, any_hit, mode)` traces n rays held in device buffers (the
viewer/cl/transfer.py layout) into (t, tri) device buffers; kernels ivw.cl and ec.cl beside this
file. With `stats` on, each pass also records what the study and the overlays need
(`PassStats`): per-ray iterations and first non-empty cell, and for EC per iteration the active
rays, ray-cell pairs, work-groups after compaction, resolved rays and the distinct cells per
screen tile; rays per cell at the first iteration. The per-iteration host statistics read small
device arrays back, so they cost time: timing runs leave `stats` off.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.grid import UniformGrid
from viewer.cl import io as clio
from viewer.cl.limits import new_buffer
from viewer.errors import RtwalkError

HERE = Path(__file__).resolve().parent
WG_IVW = 64
WG_SMALL = 64  # local size of the one-per-ray EC kernels
TILE = 8  # screen tile edge for the divergence statistics (pixels)


@dataclass
class PassStats:
    """What one pass did. Arrays are per ray of the batch (row-major pixels)."""

    mode: str
    rays: int = 0  # active rays
    pairs: int = 0  # ray-cell pairs over all iterations (EC)
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

    def __init__(self, ctx: Any, grid: UniformGrid, chunk: int = 64, window: int = 1):
        from viewer.cl import build

        self.ctx, self.grid, self.chunk, self.window = ctx, grid, int(chunk), int(window)
        self.prims = grid.prims
        ivw = build(HERE / "ivw.cl", {"WG": WG_IVW}, ctx)
        ec = build(HERE / "ec.cl", {"WG": self.chunk}, ctx)
        self.k = {"ivw": clio.kernel(ivw, "ivw_trace")}
        for name in ("ec_init", "ec_count", "ec_write", "ec_process", "ec_resolve", "ec_finish"):
            self.k[name] = clio.kernel(ec, name)
        self._bufs: dict[str, Any] = {}

    def _buf(self, name: str, nbytes: int) -> Any:
        buf = self._bufs.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = new_buffer(self.ctx, self.ctx.cl.mem_flags.READ_WRITE, int(nbytes), f"voxelwalk {name}")
            self._bufs[name] = buf
        return buf

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
        self._run("ivw", n, g.header, g.cells, g.refs, tris, ray_o, ray_d, out_t, out_id, np.int32(n),
                  np.int32(bool(any_hit)), iters, first, wg=WG_IVW)
        clio.finish(q)
        ps = PassStats("ivw", trace_ms=(time.perf_counter() - t0) * 1e3)
        if stats:
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
    def trace_ec(self, tris: Any, ray_o: Any, ray_d: Any, out_t: Any, out_id: Any, n: int,
                 stats: bool = False, size: tuple[int, int] | None = None) -> PassStats:
        g, q, u = self.grid, self.ctx.queue, np.uint32
        ps = PassStats("ec")
        if n == 0:
            return ps
        keys, nxt = self._buf("keys", 8 * n), self._buf("next", 4 * n)
        iters, first = self._buf("iters", 4 * n), self._buf("first", 4 * n)
        win_exit = self._buf("win_exit", 4 * n)
        act, act2, flags = self._buf("act", 4 * n), self._buf("act2", 4 * n), self._buf("flags", 4 * n)
        t0 = time.perf_counter()
        self._run("ec_init", n, g.header, ray_o, ray_d, u(n), keys, nxt, iters)
        m = self.prims.compact(n, predicate="x != 0xffffffffu", src=nxt, dst_index=act)
        ps.rays = self._active(ray_o, ray_d, n) if stats else m
        if stats and size is not None:
            ps.first_cell = np.full(n, 0xFFFFFFFF, np.uint32)  # no active ray: no cell anywhere
        key_bits = max(1, (int(g.stats.cells) - 1).bit_length())
        limit = int(sum(g.stats.res)) + 8  # a 3D-DDA visits at most rx + ry + rz - 2 cells
        trace_s = 0.0
        it = 0
        while m:
            if it > limit:
                raise RtwalkError(f"voxelwalk EC did not converge in {limit} iterations ({m} rays left)")
            counts = self._buf("counts", 4 * m)
            self._run("ec_count", m, g.header, g.cells, ray_o, ray_d, keys, nxt, act, u(m), u(self.window), counts)
            p = self.prims.exclusive_scan(counts, counts, m)
            pk, pv = self._buf("pkeys", 4 * p), self._buf("pvals", 4 * p)
            self._run("ec_write", m, g.header, g.cells, ray_o, ray_d, keys, nxt, act, u(m), u(self.window), counts,
                      pk, pv, win_exit, first, iters)
            chunks = 0
            if p:
                self.prims.sort_pairs(pk, pv, p, key_bits=key_bits)
                from viewer.cl.primitives import Chunks

                out = Chunks(0, self._buf("ck", 4 * p), self._buf("cs", 4 * p), self._buf("cl", 4 * p))
                ch = self.prims.segments(pk, p, r=self.chunk, out=out)
                chunks = ch.count
                clio.finish(q)
                t1 = time.perf_counter()
                self.k["ec_process"](q, (chunks * self.chunk,), (self.chunk,), g.cells, g.refs, tris, ray_o, ray_d,
                                     ch.key, ch.start, ch.length, pv, keys)
                clio.finish(q)
                trace_s += time.perf_counter() - t1
                if stats and it == 0:
                    ck, _, cl_ = ch.to_numpy(self.ctx)
                    ps.rays_per_cell = np.bincount(np.searchsorted(np.unique(ck), ck), weights=cl_).astype(np.int64)
            self._run("ec_resolve", m, keys, nxt, win_exit, act, u(m), flags)
            m_next = self.prims.compact(m, flags=flags, src=act, dst=act2)
            if stats:
                row = {"active": float(m), "pairs": float(p), "workgroups": float(chunks),
                       "resolved": float(m - m_next)}
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
            ps.pairs += p
            ps.workgroups += chunks
            act, act2 = act2, act
            m = m_next
            it += 1
        self._bufs["act"], self._bufs["act2"] = act, act2
        self._run("ec_finish", n, keys, u(n), out_t, out_id)
        clio.finish(q)
        ps.iterations = it
        ps.trace_ms = trace_s * 1e3
        ps.reorder_ms = (time.perf_counter() - t0) * 1e3 - ps.trace_ms
        if stats:
            ps.iters = self._read(iters, n, np.int32)
        return ps

    def release(self) -> None:
        for buf in self._bufs.values():
            buf.release()
        self._bufs.clear()

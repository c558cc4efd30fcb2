"""Sort, scan, compaction, segments and reduce on pyopencl Buffers, shaped for a CPU device.

Each work-item owns one contiguous block of the input and walks it sequentially with private
counters (PoCL does not vectorise across work-items; streaming one block per thread is what a CPU
does fast); the few per-block totals are combined by one work-item. Work-group size is fixed
(`WG`, one PoCL compile) and the block count grows with n up to `max_blocks`.
Kernels: viewer/cl/kernels/primitives.cl. n < 2**32 - 2**16 elements.

On Buffers (results stay on the device; counts/totals come back as Python ints):
  sort_pairs(keys, vals, n, key_bits=None, temp=None)   stable LSD radix sort of uint32 keys with uint32
      values in place, 8-bit digits, ceil(key_bits / 8) passes (key_bits=None: from a max-reduce).
  exclusive_scan(src, dst, n) -> total        uint32 (wraps modulo 2**32); dst may be src.
  compact(n, flags=..., src=..., dst=..., dst_index=..., predicate=..., itemsize=4) -> count
      keeps items whose uint32 flag != 0 (or for which the C expression `predicate` in x is true),
      in order; writes the items (itemsize 4, 8 or 16 bytes) and/or their indices.
  segments(keys, n, r=None) -> Chunks         runs of equal keys in a sorted uint32 array, each cut
      into chunks of at most r: per chunk (key, start, count) -- the "get boundaries / segmented
      scan / chunks / compact" pipeline of perspective grids (thesis Fig. 4.2).
  reduce(src, n, "min"|"max", dtype) -> scalar  uint32, int32 or float32 (NaN: unspecified).
NumPy wrappers with the same names and an `_np` suffix upload, run and read back (tests, bench).

Device-count variants (`*_dev`): the element count is a uint32 in a device buffer (written by an
earlier kernel: a scan's total, a compaction's count) and `bound` >= it is known on the host; the
result count goes to a device buffer too. A chain of them runs with no host round trip (the
kernels' block ranges shrink to the device count; launches are sized for the bound):
  exclusive_scan_dev(src, dst, n_buf, bound, total_buf)
  sort_pairs_dev(keys, vals, n_buf, bound, key_bits)           (keys/vals hold >= bound items)
  compact_dev(n_buf, bound, count_buf, flags=..., src=..., dst=..., dst_index=..., predicate=...)
  segments_dev(keys, n_buf, bound, r, out, count_buf)          (out: Chunks with room for bound)
  reduce_dev(src, n, op, dtype, out)                            (n on the host; result in `out`)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

import viewer.cl.io as clio
from viewer.cl.context import ClContext, cl_context
from viewer.cl.limits import new_buffer
from viewer.cl.programs import build

WG = 16  # work-items per work-group (fixed; PoCL compiles one variant per local size)
MIN_BLOCK = 4096  # elements per block before more blocks are worth their overhead
MAX_N = 2**32 - 2**16  # block ranges are computed in uint
_RTYPES = {np.dtype(np.uint32): ("uint", 0xFFFFFFFF, 0), np.dtype(np.int32): ("int", 2**31 - 1, -(2**31)),
           np.dtype(np.float32): ("float", np.inf, -np.inf)}
_ITEMS = {4: "uint", 8: "uint2", 16: "uint4"}


@dataclass
class Chunks:
    """Chunks of the segments of a sorted key array: `count` chunks; buffers hold uint32 each
    (key, first index, length), in key order then position order. Capacity >= count."""

    count: int
    key: Any
    start: Any
    length: Any

    def to_numpy(self, ctx: ClContext | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ctx = ctx or cl_context()
        return tuple(_read(ctx, b, self.count, np.uint32) for b in (self.key, self.start, self.length))


def _read(ctx: ClContext, buf: Any, n: int, dtype: Any) -> np.ndarray:
    out = np.empty(n, dtype)
    if n:
        clio.copy(ctx.queue, out, buf)
    return out


class Primitives:
    """Kernels and scratch buffers for one context; not thread-safe (one per queue user)."""

    def __init__(self, ctx: ClContext | None = None, max_blocks: int | None = None):
        self.ctx = ctx or cl_context()
        self.max_blocks = max_blocks or min(1024, max(WG, 64 * self.ctx.compute_units))
        self.max_blocks = -(-self.max_blocks // WG) * WG
        prog = build("primitives.cl", {"WG": WG}, self.ctx)
        self._k = {name: clio.kernel(prog, name) for name in (
            "scan_small", "block_sum", "block_scan", "radix_hist", "radix_scatter", "seg_last_start",
            "seg_count_chunks", "seg_write_chunks", "seg_chunk_counts")}
        self._variants: dict[tuple, dict[str, Any]] = {}
        self._scratch: dict[str, Any] = {}

    # -- helpers ----------------------------------------------------------------------------
    def nblocks(self, n: int) -> int:
        """Blocks (= work-items) for n elements: a multiple of WG, at most max_blocks."""
        want = max(1, -(-n // MIN_BLOCK))
        return min(self.max_blocks, -(-want // WG) * WG)

    def scratch(self, name: str, nbytes: int) -> Any:
        """A device buffer of at least nbytes, reused across calls (grown when too small)."""
        buf = self._scratch.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
                del self._scratch[name]
            buf = new_buffer(self.ctx, self.ctx.cl.mem_flags.READ_WRITE, int(nbytes), f"primitives scratch {name}")
            self._scratch[name] = buf
        return buf

    def _run(self, kernel: Any, nblocks: int, *args: Any) -> None:
        kernel(self.ctx.queue, (-(-nblocks // WG) * WG,), (WG,), *args)

    def _read_u32(self, buf: Any) -> int:
        out = np.empty(1, np.uint32)
        clio.copy(self.ctx.queue, out, buf)
        return int(out[0])

    def _scan_small(self, buf: Any, m: int, total: Any) -> None:
        self._k["scan_small"](self.ctx.queue, (WG,), (WG,), buf, np.uint32(m), total)

    def _variant(self, key: tuple, defines: dict, prelude: str, names: tuple[str, ...]) -> dict[str, Any]:
        if key not in self._variants:
            prog = build("primitives.cl", {"WG": WG, **defines}, self.ctx, prelude=prelude)
            self._variants[key] = {n: clio.kernel(prog, n) for n in names}
        return self._variants[key]

    # -- exclusive scan ---------------------------------------------------------------------
    def exclusive_scan(self, src: Any, dst: Any, n: int) -> int:
        """dst[i] = src[0] + ... + src[i-1] (uint32, wrapping); returns the total (mod 2**32)."""
        if n == 0:
            return 0
        nb = self.nblocks(n)
        sums, total = self.scratch("scan_sums", 4 * nb), self.scratch("scan_total", 4)
        u = np.uint32
        self._run(self._k["block_sum"], nb, src, u(n), u(nb), sums)
        self._scan_small(sums, nb, total)
        self._run(self._k["block_scan"], nb, src, dst, u(n), u(nb), sums)
        return self._read_u32(total)

    # -- reduce -----------------------------------------------------------------------------
    def reduce(self, src: Any, n: int, op: str = "min", dtype: Any = np.uint32) -> Any:
        """Minimum or maximum of n elements of type dtype (uint32, int32, float32); n >= 1."""
        if n == 0:
            raise ValueError("reduce of an empty array")
        dt = np.dtype(dtype)
        ctype, hi, lo = _RTYPES[dt]
        ks = self._variant(("reduce", ctype, op), {"RT": ctype, "RMIN": int(op == "min")}, "",
                           ("reduce_block", "reduce_final"))
        ident = dt.type(hi if op == "min" else lo)
        nb = self.nblocks(n)
        part, out = self.scratch("reduce_part", 4 * nb), self.scratch("reduce_out", 4)
        self._run(ks["reduce_block"], nb, src, np.uint32(n), np.uint32(nb), ident, part)
        ks["reduce_final"](self.ctx.queue, (WG,), (WG,), part, np.uint32(nb), ident, out)
        res = np.empty(1, dt)
        clio.copy(self.ctx.queue, res, out)
        return res[0]

    def reduce_dev(self, src: Any, n: int, op: str, dtype: Any, out: Any) -> None:
        """reduce of n >= 1 elements into the 4-byte device buffer `out` (no read-back: several
        reductions can come back in one wait)."""
        dt = np.dtype(dtype)
        ctype, hi, lo = _RTYPES[dt]
        ks = self._variant(("reduce", ctype, op), {"RT": ctype, "RMIN": int(op == "min")}, "",
                           ("reduce_block", "reduce_final"))
        ident = dt.type(hi if op == "min" else lo)
        nb = self.nblocks(n)
        part = self.scratch(f"reduce_part_{op}_{ctype}", 4 * nb)
        self._run(ks["reduce_block"], nb, src, np.uint32(n), np.uint32(nb), ident, part)
        ks["reduce_final"](self.ctx.queue, (WG,), (WG,), part, np.uint32(nb), ident, out)

    # -- radix sort -------------------------------------------------------------------------
    def sort_pairs(self, keys: Any, vals: Any, n: int, key_bits: int | None = None,
                   temp: tuple[Any, Any] | None = None) -> None:
        """Stable sort of n uint32 (key, value) pairs by key, in place in `keys`/`vals`.

        Only ceil(key_bits / 8) digit passes run (key_bits=None: the bit length of the largest
        key, from a max-reduce); keys must be < 2**key_bits. An odd pass count ends with a copy.
        temp: two buffers of at least 4 n bytes for the other half of each pass (default: this
        object's scratch); a caller passes memory it writes later anyway, so a cold sort touches
        no fresh pages of its own (on a CPU device a fresh page costs about as much as its use)."""
        if key_bits is not None and not 0 <= key_bits <= 32:
            raise ValueError(f"key_bits must be in 0..32, not {key_bits}")
        if n > MAX_N:
            raise ValueError(f"at most {MAX_N} elements")
        if n <= 1:
            return
        if key_bits is None:
            key_bits = int(self.reduce(keys, n, "max", np.uint32)).bit_length()
        passes = -(-int(key_bits) // 8)
        if passes == 0:
            return
        nb = self.nblocks(n)
        u = np.uint32
        hist, total = self.scratch("radix_hist", 4 * 256 * nb), self.scratch("radix_total", 4)
        tk, tv = temp or (self.scratch("radix_keys", 4 * n), self.scratch("radix_vals", 4 * n))
        src, dst = (keys, vals), (tk, tv)
        for p in range(passes):
            shift = u(8 * p)
            self._run(self._k["radix_hist"], nb, src[0], u(n), u(nb), shift, hist)
            self._scan_small(hist, 256 * nb, total)
            self._run(self._k["radix_scatter"], nb, src[0], src[1], u(n), u(nb), shift, hist, dst[0], dst[1])
            src, dst = dst, src
        if src[0] is not keys:
            q = self.ctx.queue
            clio.copy(q, keys, src[0], byte_count=4 * n)
            clio.copy(q, vals, src[1], byte_count=4 * n)

    # -- compaction -------------------------------------------------------------------------
    def compact(self, n: int, flags: Any = None, src: Any = None, dst: Any = None, dst_index: Any = None,
                predicate: str | None = None, itemsize: int = 4) -> int:
        """Stream compaction, stable. Keeps element i where flags[i] != 0 (uint32 flags) or, with
        `predicate` (a C expression in `x`, e.g. "x != 0xffffffffu"), where it holds for src[i]
        (read as uint / uint2 / uint4 by itemsize). Writes kept items to dst and/or their indices
        to dst_index (either may be None); returns how many were kept."""
        if (flags is None) == (predicate is None):
            raise ValueError("compact needs exactly one of flags and predicate")
        if predicate is not None and src is None:
            raise ValueError("a predicate reads src")
        if n == 0:
            return 0
        item = _ITEMS[itemsize]
        prelude = f"inline bool rt_keep({item} x) {{ return ({predicate}); }}\n#define PRED(v) rt_keep(v)" \
            if predicate else ""
        ks = self._variant(("compact", item, predicate), {"ITEM": item}, prelude, ("compact_count", "compact_write"))
        nb = self.nblocks(n)
        counts, total = self.scratch("compact_counts", 4 * nb), self.scratch("compact_total", 4)
        dummy = self.scratch("compact_dummy", 16)
        u = np.uint32
        s, f = src if src is not None else dummy, flags if flags is not None else dummy
        self._run(ks["compact_count"], nb, s, f, u(n), u(nb), counts)
        self._scan_small(counts, nb, total)
        self._run(ks["compact_write"], nb, s, f, u(n), u(nb), counts, total, dst if dst is not None else dummy,
                  dst_index if dst_index is not None else dummy, u(dst is not None), u(dst_index is not None))
        return self._read_u32(total)

    # -- segments and chunks ----------------------------------------------------------------
    def segments(self, keys: Any, n: int, r: int | None = None, out: Chunks | None = None) -> Chunks:
        """Chunks of the runs of equal keys of a sorted uint32 array, each at most r long
        (r=None: whole segments). `out` supplies buffers with room for n chunks (else new ones)."""
        if r is not None and r < 1:
            raise ValueError("chunk length r must be >= 1")
        cl, ctx = self.ctx.cl, self.ctx
        if out is None:
            mk = [new_buffer(ctx, cl.mem_flags.READ_WRITE, 4 * n, "segments") for _ in range(3)]
            out = Chunks(0, *mk)
        if n == 0:
            out.count = 0
            return out
        rr = np.uint32(min(int(r), 0xFFFFFFFF) if r is not None else 0xFFFFFFFF)
        nb = self.nblocks(n)
        u = np.uint32
        last, counts = self.scratch("seg_last", 4 * nb), self.scratch("seg_counts", 4 * nb)
        total = self.scratch("seg_total", 4)
        self._run(self._k["seg_last_start"], nb, keys, u(n), u(nb), last)
        self._run(self._k["seg_count_chunks"], nb, keys, u(n), u(nb), rr, last, counts)
        self._scan_small(counts, nb, total)
        self._run(self._k["seg_write_chunks"], nb, keys, u(n), u(nb), rr, last, counts, out.key, out.start)
        m = self._read_u32(total)
        mb = self.nblocks(m)
        self._run(self._k["seg_chunk_counts"], mb, out.start, u(m), u(mb), u(n), out.length)
        out.count = m
        return out

    # -- device-count variants (see the module docstring) ------------------------------------
    def _ndev(self) -> dict[str, Any]:
        return self._variant(("ndev",), {"NDEV": 1}, "", (
            "block_sum", "block_scan", "radix_hist", "radix_scatter", "seg_last_start", "seg_count_chunks",
            "seg_write_chunks", "seg_chunk_counts"))

    def exclusive_scan_dev(self, src: Any, dst: Any, n_buf: Any, bound: int, total: Any) -> None:
        """exclusive_scan of the first *n_buf elements; the total goes to `total` (device)."""
        ks, nb = self._ndev(), self.nblocks(max(1, bound))
        sums = self.scratch("scan_sums", 4 * nb)
        self._run(ks["block_sum"], nb, src, n_buf, np.uint32(nb), sums)
        self._scan_small(sums, nb, total)
        self._run(ks["block_scan"], nb, src, dst, n_buf, np.uint32(nb), sums)

    def sort_pairs_dev(self, keys: Any, vals: Any, n_buf: Any, bound: int, key_bits: int) -> None:
        """sort_pairs of the first *n_buf pairs (<= bound); keys < 2**key_bits."""
        passes = -(-int(key_bits) // 8)
        if passes == 0 or bound <= 1:
            return
        ks, nb, u = self._ndev(), self.nblocks(bound), np.uint32
        hist, total = self.scratch("radix_hist", 4 * 256 * nb), self.scratch("radix_total", 4)
        tk, tv = self.scratch("radix_keys", 4 * bound), self.scratch("radix_vals", 4 * bound)
        src, dst = (keys, vals), (tk, tv)
        for p in range(passes):
            shift = u(8 * p)
            self._run(ks["radix_hist"], nb, src[0], n_buf, u(nb), shift, hist)
            self._scan_small(hist, 256 * nb, total)
            self._run(ks["radix_scatter"], nb, src[0], src[1], n_buf, u(nb), shift, hist, dst[0], dst[1])
            src, dst = dst, src
        if src[0] is not keys:
            q = self.ctx.queue
            clio.copy(q, keys, src[0], byte_count=4 * bound)
            clio.copy(q, vals, src[1], byte_count=4 * bound)

    def compact_dev(self, n_buf: Any, bound: int, count: Any, flags: Any = None, src: Any = None, dst: Any = None,
                    dst_index: Any = None, predicate: str | None = None, itemsize: int = 4) -> None:
        """compact of the first *n_buf elements (<= bound); the kept count goes to `count` (device,
        not n_buf: the write kernel still reads n)."""
        if (flags is None) == (predicate is None):
            raise ValueError("compact needs exactly one of flags and predicate")
        item = _ITEMS[itemsize]
        prelude = f"inline bool rt_keep({item} x) {{ return ({predicate}); }}\n#define PRED(v) rt_keep(v)" \
            if predicate else ""
        ks = self._variant(("compact", item, predicate, "ndev"), {"ITEM": item, "NDEV": 1}, prelude,
                           ("compact_count", "compact_write"))
        nb = self.nblocks(max(1, bound))
        counts, dummy = self.scratch("compact_counts", 4 * nb), self.scratch("compact_dummy", 16)
        u = np.uint32
        s, f = src if src is not None else dummy, flags if flags is not None else dummy
        self._run(ks["compact_count"], nb, s, f, n_buf, u(nb), counts)
        self._scan_small(counts, nb, count)
        self._run(ks["compact_write"], nb, s, f, n_buf, u(nb), counts, count, dst if dst is not None else dummy,
                  dst_index if dst_index is not None else dummy, u(dst is not None), u(dst_index is not None))

    def segments_dev(self, keys: Any, n_buf: Any, bound: int, r: int | None, out: Chunks, count: Any) -> Chunks:
        """segments of the first *n_buf sorted keys (<= bound); the chunk count goes to `count`
        (device; out.count is left at the bound)."""
        ks, nb, u = self._ndev(), self.nblocks(max(1, bound)), np.uint32
        rr = u(min(int(r), 0xFFFFFFFF) if r is not None else 0xFFFFFFFF)
        last, counts = self.scratch("seg_last", 4 * nb), self.scratch("seg_counts", 4 * nb)
        self._run(ks["seg_last_start"], nb, keys, n_buf, u(nb), last)
        self._run(ks["seg_count_chunks"], nb, keys, n_buf, u(nb), rr, last, counts)
        self._scan_small(counts, nb, count)
        self._run(ks["seg_write_chunks"], nb, keys, n_buf, u(nb), rr, last, counts, out.key, out.start)
        self._run(ks["seg_chunk_counts"], nb, out.start, count, u(nb), n_buf, out.length)
        out.count = int(bound)
        return out

    def release(self) -> None:
        """Free the scratch buffers (a 10M-pair sort keeps 80 MB of them for the next call)."""
        for buf in self._scratch.values():
            buf.release()
        self._scratch.clear()

    # -- warm-up ----------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Run every kernel once on a small input (PoCL compiles per kernel and local size)."""
        k = np.arange(5000, dtype=np.uint32)[::-1].copy()
        sort_pairs_np(k, k, prims=self)
        exclusive_scan_np(k, prims=self)
        compact_np(k, k & 1, prims=self)
        segments_np(np.sort(k // 3), 2, prims=self)
        reduce_np(k, "min", prims=self)
        self.ctx.finish()


_default: dict[int, Primitives] = {}


def primitives(ctx: ClContext | None = None) -> Primitives:
    """The shared Primitives for a context (the default context when None)."""
    ctx = ctx or cl_context()
    key = id(ctx)
    if key not in _default:
        _default[key] = Primitives(ctx)
    return _default[key]


# -- NumPy wrappers -------------------------------------------------------------------------
def _upload(p: Primitives, a: np.ndarray) -> Any:
    cl = p.ctx.cl
    a = np.ascontiguousarray(a)
    if a.nbytes == 0:
        return cl.Buffer(p.ctx.context, cl.mem_flags.READ_WRITE, 16)
    return clio.upload(p.ctx, a, cl.mem_flags.READ_WRITE)


def sort_pairs_np(keys: np.ndarray, vals: np.ndarray, key_bits: int | None = None,
                  prims: Primitives | None = None) -> tuple[np.ndarray, np.ndarray]:
    p = prims or primitives()
    keys, vals = np.asarray(keys, np.uint32), np.asarray(vals, np.uint32)
    assert keys.shape == vals.shape and keys.ndim == 1
    n = keys.size
    kb, vb = _upload(p, keys), _upload(p, vals)
    p.sort_pairs(kb, vb, n, key_bits)
    return _read(p.ctx, kb, n, np.uint32), _read(p.ctx, vb, n, np.uint32)


def exclusive_scan_np(a: np.ndarray, prims: Primitives | None = None) -> tuple[np.ndarray, int]:
    p = prims or primitives()
    a = np.asarray(a, np.uint32)
    b = _upload(p, a)
    total = p.exclusive_scan(b, b, a.size)
    return _read(p.ctx, b, a.size, np.uint32), total


def compact_np(values: np.ndarray, flags: np.ndarray | None = None, predicate: str | None = None,
               prims: Primitives | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(kept values, their indices). values: 1-D uint32, or (n, 2) / (n, 4) uint32/float32 rows."""
    p = prims or primitives()
    values = np.ascontiguousarray(values)
    n = values.shape[0]
    itemsize = values.itemsize * (values.shape[1] if values.ndim == 2 else 1)
    vb = _upload(p, values)
    fb = _upload(p, np.asarray(flags, np.uint32)) if flags is not None else None
    cl = p.ctx.cl
    db = cl.Buffer(p.ctx.context, cl.mem_flags.READ_WRITE, max(16, values.nbytes))
    ib = cl.Buffer(p.ctx.context, cl.mem_flags.READ_WRITE, max(16, 4 * n))
    m = p.compact(n, flags=fb, src=vb, dst=db, dst_index=ib, predicate=predicate, itemsize=itemsize)
    out = np.empty((m, *values.shape[1:]), values.dtype)
    if m:
        clio.copy(p.ctx.queue, out, db)
    return out, _read(p.ctx, ib, m, np.uint32)


def segments_np(sorted_keys: np.ndarray, r: int | None = None,
                prims: Primitives | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(chunk key, chunk start, chunk length) arrays."""
    p = prims or primitives()
    k = np.asarray(sorted_keys, np.uint32)
    return p.segments(_upload(p, k), k.size, r).to_numpy(p.ctx)


def reduce_np(a: np.ndarray, op: str = "min", prims: Primitives | None = None) -> Any:
    p = prims or primitives()
    a = np.ascontiguousarray(a)
    return p.reduce(_upload(p, a), a.size, op, a.dtype)

/* Data-parallel primitives shaped for a CPU OpenCL device (viewer/cl/primitives.py).
 *
 * PoCL runs the work-items of a work-group as a loop and does not vectorise it, so each
 * work-item owns one contiguous block of the input (rt_block_range) and walks it sequentially
 * with private counters: memory is streamed, no atomics, no barriers. `nblocks` work-items run in
 * work-groups of WG (fixed: each new local size costs PoCL another compile).
 * Defines: WG; ITEM (the element type moved by compaction: uint, uint2 or uint4);
 * RT (reduce type) and RMIN (1: min, 0: max); PRED(x) (compaction predicate, via the prelude). */

#include "common.cl"

#ifndef WG
#define WG 16
#endif
#define WG_ATTR __attribute__((reqd_work_group_size(WG, 1, 1)))

/* NDEV: element counts are read from device memory (a count an earlier kernel wrote: a scan's
 * total, a compaction's count) instead of passed by value, so a chain of primitives runs with no
 * host round trip; the host launches `nblocks` for an upper bound and the blocks' ranges shrink
 * to the count on the device. */
#ifdef NDEV
#define NARG(name) __global const uint *name##_ptr
#define NGET(name) const uint name = *name##_ptr
#else
#define NARG(name) uint name
#define NGET(name)
#endif

/* ---- scans over small arrays (per-block totals): one work-item ------------------------- */

/* In-place exclusive scan of a[0..m); *total = sum. */
__kernel WG_ATTR void scan_small(__global uint *a, uint m, __global uint *total) {
    if (get_global_id(0) != 0) return;
    uint run = 0;
    for (uint i = 0; i < m; ++i) { uint v = a[i]; a[i] = run; run += v; }
    *total = run;
}

/* ---- exclusive scan -------------------------------------------------------------------- */

__kernel WG_ATTR void block_sum(__global const uint *src, NARG(n), uint nblocks, __global uint *sums) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint4 s4 = (uint4)(0);
    uint i = r.x;
    for (; i + 4 <= r.y; i += 4) s4 += vload4(0, src + i);
    uint s = s4.x + s4.y + s4.z + s4.w;
    for (; i < r.y; ++i) s += src[i];
    sums[b] = s;
}

/* dst may alias src: each element is read before it is written, by the same work-item. Four
 * elements at a time with an in-register prefix sum (shortens the serial add chain). */
__kernel WG_ATTR void block_scan(__global const uint *src, __global uint *dst, NARG(n), uint nblocks,
                                 __global const uint *offsets) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint run = offsets[b];
    uint i = r.x;
    for (; i + 4 <= r.y; i += 4) {
        uint4 v = vload4(0, src + i);
        uint4 e = (uint4)(0u, v.x, v.x + v.y, v.x + v.y + v.z);
        vstore4(e + run, 0, dst + i);
        run += e.w + v.w;
    }
    for (; i < r.y; ++i) { uint v = src[i]; dst[i] = run; run += v; }
}

/* ---- LSD radix sort, 8-bit digits ------------------------------------------------------- */

/* hist[d * nblocks + b] = number of keys in block b whose digit at `shift` is d: scanned in this
 * digit-major order the counts give each (digit, block) its first output slot, which keeps the
 * sort stable. */
__kernel WG_ATTR void radix_hist(__global const uint *keys, NARG(n), uint nblocks, uint shift,
                                 __global uint *hist) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint h[256];
    for (uint d = 0; d < 256; ++d) h[d] = 0;
    for (uint i = r.x; i < r.y; ++i) h[(keys[i] >> shift) & 255u]++;
    for (uint d = 0; d < 256; ++d) hist[d * nblocks + b] = h[d];
}

__kernel WG_ATTR void radix_scatter(__global const uint *keys, __global const uint *vals, NARG(n), uint nblocks,
                                    uint shift, __global const uint *offsets,
                                    __global uint *keys_out, __global uint *vals_out) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint o[256];
    for (uint d = 0; d < 256; ++d) o[d] = offsets[d * nblocks + b];
    for (uint i = r.x; i < r.y; ++i) {
        uint k = keys[i];
        uint p = o[(k >> shift) & 255u]++;
        keys_out[p] = k;
        vals_out[p] = vals[i];
    }
}

/* ---- stream compaction ----------------------------------------------------------------- */

#ifdef PRED
#define KEEP(i) (PRED(src[i]))
#else
#define KEEP(i) (flags[i] != 0u)
#endif
#ifndef ITEM
#define ITEM uint
#endif

__kernel WG_ATTR void compact_count(__global const ITEM *src, __global const uint *flags, NARG(n), uint nblocks,
                                    __global uint *counts) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint c = 0;
    for (uint i = r.x; i < r.y; ++i) c += KEEP(i) ? 1u : 0u;
    counts[b] = c;
}

/* Writes kept items (write_items) and/or their indices (write_index) from offsets[b] on. Every
 * element is written to slot o (the next free one) and o advances only when it is kept: no
 * data-dependent branch, so a random mask costs no mispredictions. Slots up to the block's end
 * (the next block's offset) only, which keeps blocks from overwriting each other. */
__kernel WG_ATTR void compact_write(__global const ITEM *src, __global const uint *flags, NARG(n), uint nblocks,
                                    __global const uint *offsets, __global const uint *total,
                                    __global ITEM *dst, __global uint *dst_index,
                                    uint write_items, uint write_index) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    uint o = offsets[b], end = b + 1 < nblocks ? offsets[b + 1] : *total;
    if (write_items && write_index) {
        for (uint i = r.x; i < r.y && o < end; ++i) { dst[o] = src[i]; dst_index[o] = i; o += KEEP(i) ? 1u : 0u; }
    } else if (write_items) {
        for (uint i = r.x; i < r.y && o < end; ++i) { dst[o] = src[i]; o += KEEP(i) ? 1u : 0u; }
    } else if (write_index) {
        for (uint i = r.x; i < r.y && o < end; ++i) { dst_index[o] = i; o += KEEP(i) ? 1u : 0u; }
    }
}

/* ---- segments of a sorted key array, chunked to at most r elements ---------------------- */

/* last[b] = the last segment start (i == 0 or key[i] != key[i-1]) in block b, or -1. */
__kernel WG_ATTR void seg_last_start(__global const uint *keys, NARG(n), uint nblocks, __global int *last) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 r = rt_block_range(n, b, nblocks);
    int l = -1;
    for (uint i = r.x; i < r.y; ++i)
        if (i == 0 || keys[i] != keys[i - 1]) l = (int)i;
    last[b] = l;
}

/* The segment start in effect at the first element of block b: the latest start in an earlier
 * block (a max-scan over `last`, done by each work-item: nblocks is small). */
inline uint seg_incoming(__global const int *last, uint b) {
    int s = 0;
    for (uint j = 0; j < b; ++j) s = max(s, last[j]);
    return (uint)s;
}

/* A chunk starts where a segment starts and every r elements after that. */
#define CHUNK_START(i) ((i) == seg || ((i) - seg) % r == 0u)

__kernel WG_ATTR void seg_count_chunks(__global const uint *keys, NARG(n), uint nblocks, uint r,
                                       __global const int *last, __global uint *counts) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 rg = rt_block_range(n, b, nblocks);
    uint seg = seg_incoming(last, b), c = 0;
    for (uint i = rg.x; i < rg.y; ++i) {
        if (i == 0 || keys[i] != keys[i - 1]) seg = i;
        c += CHUNK_START(i) ? 1u : 0u;
    }
    counts[b] = c;
}

__kernel WG_ATTR void seg_write_chunks(__global const uint *keys, NARG(n), uint nblocks, uint r,
                                       __global const int *last, __global const uint *offsets,
                                       __global uint *chunk_key, __global uint *chunk_start) {
    NGET(n);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 rg = rt_block_range(n, b, nblocks);
    uint seg = seg_incoming(last, b), o = offsets[b];
    for (uint i = rg.x; i < rg.y; ++i) {
        if (i == 0 || keys[i] != keys[i - 1]) seg = i;
        if (CHUNK_START(i)) { chunk_key[o] = keys[i]; chunk_start[o] = i; ++o; }
    }
}

/* count[c] = start[c+1] - start[c] (chunks tile [0, n)); one work-item per block of chunks. */
__kernel WG_ATTR void seg_chunk_counts(__global const uint *chunk_start, NARG(m), uint nblocks, NARG(n),
                                       __global uint *chunk_count) {
    NGET(n);
    NGET(m);
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 rg = rt_block_range(m, b, nblocks);
    for (uint c = rg.x; c < rg.y; ++c)
        chunk_count[c] = (c + 1 < m ? chunk_start[c + 1] : n) - chunk_start[c];
}

/* ---- min / max reduce ------------------------------------------------------------------ */

#ifndef RT
#define RT uint
#endif
#ifndef RMIN
#define RMIN 1
#endif
#if RMIN
#define ROP(a, b) min(a, b)
#else
#define ROP(a, b) max(a, b)
#endif

/* partial[b] = reduction of block b; empty blocks write `ident`. */
__kernel WG_ATTR void reduce_block(__global const RT *src, uint n, uint nblocks, RT ident, __global RT *partial) {
    uint b = get_global_id(0);
    if (b >= nblocks) return;
    uint2 rg = rt_block_range(n, b, nblocks);
    RT a = ident;
    for (uint i = rg.x; i < rg.y; ++i) a = ROP(a, src[i]);
    partial[b] = a;
}

__kernel WG_ATTR void reduce_final(__global const RT *partial, uint nblocks, RT ident, __global RT *out) {
    if (get_global_id(0) != 0) return;
    RT a = ident;
    for (uint j = 0; j < nblocks; ++j) a = ROP(a, partial[j]);
    *out = a;
}

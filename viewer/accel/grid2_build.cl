// Two-level grid build (Kalojanov, Billeter & Slusallek 2011), after the top-level uniform grid
// (grid_build.cl) and from its sorted pairs; layout and walk: viewer/cl/kernels/grid2.cl.
//
// A pair (top cell, triangle) of a dense cell is "big" when the triangle's box spans at least
// BIG_FRAC top cells on some axis (ground under a small object, a wall behind it): kept in the
// cell's big list. The others are "small": the cell's sub-grid is fitted to the union of their
// boxes (each spans < BIG_FRAC cells, so the union reaches at most that far past the cell) and
// sized from their count. Only cells with at least `min_small` small triangles get a sub-grid.
#include "grid2.cl"

#ifndef WG
#define WG 64
#endif

// 2: big, 1: small; the triangle's box in *mn, *mx (world).
inline int g2_classify(const Grid *g, __global const float4 *tris, uint t, float big_frac, float3 *mn, float3 *mx) {
    float3 a = tris[3 * t].xyz, b = tris[3 * t + 1].xyz, c = tris[3 * t + 2].xyz;
    *mn = fmin(fmin(a, b), c);
    *mx = fmax(fmax(a, b), c);
    float3 span = (*mx - *mn) * g->inv.xyz;
    return (span.x >= big_frac || span.y >= big_frac || span.z >= big_frac) ? 2 : 1;
}

// Small triangles of top cell c and the union of their boxes.
inline uint g2_small(const Grid *g, uint2 cr, __global const uint *refs, __global const float4 *tris, float big_frac,
                     float3 *umn, float3 *umx) {
    uint n = 0;
    *umn = (float3)(INFINITY);
    *umx = (float3)(-INFINITY);
    for (uint k = 0; k < cr.y; ++k) {
        float3 mn, mx;
        if (g2_classify(g, tris, refs[cr.x + k], big_frac, &mn, &mx) == 1) {
            ++n;
            *umn = fmin(*umn, mn);
            *umx = fmax(*umx, mx);
        }
    }
    return n;
}

// flags[c] = 1 when top cell c gets a sub-grid.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_flags(__global const Grid *grid, __global const uint2 *cells, __global const uint *refs,
              __global const float4 *tris, const uint ncells, const uint min_small, const float big_frac,
              __global uint *flags) {
    uint c = get_global_id(0);
    if (c >= ncells) return;
    uint2 cr = cells[c];
    uint f = 0;
    if (cr.y >= min_small) {
        Grid g = *grid;
        float3 umn, umx;
        f = g2_small(&g, cr, refs, tris, big_frac, &umn, &umx) >= min_small ? 1u : 0u;
    }
    flags[c] = f;
}

inline float g2_ulp(float x) {
    return nextafter(x, INFINITY) - x;
}

// Sub-grid records: box padded as the host pads the top grid's (viewer.accel.grid._padded_extent,
// relative to the extent only), resolution ~density cells per small triangle shaped like the box
// (each axis in [1, max_axis], at most max_cells). sub_of[c] = the sub-grid of top cell c or -1;
// nsubc[s] = its cell count. `subidx` is the exclusive scan of the flags.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_setup(__global const Grid *grid, __global const uint2 *cells, __global const uint *refs,
              __global const float4 *tris, const uint ncells, const uint min_small, const float big_frac,
              const float density, const int max_axis, const uint max_cells, __global const uint *flags,
              __global const uint *subidx, __global int *sub_of, __global SubGrid *subs, __global uint *nsubc) {
    uint c = get_global_id(0);
    if (c >= ncells) return;
    if (!flags[c]) {
        sub_of[c] = -1;
        return;
    }
    uint s = subidx[c];
    sub_of[c] = (int)s;
    Grid g = *grid;
    float3 umn, umx;
    uint n = g2_small(&g, cells[c], refs, tris, big_frac, &umn, &umx);
    float3 ext = umx - umn;
    float big = fmax(fmax(ext.x, ext.y), ext.z);
    float3 amn = fabs(umn), amx = fabs(umx);
    float mag = fmax(fmax(fmax(amn.x, amn.y), amn.z), fmax(fmax(amx.x, amx.y), amx.z));
    big = fmax(fmax(big, 1e-30f), 1e-6f * mag);
    if (mag < 1.0f) big = fmax(big, 1e-6f);
    float pad = 1e-5f * big;
    float3 grow = fmax((float3)(1e-3f * big) - ext, (float3)(0.0f)) * 0.5f;
    float3 lo = umn - (pad + grow), hi = umx + (pad + grow);
    lo = (float3)(nextafter(lo.x, -INFINITY), nextafter(lo.y, -INFINITY), nextafter(lo.z, -INFINITY));
    hi = (float3)(nextafter(hi.x, INFINITY), nextafter(hi.y, INFINITY), nextafter(hi.z, INFINITY));
    float3 e = hi - lo;
    e = (float3)(nextafter(e.x, INFINITY), nextafter(e.y, INFINITY), nextafter(e.z, INFINITY));
    float emax = fmax(fmax(e.x, e.y), e.z);
    float3 en = e / emax;  // (0, 1]: the shape, free of the box's magnitude
    float k = cbrt(density * (float)n / (en.x * en.y * en.z));
    int3 res = clamp(convert_int3(ceil(en * k)), 1, max_axis);
    while ((ulong)res.x * (ulong)res.y * (ulong)res.z > (ulong)max_cells)
        res = max(convert_int3(floor(convert_float3(res) * 0.9f)), (int3)(1));
    float3 cell = e / convert_float3(res);
    cell = (float3)(nextafter(cell.x, INFINITY), nextafter(cell.y, INFINITY), nextafter(cell.z, INFINITY));
    SubGrid sg;
    sg.lo = (float4)(lo, 1e-3f + 32.0f * g2_ulp(emax) / fmin(fmin(cell.x, cell.y), cell.z));
    sg.cell = (float4)(cell, 0.0f);
    sg.res = (int4)(res, 0);
    sg.big = (uint4)(0);
    subs[s] = sg;
    nsubc[s] = (uint)(res.x * res.y * res.z);
}

// Sub-cell range [c0, c1] of a small triangle's box (grown by eps sub-cells, clipped).
inline bool g2_range(const SubGrid *s, float3 mn, float3 mx, int3 *c0, int3 *c1) {
    float3 inv = 1.0f / s->cell.xyz;
    float3 lo = (mn - s->lo.xyz) * inv - s->lo.w;
    float3 hi = (mx - s->lo.xyz) * inv + s->lo.w;
    float3 res = convert_float3(s->res.xyz);
    if (hi.x < 0.0f || hi.y < 0.0f || hi.z < 0.0f || lo.x >= res.x || lo.y >= res.y || lo.z >= res.z) return false;
    float3 top = res - 1.0f;
    *c0 = convert_int3(fmin(fmax(floor(lo), (float3)(0.0f)), top));
    *c1 = convert_int3(fmin(fmax(floor(hi), (float3)(0.0f)), top));
    return true;
}

// Per top-level pair: sub-cell pairs of a small triangle (cnt), 1 for a big one (bigf).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_pair_count(__global const Grid *grid, __global const uint *keys, __global const uint *vals,
                   __global const float4 *tris, __global const uint *np, __global const int *sub_of,
                   __global const SubGrid *subs, const float big_frac, __global uint *cnt, __global uint *bigf) {
    uint i = get_global_id(0);
    if (i >= *np) return;  // the pair count on the device (launched for a bound)
    int s = sub_of[keys[i]];
    uint nc = 0, nb = 0;
    if (s >= 0) {
        Grid g = *grid;
        float3 mn, mx;
        if (g2_classify(&g, tris, vals[i], big_frac, &mn, &mx) == 2) {
            nb = 1;
        } else {
            SubGrid sg = subs[s];
            int3 c0, c1;
            if (g2_range(&sg, mn, mx, &c0, &c1)) {
                int3 e = c1 - c0 + 1;
                nc = (uint)e.x * (uint)e.y * (uint)e.z;
            }
        }
    }
    cnt[i] = nc;
    bigf[i] = nb;
}

// Writes the sub-cell pairs (key: global sub-cell id) and the big lists' triangles.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_pair_write(__global const Grid *grid, __global const uint *keys, __global const uint *vals,
                   __global const float4 *tris, __global const uint *np, __global const int *sub_of,
                   __global const SubGrid *subs, __global const uint *sub_base, const float big_frac,
                   __global const uint *off, __global const uint *bigoff, __global uint *keys2,
                   __global uint *vals2, __global uint *bigrefs) {
    uint i = get_global_id(0);
    if (i >= *np) return;
    int s = sub_of[keys[i]];
    if (s < 0) return;
    Grid g = *grid;
    uint t = vals[i];
    float3 mn, mx;
    if (g2_classify(&g, tris, t, big_frac, &mn, &mx) == 2) {
        bigrefs[bigoff[i]] = t;
        return;
    }
    SubGrid sg = subs[s];
    sg.res.w = (int)sub_base[s];
    int3 c0, c1;
    if (!g2_range(&sg, mn, mx, &c0, &c1)) return;
    uint o = off[i];
    for (int z = c0.z; z <= c1.z; ++z)
        for (int y = c0.y; y <= c1.y; ++y)
            for (int x = c0.x; x <= c1.x; ++x) {
                keys2[o] = (uint)g2_cell_id(&sg, (int3)(x, y, z));
                vals2[o] = t;
                ++o;
            }
}

// The big list of each sub-grid: (first, count) in bigrefs (the big pairs of a top cell are
// consecutive: the top pairs are sorted by cell and the scan is in pair order).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_big_ranges(__global const uint2 *cells, __global const int *sub_of, __global const uint *bigoff,
                   __global const uint *big_total, __global const uint *np, const uint ncells,
                   __global uint2 *bigcells) {
    uint c = get_global_id(0);
    if (c >= ncells) return;
    int s = sub_of[c];
    if (s < 0) return;
    uint2 cr = cells[c];
    uint start = bigoff[cr.x];
    uint end = cr.x + cr.y < *np ? bigoff[cr.x + cr.y] : *big_total;
    bigcells[s] = (uint2)(start, end - start);
}

// Final records: first sub-cell id and the big list's blocks.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void g2_finish(__global SubGrid *subs, __global const uint *sub_base, __global const uint *big_start,
               __global const uint2 *bigcells, const uint nsub) {
    uint s = get_global_id(0);
    if (s >= nsub) return;
    subs[s].res.w = (int)sub_base[s];
    subs[s].big = (uint4)(big_start[s], bigcells[s].y, 0u, 0u);
}

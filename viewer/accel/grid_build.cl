// Uniform grid build (Kalojanov & Slusallek 2009): triangle-cell pairs counted per triangle,
// offsets by an exclusive scan, pairs written, radix-sorted by cell (viewer/cl/primitives.py),
// cell ranges from the segment boundaries of the sorted keys. Layout: grid.cl.
//
// Binning is triangle/cell: a triangle goes to every cell whose box, grown by eps cells per axis,
// it meets. Row by row: the triangle is clipped to each z slab of its box (Sutherland-Hodgman,
// at most 7 vertices), the slab's polygon gives the y rows it reaches, and the polygon's part in
// each row gives the row's x span (the vertices inside the row and the edges' crossings of its
// two planes are the clipped polygon's vertices, so the span is exact). The work is the cells
// written plus the rows and slabs crossed, so a long diagonal triangle costs its cells, not its
// bounding box's (box binning gave a 62,832-needle disk 74 M pairs, 4.7 GB). Rounding in the
// clip is a few ulps of the local cell coordinates, well inside eps (grid.py). Triangles with a
// non-finite vertex or two equal vertices are not binned (they can never be hit). Triangles: 3 float4 per slot (v0,
// v1, v2; w unused).
#include "grid.cl"

#ifndef WG
#define WG 64
#endif

#define CLIP_MAX 8  // a triangle clipped by two planes has at most 5 vertices; 8 leaves room

// Cell range [c0, c1] (inclusive) of triangle i's grown box and its vertices in cell units
// (local coordinates); false when it is not binned.
inline bool tri_cell_range(const Grid *g, __global const float4 *tris, uint i, float3 q[3], int3 *c0, int3 *c1) {
    float3 a = tris[3 * i].xyz, b = tris[3 * i + 1].xyz, c = tris[3 * i + 2].xyz;
    // fmin/fmax drop NaN operands: test the vertices themselves
    if (!(all(isfinite(a)) && all(isfinite(b)) && all(isfinite(c)))) return false;
    if (rt_two_equal_vertices(a, b, c)) return false;  // never hit (geometry.cl)
    q[0] = (a - g->lo.xyz) * g->inv.xyz;
    q[1] = (b - g->lo.xyz) * g->inv.xyz;
    q[2] = (c - g->lo.xyz) * g->inv.xyz;
    float3 lo = fmin(fmin(q[0], q[1]), q[2]) - g->eps.xyz;
    float3 hi = fmax(fmax(q[0], q[1]), q[2]) + g->eps.xyz;
    float3 res = convert_float3(g->res.xyz);
    if (hi.x < 0.0f || hi.y < 0.0f || hi.z < 0.0f || lo.x >= res.x || lo.y >= res.y || lo.z >= res.z) return false;
    float3 top = res - 1.0f;
    *c0 = convert_int3(fmin(fmax(floor(lo), (float3)(0.0f)), top));
    *c1 = convert_int3(fmin(fmax(floor(hi), (float3)(0.0f)), top));
    return true;
}

// The part of convex polygon p (n vertices) with s * (z - plane) >= 0, into out; its vertex count.
inline int clip_z_plane(const float3 *p, int n, float3 *out, float plane, float s) {
    int m = 0;
    for (int k = 0; k < n; ++k) {
        float3 a = p[k], b = p[k + 1 < n ? k + 1 : 0];
        float da = s * (a.z - plane), db = s * (b.z - plane);
        if (da >= 0.0f) out[m++] = a;
        if ((da >= 0.0f) != (db >= 0.0f)) out[m++] = a + (da / (da - db)) * (b - a);  // signs differ: no 0/0
    }
    return m;
}

// Triangle q clipped to the z slab [zlo, zhi] (into out); its vertex count (0: it misses the slab).
inline int clip_z_slab(const float3 q[3], float zlo, float zhi, float3 *out) {
    float3 mid[CLIP_MAX];
    int m = clip_z_plane(q, 3, mid, zlo, 1.0f);
    return m ? clip_z_plane(mid, m, out, zhi, -1.0f) : 0;
}

// x extent [*x0, *x1] of convex polygon p's part with ylo <= y <= yhi; false when there is none.
inline bool row_x_extent(const float3 *p, int n, float ylo, float yhi, float *x0, float *x1) {
    float mn = INFINITY, mx = -INFINITY;
    for (int k = 0; k < n; ++k) {
        float3 a = p[k], b = p[k + 1 < n ? k + 1 : 0];
        if (a.y >= ylo && a.y <= yhi) {
            mn = fmin(mn, a.x);
            mx = fmax(mx, a.x);
        }
        for (int side = 0; side < 2; ++side) {
            float plane = side ? yhi : ylo;
            float da = a.y - plane, db = b.y - plane;
            if ((da < 0.0f && db > 0.0f) || (da > 0.0f && db < 0.0f)) {
                float x = a.x + (da / (da - db)) * (b.x - a.x);
                mn = fmin(mn, x);
                mx = fmax(mx, x);
            }
        }
    }
    *x0 = mn;
    *x1 = mx;
    return mn <= mx;
}

// The first and last cell index (clamped to [c0, c1]) of the grown cells that interval [v0, v1]
// (cell units) meets along one axis.
inline int2 cell_span(float v0, float v1, float eps, int c0, int c1) {
    float lo = fmax(floor(v0 - eps), (float)c0), hi = fmin(floor(v1 + eps), (float)c1);
    return (int2)((int)lo, (int)hi);
}

// Visits the cells triangle i is binned to, row by row: BODY runs once per row with x0, x1 (the
// row's first and last cell), y and z set. Shared by the count and the write kernel, so both
// see the very same cells.
#define FOR_EACH_TRIANGLE_ROW(g, q, c0, c1, BODY)                                                     \
    for (int z = (c0).z; z <= (c1).z; ++z) {                                                         \
        float3 slab[CLIP_MAX];                                                                       \
        int m = clip_z_slab(q, (float)z - (g).eps.z, (float)(z + 1) + (g).eps.z, slab);              \
        if (m == 0) continue;                                                                        \
        float ymn = slab[0].y, ymx = slab[0].y;                                                      \
        for (int k = 1; k < m; ++k) { ymn = fmin(ymn, slab[k].y); ymx = fmax(ymx, slab[k].y); }      \
        int2 ys = cell_span(ymn, ymx, (g).eps.y, (c0).y, (c1).y);                                    \
        for (int y = ys.x; y <= ys.y; ++y) {                                                         \
            float xa, xb;                                                                            \
            if (!row_x_extent(slab, m, (float)y - (g).eps.y, (float)(y + 1) + (g).eps.y, &xa, &xb)) continue; \
            int2 xs = cell_span(xa, xb, (g).eps.x, (c0).x, (c1).x);                                  \
            int x0 = xs.x, x1 = xs.y;                                                                \
            if (x0 > x1) continue;                                                                   \
            BODY                                                                                     \
        }                                                                                            \
    }

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_count(__global const Grid *grid, __global const float4 *tris, const uint n, __global uint *counts) {
    uint i = get_global_id(0);
    if (i >= n) return;
    Grid g = *grid;
    float3 q[3];
    int3 c0, c1;
    uint cnt = 0;
    if (tri_cell_range(&g, tris, i, q, &c0, &c1)) {
        FOR_EACH_TRIANGLE_ROW(g, q, c0, c1, { cnt += (uint)(x1 - x0 + 1); })
    }
    counts[i] = cnt;
}

// Pairs past `cap` (the buffers' room, when sized from the last build) are not written: the host
// sees the total exceed it and builds again with exact buffers.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_write(__global const Grid *grid, __global const float4 *tris, const uint n, __global const uint *offsets,
                __global uint *keys, __global uint *vals, const uint cap) {
    uint i = get_global_id(0);
    if (i >= n) return;
    Grid g = *grid;
    float3 q[3];
    int3 c0, c1;
    if (!tri_cell_range(&g, tris, i, q, &c0, &c1)) return;
    uint o = offsets[i];
    FOR_EACH_TRIANGLE_ROW(g, q, c0, c1, {
        for (int x = x0; x <= x1; ++x) {
            if (o >= cap) return;
            keys[o] = (uint)grid_cell_id(&g, (int3)(x, y, z));
            vals[o] = i;
            ++o;
        }
    })
}

// n_out = min(total, cap): the pairs a build sized from the last one sorts.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_clamp(__global const uint *total, const uint cap, __global uint *n_out) {
    if (get_global_id(0) == 0) *n_out = min(*total, cap);
}

// Cell ranges from the segments of the sorted keys (one chunk per non-empty cell).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_ranges(__global const uint *seg_key, __global const uint *seg_start, __global const uint *seg_len,
                 __global const uint *m_ptr, __global uint2 *cells) {
    uint i = get_global_id(0);
    if (i >= *m_ptr) return;  // the segment count, on the device (launched for a bound)
    cells[seg_key[i]] = (uint2)(seg_start[i], seg_len[i]);
}

// Blocks per cell for the walkers' four-wide test: nblocks[c] = ceil(count / 4).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_block_counts(__global const uint2 *cells, const uint ncells, __global uint *nblocks) {
    uint c = get_global_id(0);
    if (c >= ncells) return;
    nblocks[c] = (cells[c].y + 3u) >> 2;
}

// The triangles of each cell four at a time in SoA form (GRID_BLOCK_DTYPE in grid.py): rows
// v0x, v0y, v0z, v1x, v1y, v1z, v2x, v2y, v2z (one lane per triangle, NaN padding), then the
// four triangle slots (-1 padding). Cell c's blocks start at block_start[c].
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_blocks(__global const uint2 *cells, __global const uint *block_start, __global const uint *refs,
                 __global const float4 *tris, const uint ncells, __global float4 *blocks) {
    uint c = get_global_id(0);
    if (c >= ncells) return;
    uint2 cr = cells[c];
    uint b0 = block_start[c];
    uint nb = (cr.y + 3u) >> 2;
    for (uint b = 0; b < nb; ++b) {
        float v[9][4];
        int slots[4];
        for (int lane = 0; lane < 4; ++lane) {
            uint k = 4u * b + (uint)lane;
            if (k < cr.y) {
                uint slot = refs[cr.x + k];
                slots[lane] = (int)slot;
                for (int vi = 0; vi < 3; ++vi) {
                    float4 p = tris[3 * slot + vi];
                    v[3 * vi][lane] = p.x;
                    v[3 * vi + 1][lane] = p.y;
                    v[3 * vi + 2][lane] = p.z;
                }
            } else {
                slots[lane] = -1;
                for (int row = 0; row < 9; ++row) v[row][lane] = NAN;
            }
        }
        __global float4 *blk = blocks + 10 * (b0 + b);
        for (int row = 0; row < 9; ++row) blk[row] = (float4)(v[row][0], v[row][1], v[row][2], v[row][3]);
        blk[9] = as_float4((int4)(slots[0], slots[1], slots[2], slots[3]));
    }
}

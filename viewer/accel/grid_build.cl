// Uniform grid build (Kalojanov & Slusallek 2009): triangle-cell pairs counted per triangle,
// offsets by an exclusive scan, pairs written, radix-sorted by cell (viewer/cl/primitives.py),
// cell ranges from the segment boundaries of the sorted keys. Layout: grid.cl.
//
// Binning is box/box: a triangle goes to every cell its bounding box (grown by eps cells, then
// clipped to the grid) overlaps. Triangles with a non-finite vertex are not binned (they can
// never be hit). Triangles: 3 float4 per slot (v0, v1, v2; w unused).
#include "grid.cl"

#ifndef WG
#define WG 64
#endif

// Cell range [c0, c1] (inclusive) of triangle i; false when it is not binned.
inline bool tri_cell_range(const Grid *g, __global const float4 *tris, uint i, int3 *c0, int3 *c1) {
    float3 a = tris[3 * i].xyz, b = tris[3 * i + 1].xyz, c = tris[3 * i + 2].xyz;
    // fmin/fmax drop NaN operands: test the vertices themselves
    if (!(all(isfinite(a)) && all(isfinite(b)) && all(isfinite(c)))) return false;
    float3 mn = fmin(fmin(a, b), c), mx = fmax(fmax(a, b), c);
    float3 lo = (mn - g->lo.xyz) * g->inv.xyz - g->eps.xyz;
    float3 hi = (mx - g->lo.xyz) * g->inv.xyz + g->eps.xyz;
    float3 res = convert_float3(g->res.xyz);
    if (hi.x < 0.0f || hi.y < 0.0f || hi.z < 0.0f || lo.x >= res.x || lo.y >= res.y || lo.z >= res.z) return false;
    float3 top = res - 1.0f;
    *c0 = convert_int3(fmin(fmax(floor(lo), (float3)(0.0f)), top));
    *c1 = convert_int3(fmin(fmax(floor(hi), (float3)(0.0f)), top));
    return true;
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void grid_count(__global const Grid *grid, __global const float4 *tris, const uint n, __global uint *counts) {
    uint i = get_global_id(0);
    if (i >= n) return;
    Grid g = *grid;
    int3 c0, c1;
    uint cnt = 0;
    if (tri_cell_range(&g, tris, i, &c0, &c1)) {
        int3 e = c1 - c0 + 1;
        cnt = (uint)e.x * (uint)e.y * (uint)e.z;
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
    int3 c0, c1;
    if (!tri_cell_range(&g, tris, i, &c0, &c1)) return;
    uint o = offsets[i];
    for (int z = c0.z; z <= c1.z; ++z)
        for (int y = c0.y; y <= c1.y; ++y)
            for (int x = c0.x; x <= c1.x; ++x) {
                if (o >= cap) return;
                keys[o] = (uint)grid_cell_id(&g, (int3)(x, y, z));
                vals[o] = i;
                ++o;
            }
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

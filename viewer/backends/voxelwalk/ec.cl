// voxelwalk EC (Enforced Coherence, Guntury 2011 ch. 5), in iterations over the active rays:
//   ec_init     every ray: miss key, its first cell (VW_NONE: inactive or misses the grid)
// Counts (active rays, pairs, chunks) stay on the device: the kernels read them, the primitives'
// device-count variants write them, and the host enqueues iterations in batches without reading
// back in between (viewer/backends/voxelwalk/engine.py).
//   ec_count    each active ray counts the (ray, cell) pairs of its next WINDOW non-empty cells
//               (WINDOW 0: all the cells it crosses up to its current hit or tmax)
//   (exclusive scan of the counts: viewer/cl/primitives.py)
//   ec_write    writes the pairs (key = cell id, value = ray) and the ray's state after the window
//   (radix sort by cell, segment boundaries cut into chunks of at most WG rays, compacted)
//   ec_process  one work-group per chunk: the cell's triangles staged in local memory WG at a time,
//               every ray of the chunk tests all of them, and its nearest hit goes to the ray's
//               packed (distance, triangle) key by a 64-bit atomic minimum: the result does not
//               depend on the order in which chunks run (ties go to the lowest triangle slot: a
//               cell lists its triangles in slot order, the grid build's sort being stable)
//   ec_resolve  a ray is done when its walk ended or its hit lies inside the last cell it walked
//               (the hit-inside-cell rule of IVW); the others go on from their next cell
//   ec_finish   hits from the keys
// Ray order inside a cell is lost (rays are sorted by cell), so every pair is processed.
#include "walk.cl"

#ifndef WG
#define WG 64
#endif

__kernel void ec_init(__global const Grid *grid, __global const float4 *ray_o, __global const float4 *ray_d,
                      const uint n, __global ulong *keys, __global uint *next_cell, __global int *iters) {
    uint i = get_global_id(0);
    if (i >= n) return;
    Grid g = *grid;
    float4 ot = ray_o[i], dt = ray_d[i];
    uint cell = VW_NONE;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        GridWalk w;
        float t_enter;
        if (grid_walk_begin(&g, &r, ot.w, dt.w, &w, &t_enter)) cell = (uint)grid_cell_id(&g, w.cell);
    }
    keys[i] = VW_MISS_KEY;
    next_cell[i] = cell;
    iters[i] = 0;
}

// Walks ray i over its next `window` non-empty cells from next_cell[i]. With WRITE, writes the
// pairs from offset o and the state after the window; returns the pair count.
inline uint ec_walk(const Grid *g, __global const uint2 *cells, uint i, float4 ot, float4 dt, ulong key,
                    uint start_cell, uint window, const bool write, uint o, __global uint *pkeys,
                    __global uint *pvals, __global uint *next_cell, __global float *win_exit,
                    __global uint *first_cell) {
    RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
    float t_limit = fmin(dt.w, vw_key_t(key));
    GridWalk w;
    vw_walk_at(g, &r, start_cell, t_limit, &w);
    uint count = 0;
    uint2 cr;
    float exit_t = INFINITY;
    uint next = VW_NONE;
    uint first = VW_NONE;
    while (vw_next_nonempty(g, cells, &r, &w, t_limit, &cr)) {
        uint id = (uint)grid_cell_id(g, w.cell);
        if (write) {
            pkeys[o + count] = id;
            pvals[o + count] = i;
        }
        if (count == 0) first = id;
        ++count;
        exit_t = grid_cell_exit(&w);
        bool more = grid_walk_step(g, &r, &w, t_limit);
        if (window != 0u && count >= window) {
            if (more) next = (uint)grid_cell_id(g, w.cell);
            break;
        }
        if (!more) break;
    }
    if (write) {
        next_cell[i] = next;
        win_exit[i] = exit_t;
        first_cell[i] = first;
    }
    return count;
}

// The per-ray kernels read the active count m from the device (the last compaction wrote it)
// and stride over it: the host launches them for a bound, with no read-back between iterations.
__kernel void ec_count(__global const Grid *grid, __global const uint2 *cells, __global const float4 *ray_o,
                       __global const float4 *ray_d, __global const ulong *keys, __global const uint *next_cell,
                       __global const uint *act, __global const uint *m_ptr, const uint window,
                       __global uint *counts) {
    uint m = *m_ptr;
    Grid g = *grid;
    for (uint j = get_global_id(0); j < m; j += get_global_size(0)) {
        uint i = act[j];
        counts[j] = ec_walk(&g, cells, i, ray_o[i], ray_d[i], keys[i], next_cell[i], window, false, 0u,
                            0, 0, 0, 0, 0);
    }
}

__kernel void ec_write(__global const Grid *grid, __global const uint2 *cells, __global const float4 *ray_o,
                       __global const float4 *ray_d, __global const ulong *keys, __global uint *next_cell,
                       __global const uint *act, __global const uint *m_ptr, const uint window,
                       __global const uint *offsets, __global uint *pkeys, __global uint *pvals,
                       __global float *win_exit, __global uint *first_cell, __global int *iters) {
    uint m = *m_ptr;
    Grid g = *grid;
    for (uint j = get_global_id(0); j < m; j += get_global_size(0)) {
        uint i = act[j];
        uint c = ec_walk(&g, cells, i, ray_o[i], ray_d[i], keys[i], next_cell[i], window, true, offsets[j],
                         pkeys, pvals, next_cell, win_exit, first_cell);
        if (c) iters[i] += (int)c;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void ec_process(__global const uint2 *cells, __global const uint *refs, __global const float4 *tris,
                __global const float4 *ray_o, __global const float4 *ray_d, __global const uint *chunk_key,
                __global const uint *chunk_start, __global const uint *chunk_len, __global const uint *pvals,
                __global ulong *keys, __global const uint *nchunks_ptr) {
    __local float4 sv[3 * WG];
    __local uint sslot[WG];
    // persistent work-groups: each takes chunks group_id, group_id + groups, ... below the
    // chunk count the segmentation wrote (uniform per group: the barriers below are safe)
    uint nchunks = *nchunks_ptr;
    for (uint c = get_group_id(0); c < nchunks; c += get_num_groups(0)) {
        uint lid = get_local_id(0);
        uint2 cr = cells[chunk_key[c]];
        uint len = chunk_len[c];
        bool mine = lid < len;
        uint i = mine ? pvals[chunk_start[c] + lid] : 0u;
        float4 ot = mine ? ray_o[i] : (float4)(0.0f);
        float4 dt = mine ? ray_d[i] : (float4)(0.0f, 0.0f, 1.0f, -1.0f);
        float tmin = ot.w;
        // bound: the ray's tmax, or just beyond its current hit (a hit at the same distance on a lower
        // slot must still win the minimum, whichever chunk ran first)
        ulong key0 = mine ? keys[i] : VW_MISS_KEY;
        float hit_t = !mine ? -1.0f : (key0 == VW_MISS_KEY ? dt.w : fmin(dt.w, nextafter(vw_key_t(key0), INFINITY)));
        uint hit_slot = VW_NONE;
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        for (uint base = 0; base < cr.y; base += WG) {
            uint cnt = min((uint)WG, cr.y - base);
            barrier(CLK_LOCAL_MEM_FENCE);
            if (lid < cnt) {
                uint slot = refs[cr.x + base + lid];
                sslot[lid] = slot;
                sv[3 * lid] = tris[3 * slot];
                sv[3 * lid + 1] = tris[3 * slot + 1];
                sv[3 * lid + 2] = tris[3 * slot + 2];
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (mine) {
                for (uint k = 0; k < cnt; ++k) {
                    float t;
                    if (rt_intersect_triangle(&r, sv[3 * k].xyz, sv[3 * k + 1].xyz, sv[3 * k + 2].xyz, tmin, hit_t, &t)) {
                        hit_t = t;  // strict: on equal distances the first in the cell's list, the lowest slot
                        hit_slot = sslot[k];
                    }
                }
            }
        }
        if (mine && hit_slot != VW_NONE) atom_min(&keys[i], vw_pack(hit_t, hit_slot));
    }
}

// Work-item 0 also adds the iteration to the pass's totals (iterations, ray-cell pairs, chunks)
// when rays were active: the host reads them once, with the pass's last count.
__kernel void ec_resolve(__global const ulong *keys, __global const uint *next_cell, __global const float *win_exit,
                         __global const uint *act, __global const uint *m_ptr, __global uint *keep,
                         __global const uint *pairs_ptr, __global const uint *chunks_ptr, __global uint *totals) {
    uint m = *m_ptr;
    if (get_global_id(0) == 0 && m) {
        totals[0] += 1u;
        totals[1] += *pairs_ptr;
        totals[2] += *chunks_ptr;
    }
    for (uint j = get_global_id(0); j < m; j += get_global_size(0)) {
        uint i = act[j];
        ulong key = keys[i];
        bool done = next_cell[i] == VW_NONE || (key != VW_MISS_KEY && vw_key_t(key) <= win_exit[i]);
        keep[j] = done ? 0u : 1u;
    }
}

__kernel void ec_finish(__global const ulong *keys, const uint n, __global float *out_t, __global int *out_id) {
    uint i = get_global_id(0);
    if (i >= n) return;
    ulong key = keys[i];
    out_t[i] = vw_key_t(key);
    out_id[i] = vw_key_id(key);
}

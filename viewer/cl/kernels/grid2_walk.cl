// Walking a cell's triangle blocks, and with TWO_LEVEL a dense top cell's sub-grid (the two-level
// grid of viewer/accel/grid2.py; layout and sub-walk steps in grid2.cl). Shared by every backend
// that walks the grid one ray per work-item (ugrid, voxelwalk's IVW). Needs geometry.cl and
// grid.cl included first.
#ifndef GRID2_WALK_CL
#define GRID2_WALK_CL

// Tests cnt triangles from the SoA blocks at blk; true when an any-hit ray is done.
inline bool test_blocks(const RayPre *r, __global const float4 *blk, uint cnt, float tmin, float *hit_t,
                        int *hit_id, const bool any_hit, int *tests) {
    for (uint k = 0; k < cnt; k += 4, blk += 10) {
        int4 slots = as_int4(blk[9]);
        int4 lanes = slots >= (int4)(0);
        float t;
        *tests += min(4u, cnt - k);
        int lane = rt_intersect_triangle4(r, blk, lanes, tmin, *hit_t, &t);
        if (lane >= 0) {
            *hit_t = t;
            *hit_id = lane == 0 ? slots.x : (lane == 1 ? slots.y : (lane == 2 ? slots.z : slots.w));
            if (any_hit) return true;
        }
    }
    return false;
}

#ifdef TWO_LEVEL
#include "grid2.cl"
// The top cell's big list, then its sub-grid walked over the ray's whole (tmin, hit_t) inside the
// sub-grid's box (the box lies within half a top cell of the cell; clipping the walk to the top
// cell's own interval would need that interval conservative too). Closest hit: the sub-walk stops
// after the first sub-cell whose exit is at or beyond the nearest hit (as the top walk does).
inline bool walk_sub(const RayPre *r, const SubGrid *s, __global const uint2 *scells,
                     __global const float4 *sblocks, __global const uint *scb, __global const float4 *bblocks,
                     float tmin, float *hit_t, int *hit_id, const bool any_hit, int *tests) {
    if (s->big.y > 0 && test_blocks(r, bblocks + 10 * s->big.x, s->big.y, tmin, hit_t, hit_id, any_hit, tests))
        return true;
    SubWalk w;
    if (!g2_walk_begin(s, r, tmin, *hit_t, &w)) return false;
    while (true) {
        int sid = g2_cell_id(s, w.cell);
        uint cnt = scells[sid].y;
        if (cnt > 0 && test_blocks(r, sblocks + 10 * scb[sid], cnt, tmin, hit_t, hit_id, any_hit, tests))
            return true;
        if (*hit_id >= 0 && (g2real)*hit_t <= g2_cell_exit(&w)) break;
        if (!g2_walk_step(s, &w, *hit_t)) break;
    }
    return false;
}
#define G2_PARAMS , __global const int *sub_of, __global const SubGrid *subs, __global const uint2 *scells, \
    __global const float4 *sblocks, __global const uint *scb, __global const float4 *bblocks
#define G2_ARGS , sub_of, subs, scells, sblocks, scb, bblocks
#else
#define G2_PARAMS
#define G2_ARGS
#endif

// One top cell `cid` holding `cnt` triangles: its sub-grid when it has one (TWO_LEVEL), else its
// own list. True when an any-hit ray is done.
inline bool test_cell(const RayPre *r, int cid, uint cnt, __global const float4 *blocks,
                      __global const uint *cell_blocks G2_PARAMS, float tmin, float *hit_t, int *hit_id,
                      const bool any_hit, int *tests) {
#ifdef TWO_LEVEL
    int s = sub_of[cid];
    if (s >= 0) {
        SubGrid sg = subs[s];
        return walk_sub(r, &sg, scells, sblocks, scb, bblocks, tmin, hit_t, hit_id, any_hit, tests);
    }
#endif
    return cnt > 0 && test_blocks(r, blocks + 10 * cell_blocks[cid], cnt, tmin, hit_t, hit_id, any_hit, tests);
}

#endif

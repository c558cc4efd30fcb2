// voxelwalk IVW (Independent Voxel Walk, Guntury 2011 ch. 5): one work-item per ray walks the
// uniform grid by 3D-DDA from its origin, tests the triangles of each non-empty cell (watertight
// test of geometry.cl) and stops at the first cell that holds a hit inside the cell (closest
// hit) or at the first hit (any hit: shadow, soft, AO). Triangles are tested four at a time from
// the cell's SoA blocks (grid.py GRID_BLOCK_DTYPE; cell order = slot order, so ties go to the
// lowest slot); with VW_SKIP empty 8^3 blocks of cells are skipped whole (walk.cl). iters[i] =
// non-empty (top) cells the ray visited (its iterations); first[i] = its first non-empty cell
// (VW_NONE: none), for the tile divergence statistics. With TWO_LEVEL (levels=2), a top cell with a sub-grid (the two-level
// grid of viewer/accel/grid2.py, as ugrid's) is walked through it instead of its own list: the
// teapot-in-a-stadium case. The one-launch EC (ec_tile.cl) walks the same sub-grids in the same
// order; the global-sort EC (ec.cl) the top lists, which stay whole.
#include "walk.cl"
#include "grid2_walk.cl"

#ifndef WG
#define WG 64
#endif

// One ray (any_hit a literal at each call: the two copies are specialised, as ugrid's kernels are).
inline void ivw_ray(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                    __global const uint *cell_blocks G2_PARAMS, float4 ot, float4 dt, const bool any_hit,
                    __global const uchar *occ_fine, __global const uchar *occ_coarse, float *out_t, int *out_id,
                    int *out_iters, uint *out_first) {
    float tmin = ot.w, hit_t = dt.w;
    int hit_id = -1;
    int iters = 0;
    uint first = VW_NONE;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        GridWalk w;
        float t_enter;
        uint2 cr;
        if (grid_walk_begin(g, &r, tmin, hit_t, &w, &t_enter)) {
            while (VW_NEXT(g, cells, occ_fine, occ_coarse, &r, &w, hit_t, &cr)) {
                int cid = grid_cell_id(g, w.cell);
                if (iters == 0) first = (uint)cid;
                ++iters;
                int tests = 0;
                if (test_cell(&r, cid, cr.y, blocks, cell_blocks G2_ARGS, tmin, &hit_t, &hit_id, any_hit, &tests))
                    break;
                if (hit_id >= 0 && hit_t <= grid_cell_exit(&w)) break;  // the hit lies inside this cell
                if (!grid_walk_step(g, &r, &w, hit_t)) break;
            }
        }
    }
    *out_t = hit_id >= 0 ? hit_t : INFINITY;
    *out_id = hit_id;
    *out_iters = iters;
    *out_first = first;
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void ivw_trace(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,
               __global const uint *cell_blocks G2_PARAMS, __global const float4 *ray_o, __global const float4 *ray_d,
               __global float *out_t, __global int *out_id, const int n, const int any_hit,
               __global int *iters_out, __global uint *first_out, __global const uchar *occ_fine,
               __global const uchar *occ_coarse) {
    int i = get_global_id(0);
    if (i >= n) return;
    Grid g = *grid;
    float t;
    int id, iters;
    uint first;
    if (any_hit)
        ivw_ray(&g, cells, blocks, cell_blocks G2_ARGS, ray_o[i], ray_d[i], true, occ_fine, occ_coarse, &t, &id,
                &iters, &first);
    else
        ivw_ray(&g, cells, blocks, cell_blocks G2_ARGS, ray_o[i], ray_d[i], false, occ_fine, occ_coarse, &t, &id,
                &iters, &first);
    out_t[i] = t;
    out_id[i] = id;
    iters_out[i] = iters;
    first_out[i] = first;
}

// Block occupancy for empty-space skipping (walk.cl), one level (blocks of 2^shift cells on a
// side): one work-item per block.
__kernel void vw_macro_build(__global const Grid *grid, __global const uint2 *cells, const int shift,
                             __global uchar *occ) {
    Grid g = *grid;
    int3 br = vw_block_res(&g, shift);
    int id = get_global_id(0);
    if (id >= br.x * br.y * br.z) return;
    int3 b = (int3)(id % br.x, (id / br.x) % br.y, id / (br.x * br.y));
    int3 lo = b << shift, hi = min(lo + (1 << shift), g.res.xyz);
    uchar any = 0;
    for (int z = lo.z; z < hi.z && !any; ++z)
        for (int y = lo.y; y < hi.y && !any; ++y)
            for (int x = lo.x; x < hi.x; ++x) any |= cells[grid_cell_id(&g, (int3)(x, y, z))].y != 0u ? 1 : 0;
    occ[id] = any;
}

// ugrid: one work-item per ray walks the uniform grid (viewer/accel/grid.py; layout and 3D-DDA in
// viewer/cl/kernels/grid.cl) and tests the triangles listed in each cell it visits, four at a
// time from the cell's SoA blocks (grid.py GRID_BLOCK_DTYPE), with the watertight float4 test of
// geometry.cl. Closest hit: the walk stops after the first cell whose exit
// distance is at or beyond the nearest hit found so far (the hit-inside-cell check: a triangle
// listed in several cells may be hit beyond the current cell, and a nearer one may still lie in
// the cells between). Any hit (shadow, soft, AO): stops at the first hit in (tmin, tmax).
// With COUNT_TESTS defined, the triangle tests of each ray are written to `tests` (overlays).
// With TWO_LEVEL defined, top cells with a sub-grid (viewer/accel/grid2.py; grid2.cl) are walked
// through it instead of their own lists.
#include "geometry.cl"
#include "grid.cl"

#ifndef WG
#define WG 64
#endif

// test_blocks; with TWO_LEVEL the sub-grid walk (walk_sub, G2_PARAMS)
#include "grid2_walk.cl"

inline void trace_ray(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                      __global const uint *cell_blocks G2_PARAMS, float4 ot, float4 dt, const bool any_hit,
                      float *out_t, int *out_id, int *out_tests) {
    float tmin = ot.w;
    float hit_t = dt.w;
    int hit_id = -1;
    int tests = 0;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        GridWalk w;
        float t_enter;
        if (grid_walk_begin(g, &r, tmin, hit_t, &w, &t_enter)) {
            while (true) {
                int cid = grid_cell_id(g, w.cell);
                if (test_cell(&r, cid, cells[cid].y, blocks, cell_blocks G2_ARGS, tmin, &hit_t, &hit_id, any_hit,
                              &tests))
                    goto done;
                if (hit_id >= 0 && hit_t <= grid_cell_exit(&w)) break;
                if (!grid_walk_step(g, &r, &w, hit_t)) break;
            }
        }
    }
done:
    *out_t = hit_id >= 0 ? hit_t : INFINITY;
    *out_id = hit_id;
    *out_tests = tests;
}

#ifdef COUNT_TESTS
#define STORE_TESTS tests_out[i] = tests;
#else
#define STORE_TESTS
#endif

#define TRACE_KERNEL(name, ANY, INDEX_ARG, RAY, N_ARG, N_GET)                                                \
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))                                                    \
void name(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,           \
          __global const uint *cell_blocks G2_PARAMS, __global const float4 *ray_o, __global const float4 *ray_d,     \
          __global float *out_t, __global int *out_id, N_ARG, __global int *tests_out INDEX_ARG) {          \
    N_GET                                                                                                   \
    int j = get_global_id(0);                                                                               \
    if (j >= n) return;                                                                                     \
    int i = RAY;                                                                                            \
    Grid g = *grid;                                                                                         \
    float t;                                                                                                \
    int id, tests;                                                                                          \
    trace_ray(&g, cells, blocks, cell_blocks G2_ARGS, ray_o[i], ray_d[i], ANY, &t, &id, &tests);                    \
    out_t[i] = t;                                                                                           \
    out_id[i] = id;                                                                                         \
    STORE_TESTS                                                                                             \
}

#define NO_INDEX
#define WITH_INDEX , __global const uint *index
#define N_HOST const int n
#define N_DEVICE __global const uint *n_ptr
#define GET_N_HOST
#define GET_N_DEVICE const int n = (int)*n_ptr;
// every ray of the batch, or (the _idx kernels) only the rays listed in `index`; the _idxd kernels
// read how many are listed from the device (a compaction's count: launched for a bound, no wait)
TRACE_KERNEL(trace_closest, false, NO_INDEX, j, N_HOST, GET_N_HOST)
TRACE_KERNEL(trace_any, true, NO_INDEX, j, N_HOST, GET_N_HOST)
TRACE_KERNEL(trace_closest_idx, false, WITH_INDEX, (int)index[j], N_HOST, GET_N_HOST)
TRACE_KERNEL(trace_any_idx, true, WITH_INDEX, (int)index[j], N_HOST, GET_N_HOST)
TRACE_KERNEL(trace_closest_idxd, false, WITH_INDEX, (int)index[j], N_DEVICE, GET_N_DEVICE)
TRACE_KERNEL(trace_any_idxd, true, WITH_INDEX, (int)index[j], N_DEVICE, GET_N_DEVICE)

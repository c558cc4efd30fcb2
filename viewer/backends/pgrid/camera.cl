// pgrid primary rays: the camera perspective grid (layout viewer/cl/kernels/camgrid.cl), traced
// with one CN x CN work-group per CN x CN pixel block; a grid tile is k x k blocks (indirect
// mapping: the tiles the grid is sorted into are k times wider than a work-group, so k x k
// work-groups read the same cell lists). Per slab, front to back, the tile's triangles are staged
// in local memory CN * CN at a time (four per SoA block, stage.cl) and every ray of the block tests
// every staged triangle, four at a time (watertight rt_intersect_triangle4 of geometry.cl: the SIMD
// a CPU device gets from inside a work-item). Slab check: after slab s a ray whose hit is nearer
// than where slab s + 1 begins is done (every triangle reaching nearer depths is in slab <= s);
// the work-group stops when all its rays are done. Rays flagged `outside` are left alone (traced
// another way). With COUNT_TESTS each ray's triangle tests are written to `tests_out`.
#include "camgrid.cl"
#include "stage.cl"

#ifndef CN
#define CN 8
#endif
#define CWG (CN * CN)

__kernel __attribute__((reqd_work_group_size(CN, CN, 1)))
void cg_trace(__global const CGrid *grid, __global const uint2 *cells, __global const uint *refs,
              __global const float4 *tris, __global const float4 *ray_o, __global const float4 *ray_d,
              __global const uint *outside, __global float *out_t, __global int *out_id, __global int *tests_out) {
    __local float4 sv[9 * (CWG / 4)];  // staged triangles, four per block in SoA form (rt_intersect_triangle4)
    __local int sslot[CWG];
    __local int remaining;
    CGrid g = *grid;
    int W = g.cells.y, H = g.cells.z;
    int px = (int)get_global_id(0), py = (int)get_global_id(1);
    uint lid = get_local_id(0) + CN * get_local_id(1);
    bool mine = px < W && py < H;
    uint ri = mine ? (uint)(py * W + px) : 0u;
    bool skip = !mine || outside[ri];
    float4 ot = skip ? (float4)(0.0f) : ray_o[ri];
    float4 dt = skip ? (float4)(0.0f, 0.0f, 1.0f, -1.0f) : ray_d[ri];
    bool active = !skip && dt.w > ot.w;
    float tmin = ot.w, hit_t = dt.w;
    int hit_id = -1;
    int tests = 0;
    RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
#ifdef RT_HAVE_FP64
    double kz = cg_project(&g, convert_double3(dt.xyz)).z;  // depth per unit of t
#endif
    int tile = ((int)get_group_id(1) * CN / g.tiles.x) * g.tiles.y + (int)get_group_id(0) * CN / g.tiles.x;
    if (lid == 0) remaining = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (active) atomic_inc(&remaining);
    barrier(CLK_LOCAL_MEM_FENCE);
    bool done = !active;
    int S = g.tiles.w;
    for (int s = 0; s < S; ++s) {
        if (remaining == 0) break;  // the same value in every work-item
        uint2 cr = cells[tile * S + s];
        for (uint b = 0; b < cr.y; b += CWG) {
            uint cnt = min((uint)CWG, cr.y - b);
            barrier(CLK_LOCAL_MEM_FENCE);
            if (lid < cnt) {
                uint slot = refs[cr.x + b + lid];
                sslot[lid] = (int)slot;
                stage_triangle(sv, lid, tris, slot);
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (!done) {
                for (uint k = 0; k < cnt; k += 4) {
                    float t;
                    tests += (int)min(4u, cnt - k);
                    int lane = rt_intersect_triangle4_local(&r, sv + 9 * (k / 4), stage_lanes(k, cnt), tmin, hit_t, &t);
                    if (lane >= 0) {
                        hit_t = t;
                        hit_id = sslot[k + lane];
                    }
                }
            }
        }
#ifdef RT_HAVE_FP64
        if (!done && hit_id >= 0 && cg_slab(&g, (double)hit_t * kz * (1.0 + 1e-5), 1e-3) <= s) {
            done = true;
            atomic_dec(&remaining);
        }
#endif
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (!skip) {
        out_t[ri] = hit_id >= 0 ? hit_t : INFINITY;
        out_id[ri] = hit_id;
#ifdef COUNT_TESTS
        tests_out[ri] = tests;
#endif
    }
}

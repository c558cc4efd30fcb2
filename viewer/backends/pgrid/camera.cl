// pgrid primary rays: the camera perspective grid (layout viewer/cl/kernels/camgrid.cl), traced
// with one CN x CN work-group per CN x CN pixel block; a grid tile is k x k blocks (indirect
// mapping: the tiles the grid is sorted into are k times wider than a work-group, so k x k
// work-groups read the same cell lists). A tile's cells (its big list, then its slabs front to
// back) hold contiguous refs, staged in local memory CN * CN at a time (four per SoA block,
// stage.cl) whatever slabs they come from (two barriers per batch, not per slab: a barrier costs a
// CPU device a save of every work-item's live state). Every ray of the block tests the staged
// triangles whose pixel rectangle holds the ray's own pixel point, four at a time (watertight
// rt_intersect_triangle4 of geometry.cl: the SIMD a CPU device gets from inside a work-item).
// Slab check: a ray whose hit lies nearer than where the next staged triangle's slab begins is
// done (every later triangle begins deeper: slabs are in order, and a triangle's slab begins at or
// before its nearest depth); the work-group stops when all its rays are done. Rays flagged
// `outside` are left alone (traced another way). With COUNT_TESTS each ray's triangle tests are
// written to `tests_out`.
#include "camgrid.cl"
#include "stage.cl"

#ifndef CN
#define CN 8
#endif
#define CWG (CN * CN)

__kernel __attribute__((reqd_work_group_size(CN, CN, 1)))
void cg_trace(__global const CGrid *grid, __global const uint2 *cells, __global const uint *refs,
              __global const uint *keys, __global const float4 *tris, __global const float4 *ray_o,
              __global const float4 *ray_d, __global const uint *outside, __global float *out_t, __global int *out_id,
              __global int *tests_out, __global const cg_bound *bounds, __global const float4 *rect) {
    __local float4 sv[9 * (CWG / 4)];  // staged triangles, four per block in SoA form (rt_intersect_triangle4)
    __local float4 sbox[CWG];  // their pixel rectangles, four per block in SoA form (stage_box)
    __local int sslot[CWG];
    __local float slo[CWG];  // the depth where each staged triangle's slab begins (-inf: big list, slab 0)
    __local int remaining;
    __local uint tile_first, tile_total;
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
    float rx = -1.0f, ry = -1.0f;  // the ray's own pixel point (the rectangle test)
    float zh = INFINITY;  // an upper bound of the hit's depth (slab check)
#ifdef RT_HAVE_FP64
    double3 q = cg_project(&g, convert_double3(dt.xyz));
    double kz = q.z;  // depth per unit of t
    if (active && q.z > 0.0) {
        rx = (float)(q.x / q.z);
        ry = (float)(q.y / q.z);
    }
#endif
    int tile = ((int)get_group_id(1) * CN / g.tiles.x) * g.tiles.y + (int)get_group_id(0) * CN / g.tiles.x;
    int S1 = g.tiles.w + 1;  // cells per tile: the big list, then the slabs; their refs are contiguous
    if (lid == 0) {
        remaining = 0;
        tile_first = UINT_MAX;
        tile_total = 0u;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int c = (int)lid; c < S1; c += CWG) {
        uint2 cr = cells[tile * S1 + c];
        if (cr.y) {
            atomic_min(&tile_first, cr.x);
            atomic_add(&tile_total, cr.y);
        }
    }
    if (active) atomic_inc(&remaining);
    barrier(CLK_LOCAL_MEM_FENCE);
    uint first = tile_first, total = tile_total;
    bool done = !active;
    for (uint b = 0; b < total; b += CWG) {
        if (remaining == 0) break;  // the same value in every work-item (read after a barrier)
        uint cnt = min((uint)CWG, total - b);
        if (lid < cnt) {
            uint p = first + b + lid, slot = refs[p];
            int sl = (int)(keys[p] % (uint)S1) - 1;
            sslot[lid] = (int)slot;
            stage_triangle(sv, lid, tris, slot);
            stage_box(sbox, lid, rect[slot]);
#ifdef RT_HAVE_FP64
            slo[lid] = sl <= 0 ? -INFINITY : cg_down((double)bounds[sl]);
#else
            slo[lid] = -INFINITY;
#endif
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (!done) {
            for (uint k = 0; k < cnt; k += 4) {
                if (zh < slo[k]) {  // every triangle from k on begins deeper than this ray's hit
                    done = true;
                    atomic_dec(&remaining);
                    break;
                }
                float t;
                int4 lanes = stage_lanes(k, cnt) & box_lanes(sbox + k, rx, ry);
                if (!any(lanes)) continue;  // the ray's pixel point is outside the four rectangles
                tests += (int)(-(lanes.x + lanes.y + lanes.z + lanes.w));
                int lane = rt_intersect_triangle4_local(&r, sv + 9 * (k / 4), lanes, tmin, hit_t, &t);
                if (lane >= 0) {
                    hit_t = t;
                    hit_id = sslot[k + lane];
#ifdef RT_HAVE_FP64
                    zh = cg_up((double)hit_t * kz * (1.0 + 1e-5));
#endif
                }
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);  // the batch is used up and `remaining` settled
    }
    if (!skip) {
        out_t[ri] = hit_id >= 0 ? hit_t : INFINITY;
        out_id[ri] = hit_id;
#ifdef COUNT_TESTS
        tests_out[ri] = tests;
#endif
    }
}

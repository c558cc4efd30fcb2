// clbvh: one work-item per ray traverses the 4-wide BVH (viewer/accel/bvh4.py) from the root.
// SIMD comes from inside the work-item: one float4 slab test checks a node's four children
// (PoCL does not vectorise this kind of loop across work-items). Closest hit: hit children are
// sorted by entry distance; leaf children are intersected at once, nearest first, and inner
// children are visited nearest first (the others pushed far-to-near with their entry distance,
// culled when popped beyond the current hit). Any hit (shadow, soft, AO): children in stored
// order, and the kernel stops at the first hit.
//
// Buffers: nodes = NODE4_DTYPE (viewer/accel/bvh4.py) as 8 float4 per node (minx, maxx, miny,
// maxy, minz, maxz, child, count) except that a leaf child is ~(its first leaf block) instead of
// ~(first slot); blocks = leaf blocks (below, packed by clbvh/__init__.py: LEAF_BLOCK_DTYPE),
// leaf triangles four at a time in SoA form; rays and hits as viewer/cl/transfer.py lays them out.
#include "geometry.cl"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef WG
#define WG 64
#endif

#define CSWAP(i, j)                                                    \
    if (d##j < d##i) {                                                 \
        float td = d##i; d##i = d##j; d##j = td;                       \
        int tc = c##i; c##i = c##j; c##j = tc;                         \
        int tn = n##i; n##i = n##j; n##j = tn;                         \
    }

// Leaf blocks (LEAF_BLOCK floats4 each): v0x, v0y, v0z, v1x, v1y, v1z, v2x, v2y, v2z of up to four
// triangles (one lane each, NaN padding), then int4 (first slot, triangles in the block, 0, 0).
// A leaf of `count` triangles is (count + 3) / 4 consecutive blocks. Returns true when the ray
// was stopped by a hit in any-hit mode.
#define LEAF_BLOCK 10
inline bool leaf_hits(const RayPre *r, __global const float4 *blocks, int block, int count, float tmin,
                      const bool any_hit, float *hit_t, int *hit_id) {
    int nb = (count + 3) >> 2;
    for (int b = 0; b < nb; ++b) {
        __global const float4 *blk = blocks + LEAF_BLOCK * (block + b);
        int4 meta = as_int4(blk[9]);
        int4 lanes = (int4)(0, 1, 2, 3) < (int4)(meta.y);
        float t;
        int lane = rt_intersect_triangle4(r, blk, lanes, tmin, *hit_t, &t);
        if (lane >= 0) {
            *hit_t = t;
            *hit_id = meta.x + lane;
            if (any_hit) return true;
        }
    }
    return false;
}

inline void trace_ray(__global const float4 *nodes, __global const float4 *blocks, float4 ot, float4 dt,
                      const bool any_hit, float *out_t, int *out_id) {
    float tmin = ot.w;
    float hit_t = dt.w;
    int hit_id = -1;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        int stack_node[STACK_SIZE];
        float stack_t[STACK_SIZE];
        int sp = 0;
        int ni = 0;
        while (true) {
            __global const float4 *nd = nodes + 8 * ni;
            float4 te;
            int4 m = rt_intersect_box4(&r, nd, tmin, hit_t, &te);
            int4 ch = as_int4(nd[6]);
            int4 cn = as_int4(nd[7]);
            float d0 = m.x ? te.x : INFINITY, d1 = m.y ? te.y : INFINITY;
            float d2 = m.z ? te.z : INFINITY, d3 = m.w ? te.w : INFINITY;
            int c0 = ch.x, c1 = ch.y, c2 = ch.z, c3 = ch.w;
            int n0 = cn.x, n1 = cn.y, n2 = cn.z, n3 = cn.w;
            int nhit = -(m.x + m.y + m.z + m.w);
            int next = -1;
            if (nhit > 0) {
                // closest hit: nearest first (sorting network, only when two or more children are
                // hit); any hit: stored order, the sort does not pay off (measured: 5-17% faster)
                if (!any_hit && nhit > 1) {
                    CSWAP(0, 1) CSWAP(2, 3) CSWAP(0, 2) CSWAP(1, 3) CSWAP(1, 2)
                }
                // leaves now, inner children collected in order
                int in0 = -1, in1 = -1, in2 = -1, in3 = -1;
                float it1 = 0.0f, it2 = 0.0f, it3 = 0.0f;
                int nin = 0;
#define VISIT(k)                                                                                        \
                if (d##k < INFINITY && d##k <= hit_t) {                                                 \
                    if (c##k < 0) {                                                                     \
                        if (leaf_hits(&r, blocks, ~c##k, n##k, tmin, any_hit, &hit_t, &hit_id))         \
                            goto done;                                                                  \
                    } else {                                                                            \
                        if (nin == 0) { in0 = c##k; }                                                   \
                        else if (nin == 1) { in1 = c##k; it1 = d##k; }                                  \
                        else if (nin == 2) { in2 = c##k; it2 = d##k; }                                  \
                        else { in3 = c##k; it3 = d##k; }                                                \
                        ++nin;                                                                          \
                    }                                                                                   \
                }
                VISIT(0) VISIT(1) VISIT(2) VISIT(3)
#undef VISIT
                if (nin > 0) {
                    if (nin > 3) { stack_node[sp] = in3; stack_t[sp] = it3; ++sp; }
                    if (nin > 2) { stack_node[sp] = in2; stack_t[sp] = it2; ++sp; }
                    if (nin > 1) { stack_node[sp] = in1; stack_t[sp] = it1; ++sp; }
                    next = in0;
                }
            }
            while (next < 0 && sp > 0) {
                --sp;
                if (stack_t[sp] <= hit_t) next = stack_node[sp];
            }
            if (next < 0) break;
            ni = next;
        }
    }
done:
    *out_t = hit_id >= 0 ? hit_t : INFINITY;
    *out_id = hit_id;
}

// The convention's active ray (viewer/tracing.py): tmin < tmax, finite origin, direction and tmin
// (tmax may be +inf). Inactive rays miss without a traversal.
inline bool ray_active(float4 ot, float4 dt) {
    return dt.w > ot.w && isfinite(ot.w) && all(isfinite(ot.xyz)) && all(isfinite(dt.xyz));
}

// One work-item per ray. The group's first work-item also counts the group's active rays and adds
// them to *active: one global atomic per work-group and no barrier (a barrier makes PoCL split the
// kernel into regions and keep each work-item's state across them).
inline void trace_item(__global const float4 *nodes, __global const float4 *blocks, __global const float4 *ray_o,
                       __global const float4 *ray_d, __global float *out_t, __global int *out_id, const int n,
                       __global int *active, const bool any_hit) {
    int i = get_global_id(0);
    if (get_local_id(0) == 0) {
        int end = min(i + WG, n), count = 0;
        for (int j = i; j < end; ++j) count += ray_active(ray_o[j], ray_d[j]) ? 1 : 0;
        if (count > 0) atomic_add(active, count);
    }
    if (i >= n) return;
    float4 ot = ray_o[i], dt = ray_d[i];
    float t = INFINITY;
    int id = -1;
    if (ray_active(ot, dt)) trace_ray(nodes, blocks, ot, dt, any_hit, &t, &id);
    out_t[i] = t;
    out_id[i] = id;
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void trace_closest(__global const float4 *nodes, __global const float4 *blocks, __global const float4 *ray_o,
                   __global const float4 *ray_d, __global float *out_t, __global int *out_id, const int n,
                   __global int *active) {
    trace_item(nodes, blocks, ray_o, ray_d, out_t, out_id, n, active, false);
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void trace_any(__global const float4 *nodes, __global const float4 *blocks, __global const float4 *ray_o,
               __global const float4 *ray_d, __global float *out_t, __global int *out_id, const int n,
               __global int *active) {
    trace_item(nodes, blocks, ray_o, ray_d, out_t, out_id, n, active, true);
}

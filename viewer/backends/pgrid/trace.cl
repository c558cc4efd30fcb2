// pgrid: one work-group per chunk of at most WG rays that share a tile of the point-centred grid
// (viewer/accel/pointgrid.cl). The tile's triangles are staged in local memory WG at a time
// (four per SoA block, stage.cl), nearest to the centre first, and every ray of the chunk tests
// every staged triangle, four at a time (watertight rt_intersect_triangle4).
//  * any hit (shadow rays towards a light): slab by slab; a ray stops at its first hit; the chunk
//    stops when all its rays have stopped or the next slab starts beyond the farthest point of its
//    rays.
//  * closest hit (primary rays from the eye): the tile's pairs, sorted by slab and then distance
//    level (pointgrid.cl pg_levels), are staged in batches straight through the slabs; before
//    each batch and each staged block of four, a ray whose hit lies nearer to the centre than the
//    lower bound of what follows is done (the slab check); the chunk stops when all are done.
//  * both: a ray tests a staged triangle only when its own angles lie in the triangle's angular
//    box (tri_box: the box it was binned by), the binning test at full resolution.
// A tile without triangles (background) writes misses at once; empty slabs are skipped.
// Chunks whose key is the "outside" tile (ntiles) are not traced: those rays go another way. The
// work-groups are persistent: each takes chunks group, group + groups, ... up to the chunk count
// on the device, so the launch is sized without reading that count back.
// A chunk of more than WG rays (load balancing off: whole tiles) is traced WG rays at a time.
// With COUNT_TESTS, each ray's triangle tests are written to `tests`.
#include "geometry.cl"
#include "stage.cl"

#ifndef WG
#define WG 64
#endif

typedef struct {
    float4 centre;
    float4 fwd;
    float4 up;
    float4 right;
    float4 rect;
    float4 slab;
    int4 res;
} PGrid;

#define MAX_SLABS 256

// A triangle's angular box (pointgrid.cl pg_tri: alpha min, max, theta min, max, grown by the
// rays' margin) is staged by stage_box (stage.cl); a ray tests only the triangles whose box holds
// its angles (box_lanes).
// Stages triangle `slot` (vertices, slot id, angular box) as entry k of the local arrays.
inline void pg_stage(__local float4 *sv, __local int *sslot, __local float4 *sbox, uint k,
                     __global const float4 *tris, __global const float4 *tri_box, uint slot) {
    sslot[k] = (int)slot;
    stage_triangle(sv, k, tris, slot);
    stage_box(sbox, k, tri_box[slot]);
}

// A lower bound of the distance from E of the triangle of a sorted pair key ((cell << up.w) |
// distance level, cell = tile * slabs + slab; pointgrid.cl pg_tri_write): where its slab starts,
// and where its level starts when the build made levels (lv.y >= 0: pg_levels). Monotone in the
// key within a tile (slab and level are both monotone in the triangle's distance bound), so the
// bound of a tile's pair also bounds every later pair of the tile.
inline float pg_pair_lo(const PGrid *g, uint key, uint cell0, float4 lv) {
    uint qb = (uint)g->up.w;
    int s = (int)((key >> qb) - cell0);
    float lo = g->slab.w + ((float)s - 0.001f) * g->slab.x;
    uint q = qb ? key & ((1u << qb) - 1u) : 0u;
    if (lv.y >= 0.0f && q)
        lo = fmax(lo, as_float(as_uint(lv.x) + (q << (uint)lv.y)) * (1.0f - 1e-5f));
    return lo;
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_trace(__global const PGrid *grid, __global const uint *chunk_key, __global const uint *chunk_start,
              __global const uint *chunk_len, __global const uint *ray_index, __global const uint *cell_start,
              __global const uint *refs, __global const float4 *tris, __global const float4 *ray_o,
              __global const float4 *ray_d, __global float *out_t, __global int *out_id, const int any_hit,
              __global int *tests_out, const int from_far, __global const uint *keys,
              __global const float4 *levels, __global const float *ray_alpha, __global const float *ray_theta,
              __global const float4 *tri_box, __global const uint *chunk_count) {
    __local float4 sv[9 * (WG / 4)];  // staged triangles, four per block in SoA form
    __local int sslot[WG];
    __local float slo[WG];  // closest hit: lower bounds of the staged triangles' distances from E
    __local float4 sbox[WG];  // the staged triangles' angular boxes, four per block in SoA form
    __local int remaining;
    __local uint far_bits;
    PGrid g = *grid;
    uint lid = get_local_id(0);
    uint ntiles = (uint)(g.res.x * g.res.y);
    // persistent: the work-groups take chunks c, c + groups, ... up to the chunk count the build
    // left on the device (the launch is sized without reading it back)
    uint nchunks = *chunk_count;
    for (uint c = get_group_id(0); c < nchunks; c += get_num_groups(0)) {
    uint key = chunk_key[c];
    if (key >= ntiles) break;  // uniform for the work-group; keys are sorted, so every later chunk too
    uint len = chunk_len[c];
    uint cell0 = key * (uint)g.res.z;
    if (cell_start[cell0] == cell_start[cell0 + (uint)g.res.z]) {
        // no triangle in the whole tile (often most of a view: sky, background): every ray of the
        // chunk misses, without the slab loop and its barriers (uniform for the work-group)
        for (uint k = lid; k < len; k += WG) {
            uint ri = ray_index[chunk_start[c] + k];
            out_t[ri] = INFINITY;
            out_id[ri] = -1;
#ifdef COUNT_TESTS
            tests_out[ri] = 0;
#endif
        }
        continue;
    }
    // a chunk longer than WG (no load balancing: one work-group per tile) is done WG rays at a time
    for (uint rb = 0; rb < len; rb += WG) {
    barrier(CLK_LOCAL_MEM_FENCE);
    bool mine = rb + lid < len;
    uint ri = mine ? ray_index[chunk_start[c] + rb + lid] : 0u;
    float4 ot = mine ? ray_o[ri] : (float4)(0.0f);
    float4 dt = mine ? ray_d[ri] : (float4)(0.0f, 0.0f, 1.0f, -1.0f);
    bool active = mine && dt.w > ot.w;
    float ra = mine ? ray_alpha[ri] : 0.0f, rth = mine ? ray_theta[ri] : 0.0f;  // the angles of u
    float tmin = ot.w, hit_t = dt.w;
    int hit_id = -1;
    int tests = 0;
    RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
    float3 E = g.centre.xyz;
    float dlen = length(dt.xyz);
    // signed distance along the ray's direction from E of o + t d, and the line's distance from E
    float3 w = ot.xyz - E;
    float base = dlen > 0.0f ? rt_dot(w, dt.xyz) / dlen : 0.0f;
    float h = dlen > 0.0f ? length(rt_cross(w, dt.xyz)) / dlen : 0.0f;
    bool outward = base + tmin * dlen >= 0.0f;
    float far = fmax(fabs(base + tmin * dlen), fabs(base + fmin(hit_t, 3.0e38f) * dlen)) + h;
    if (lid == 0) { remaining = 0; far_bits = 0u; }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (active) {
        atomic_inc(&remaining);
        atomic_max(&far_bits, as_uint(fmin(far, 3.0e38f)));
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    bool done = !active;
    float chunk_far = as_float(far_bits);
    // closest hit: front to back (the slab check needs it). Any hit: front to back, or with
    // `from_far` from the farthest slab the chunk's rays reach back towards the centre (occluders
    // next to the surface points first: the better order when the light is outside the scene)
    int s_far = clamp((int)floor((chunk_far - g.slab.w) * g.slab.y + 0.001f), 0, g.res.z - 1);
    bool back = any_hit && from_far;
    float4 lv = levels[0];
    if (!any_hit) {
        // closest hit: the tile's pairs are contiguous and sorted by (slab, distance level), both
        // monotone in the triangle's distance lower bound from E, so they are staged WG at a time
        // straight through the slabs (two barriers per batch, none per slab: on a CPU device a
        // barrier region is a pass over the work-group, and a tile of a few large triangles in
        // several slabs, the ground and the wall, paid one per slab). Before each batch, every
        // triangle from it on is at least `lo` from E (its first pair's slab start and level):
        // a hit nearer than that is final (the slab check, at batch granularity)
        // (and again before each block of four: the staged `slo`, so a ray stops within a batch)
        uint pa = cell_start[cell0], pb = cell_start[cell0 + (uint)g.res.z];
        for (uint base_i = pa; base_i < pb; base_i += WG) {
            float lo = pg_pair_lo(&g, keys[base_i], cell0, lv);
            if (!done && hit_id >= 0 && outward && base + hit_t * dlen + h < lo) {
                done = true;
                atomic_dec(&remaining);
            }
            barrier(CLK_LOCAL_MEM_FENCE);  // also: every ray is done with the previous batch
            if (remaining == 0 || lo > chunk_far) break;  // same value in every work-item
            uint cnt = min((uint)WG, pb - base_i);
            if (lid < cnt) {
                slo[lid] = pg_pair_lo(&g, keys[base_i + lid], cell0, lv);
                pg_stage(sv, sslot, sbox, lid, tris, tri_box, refs[base_i + lid]);
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (!done && lo <= far) {  // this ray's segment may reach these triangles
                for (uint k = 0; k < cnt; k += 4) {
                    float t;
                    if (hit_id >= 0 && outward && base + hit_t * dlen + h < slo[k]) {
                        done = true;  // every triangle from k on is at least slo[k] from E
                        atomic_dec(&remaining);
                        break;
                    }
                    int4 lanes = stage_lanes(k, cnt) & box_lanes(sbox + k, ra, rth);
                    if (!any(lanes)) continue;  // u outside the four triangles' angular boxes
                    tests += (int)(-(lanes.x + lanes.y + lanes.z + lanes.w));
                    int lane = rt_intersect_triangle4_local(&r, sv + 9 * (k / 4), lanes, tmin, hit_t, &t);
                    if (lane >= 0) {
                        hit_t = t;
                        hit_id = sslot[k + lane];
                    }
                }
            }
        }
    } else {
    // any hit: the slabs with triangles in visiting order; empty slabs are skipped by a plain loop (no
    // barrier inside: PoCL runs every iteration of a loop holding a barrier once per work-item,
    // which made the empty slabs of a tile cost as much as its tests)
    int step = 0;
    for (;;) {
        int s = -1;
        uint a = 0u, b = 0u;
        for (; step < g.res.z; ++step) {
            int t = back ? s_far - step : step;
            if (t < 0) { step = g.res.z; break; }
            a = cell_start[cell0 + t];
            b = cell_start[cell0 + t + 1];
            if (a != b) { s = t; break; }
        }
        if (s < 0) break;  // same value in every work-item
        ++step;
        float slab_lo = g.slab.w + ((float)s - 0.001f) * g.slab.x;
        if (remaining == 0 || slab_lo > chunk_far) break;  // same value in every work-item
        for (uint base_i = a; base_i < b; base_i += WG) {
            uint cnt = min((uint)WG, b - base_i);
            barrier(CLK_LOCAL_MEM_FENCE);
            if (lid < cnt) {
                pg_stage(sv, sslot, sbox, lid, tris, tri_box, refs[base_i + lid]);
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (!done && slab_lo <= far) {  // this ray's segment may reach this slab
                for (uint k = 0; k < cnt; k += 4) {
                    float t;
                    int4 lanes = stage_lanes(k, cnt) & box_lanes(sbox + k, ra, rth);
                    if (!any(lanes)) continue;  // u outside the four triangles' angular boxes
                    tests += (int)(-(lanes.x + lanes.y + lanes.z + lanes.w));
                    int lane = rt_intersect_triangle4_local(&r, sv + 9 * (k / 4), lanes, tmin, hit_t, &t);
                    if (lane >= 0) {  // any hit: this ray is done
                        hit_t = t;
                        hit_id = sslot[k + lane];
                        done = true;
                        atomic_dec(&remaining);
                        break;
                    }
                }
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (remaining == 0) break;
        }
    }
    }
    if (mine) {
        out_t[ri] = hit_id >= 0 ? hit_t : INFINITY;
        out_id[ri] = hit_id;
#ifdef COUNT_TESTS
        tests_out[ri] = tests;
#endif
    }
    }
}  // chunks
}

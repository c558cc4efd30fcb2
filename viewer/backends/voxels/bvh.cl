// Voxel BVH traversal (viewer/accel/voxel_bvh.py NODE_DTYPE as 9 uints per node): strictly front
// to back, the near child is the one on the ray's side of the split axis (child 1 when the
// direction is negative on it), the far child is pushed with its [entry, exit]. A popped entry
// starts after everything searched so far (children are separated by their split plane), so
// t_done rises to its entry; leaves raise it to their exit. Restart: from the root with the
// child boxes clipped to [t_done, tmax].
#include "common.cl"

inline void traverse_bvh(__global const uint *nodes, __global const ushort *leaves, int root, ulong R,
                         float3 rlo, float3 rhi, const VRay *r, float tmin, float tmax, int any_hit, Best *best,
                         Rec *rec) {
    float2 rs = vx_slab(r, rlo, rhi);
    float t_done = fmax(rs.x, tmin);
    float t_end = fmin(rs.y, tmax);
    if (!(t_done < t_end)) return;
    ShortStack st;
    for (int iter = 0; iter < MAX_ITER; ++iter) {  // one pass per (re)start
        st_reset(&st);
        int ref = root;
        float exit_t = t_end;
        while (true) {
            if (ref >= 0) {
                REC(x);
                __global const uint *nd = nodes + 9 * ref;
                __global const ushort *b = (__global const ushort *)nd;
                float3 lo0 = (float3)(b[0], b[1], b[2]), lo1 = (float3)(b[3], b[4], b[5]);
                float3 hi0 = (float3)(b[6], b[7], b[8]), hi1 = (float3)(b[9], b[10], b[11]);
                int c0 = (int)nd[6], c1 = (int)nd[7];
                int axis = (int)nd[8];
                float2 s0 = vx_slab(r, lo0, hi0), s1 = vx_slab(r, lo1, hi1);
                float a0 = fmax(s0.x, t_done), a1 = fmax(s1.x, t_done);
                float e0 = fmin(s0.y, tmax), e1 = fmin(s1.y, tmax);
                bool h0 = a0 < e0 && a0 <= best->t, h1 = a1 < e1 && a1 <= best->t;
                if (vx_icomp(r->neg, axis)) {  // near = child 1
                    int tc = c0; c0 = c1; c1 = tc;
                    bool th = h0; h0 = h1; h1 = th;
                    float ta = a0; a0 = a1; a1 = ta;
                    float te = e0; e0 = e1; e1 = te;
                }
                if (h0) {
                    if (h1) st_push(&st, c1, a1, e1);
                    ref = c0;
                    exit_t = e0;
                    continue;
                }
                if (h1) {
                    ref = c1;
                    exit_t = e1;
                    continue;
                }
            } else {
                REC(y);
                if (vx_leaf(r, leaves, ~ref, tmin, tmax, R, best) && any_hit) return;
                t_done = fmax(t_done, exit_t);
            }
            // pop the nearest pending child that can still hold the first hit
            float a, b;
            if (!st_pop_live(&st, best, &t_done, &ref, &a, &b, rec)) break;
            exit_t = b;
        }
        if (!st_restart(&st, t_done, best, t_end, rec)) return;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1))) void trace(VX_KERNEL_ARGS) {
    VX_KERNEL_BODY(traverse_bvh(nodes, leaves, root, (ulong)R, root_lo.xyz, root_hi.xyz, &r, tmin, tmax, any_hit,
                                &best, &rec))
}

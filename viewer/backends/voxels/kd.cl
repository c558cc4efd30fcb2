// Voxel KD-tree traversal (viewer/accel/voxel_kd.py NODE_DTYPE as 3 uints per node) with a short
// stack and restart (Horn et al. 2007): the node's ray interval [a, b] is split at the plane
// distance ts; the near child (lower side when the direction is positive on the axis) gets
// [a, ts], the far child [ts, b] is pushed. A leaf (or an empty cell) ends at b, which becomes
// t_done; a restart descends from the root with [t_done, t_end].
#include "common.cl"

#define KD_EMPTY ((int)0x80000000)

inline void traverse_kd(__global const uint *nodes, __global const ushort *leaves, int root, ulong R,
                        float3 rlo, float3 rhi, const VRay *r, float tmin, float tmax, int any_hit, Best *best,
                        Rec *rec) {
    float2 rs = vx_slab(r, rlo, rhi);
    float t_done = fmax(rs.x, tmin);
    float t_end = fmin(rs.y, tmax);
    if (!(t_done < t_end)) return;
    ShortStack st;
    for (int iter = 0; iter < MAX_ITER; ++iter) {
        st_reset(&st);
        int ref = root;
        float a = t_done, b = t_end;
        while (true) {
            if (ref >= 0) {
                REC(x);
                __global const uint *nd = nodes + 3 * ref;
                uint w = nd[2];
                int axis = (int)(w >> 16);
                float plane = (float)(w & 0xffffu);
                int neg = vx_icomp(r->neg, axis);
                int cn = (int)nd[neg], cf = (int)nd[1 - neg];
                float ts = (plane - vx_comp(r->o, axis)) * vx_comp(r->inv, axis);
                if (ts >= b) {
                    ref = cn;
                } else if (ts <= a) {
                    ref = cf;
                } else {
                    if (cf != KD_EMPTY && ts <= best->t) st_push(&st, cf, ts, b);
                    ref = cn;
                    b = ts;
                }
                continue;
            }
            if (ref != KD_EMPTY) {
                REC(y);
                if (vx_leaf(r, leaves, ~ref, tmin, tmax, R, best) && any_hit) return;
            }
            t_done = fmax(t_done, b);
            if (!st_pop_live(&st, best, &t_done, &ref, &a, &b, rec)) break;
        }
        if (!st_restart(&st, t_done, best, t_end, rec)) return;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1))) void trace(VX_KERNEL_ARGS) {
    VX_KERNEL_BODY(traverse_kd(nodes, leaves, root, (ulong)R, root_lo.xyz, root_hi.xyz, &r, tmin, tmax, any_hit,
                               &best, &rec))
}

// Voxel octree traversal (viewer/accel/voxel_octree.py NODE_DTYPE as 5 uints per node). At a node
// with ray interval [a, b] the children are visited in ray order: the octant at a follows from
// the midplane distances tm (past a plane: the half the direction points to), and each crossing
// tm in (s, b) flips that axis. Leaf children are tested in place; on descending into an
// interior child whose segment ends at e < b, the current node is pushed with its remaining
// interval [e, b] (Laine & Karras), so a pop resumes the node at e. Restart: from the root with
// [t_done, t_end].
#include "common.cl"

inline void traverse_octree(__global const uint *nodes, __global const ushort *leaves, int root, ulong R,
                            float3 rlo, float3 rhi, const VRay *r, float tmin, float tmax, int any_hit, Best *best,
                            Rec *rec) {
    float2 rs = vx_slab(r, rlo, rhi);
    float t_done = fmax(rs.x, tmin);
    float t_end = fmin(rs.y, tmax);
    if (!(t_done < t_end)) return;
    ShortStack st;
    for (int iter = 0; iter < MAX_ITER; ++iter) {
        st_reset(&st);
        int node = 0;
        float a = t_done, b = t_end;
        while (true) {
            bool descended = false;
            if (root >= 0) {
                REC(x);
                __global const uint *nd = nodes + 5 * node;
                __global const ushort *hs = (__global const ushort *)nd;
                float3 org = (float3)(hs[0], hs[1], hs[2]);
                float hsz = (float)(R >> (hs[3] + 1));
                int first_child = (int)nd[2], first_leaf = (int)nd[3];
                uint cmask = nd[4] & 0xffu, lmask = (nd[4] >> 8) & 0xffu;
                float3 tm = (org + hsz - r->o) * r->inv;
                int oct = 0;
                if ((tm.x <= a) != (r->neg.x != 0)) oct |= 1;
                if ((tm.y <= a) != (r->neg.y != 0)) oct |= 2;
                if ((tm.z <= a) != (r->neg.z != 0)) oct |= 4;
                float s = a;
                for (int seg = 0; seg < 4 && s < b && s <= best->t; ++seg) {
                    float tn = b;
                    if (tm.x > s) tn = fmin(tn, tm.x);
                    if (tm.y > s) tn = fmin(tn, tm.y);
                    if (tm.z > s) tn = fmin(tn, tm.z);
                    uint below = (1u << oct) - 1u;
                    if ((lmask >> oct) & 1u) {
                        REC(y);
                        if (vx_leaf(r, leaves, first_leaf + popcount(lmask & below), tmin, tmax, R, best) && any_hit)
                            return;
                        t_done = fmax(t_done, tn);
                    } else if ((cmask >> oct) & 1u) {
                        if (tn < b) st_push(&st, node, tn, b);
                        node = first_child + (int)popcount(cmask & below);
                        a = s;
                        b = tn;
                        descended = true;
                        break;
                    } else {
                        t_done = fmax(t_done, tn);
                    }
                    if (tm.x == tn) oct ^= 1;
                    if (tm.y == tn) oct ^= 2;
                    if (tm.z == tn) oct ^= 4;
                    s = tn;
                }
                if (descended) continue;
                t_done = fmax(t_done, fmin(b, best->t));
            } else {  // the whole set is one leaf
                REC(y);
                vx_leaf(r, leaves, 0, tmin, tmax, R, best);
                return;
            }
            if (!st_pop_live(&st, best, &t_done, &node, &a, &b, rec)) break;
        }
        if (!st_restart(&st, t_done, best, t_end, rec)) return;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1))) void trace(VX_KERNEL_ARGS) {
    VX_KERNEL_BODY(traverse_octree(nodes, leaves, root, (ulong)R, root_lo.xyz, root_hi.xyz, &r, tmin, tmax,
                                   any_hit, &best, &rec))
}

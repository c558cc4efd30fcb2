// Shared by the voxel traversal kernels (bvh.cl, kd.cl, octree.cl): the ray in grid units, the
// voxel slab test, the leaf test, the short stack and the per-ray step record.
//
// Hit rule (the same in the float64 reference of tests/test_voxel_trace.py): voxel box
// [v, v + 1] gives the slab interval [e, x] (reciprocals of zero direction components are
// +-1e30 with the component's sign, so a ray lying in a face plane enters the voxel on the side
// its direction's sign points to); it is hit when max(e, tmin) < min(x, tmax); the first voxel
// has the smallest max(e, tmin), ties broken by the smallest key x + R * (y + R * z).
//
// Short stack (STACK entries, 4-8): a ring; pushing onto a full stack overwrites the oldest
// (farthest) entry and marks the walk incomplete; when the stack runs empty on an incomplete
// walk the traversal restarts from the root with the ray interval starting at t_done, the end
// of the part of the ray already searched (Horn et al. 2007).
//
// Buffers: leaves = LEAF_DTYPE (viewer/accel/voxel_leaves.py) as ushort (28 per leaf), voxel_tri
// int per voxel in leaf order; hdr float[8] = grid origin xyz, scale, 0...; rays and hits as
// viewer/cl/transfer.py lays them out; out_vox = leaf-order voxel index (-1 miss);
// record (RECORD builds only) = int4 per ray: interior steps, leaf tests, pops, restarts.
#pragma OPENCL FP_CONTRACT OFF

#ifndef STACK
#define STACK 8
#endif
#ifndef WG
#define WG 64
#endif
#define MAX_ITER (1 << 22)
// `leave` (secondary rays): the run of voxels the ray is in at its start, each beginning within
// `gap` voxel widths of the previous one's exit, is the surface the ray leaves and is skipped; a
// ray still in such a run after LEAVE_MAX voxels reports no hit.
#define LEAVE_MAX 32

typedef struct {
    float3 o;
    float3 inv;
    int3 neg;  // 1 where the direction is negative (signbit of the safe reciprocal)
    float len;  // |direction| in grid units: t per voxel width = 1 / len
} VRay;

inline float vx_rcp(float x) {
    float s = signbit(x) ? -1.0f : 1.0f;
    return fabs(x) < 1e-30f ? s * 1e30f : 1.0f / x;
}

inline float vx_comp(float3 v, int k) { return k == 0 ? v.x : (k == 1 ? v.y : v.z); }
inline int vx_icomp(int3 v, int k) { return k == 0 ? v.x : (k == 1 ? v.y : v.z); }

// slab interval of the box [lo, hi]
inline float2 vx_slab(const VRay *r, float3 lo, float3 hi) {
    float3 a = (lo - r->o) * r->inv;
    float3 b = (hi - r->o) * r->inv;
    float3 tn = (float3)(r->neg.x ? b.x : a.x, r->neg.y ? b.y : a.y, r->neg.z ? b.z : a.z);
    float3 tf = (float3)(r->neg.x ? a.x : b.x, r->neg.y ? a.y : b.y, r->neg.z ? a.z : b.z);
    return (float2)(fmax(fmax(tn.x, tn.y), tn.z), fmin(fmin(tf.x, tf.y), tf.z));
}

typedef struct {
    float t;    // entry distance of the best voxel (tmax while none)
    float x;    // its exit distance
    ulong key;  // its key
    int idx;    // its leaf-order index, -1 none
} Best;

// Tests the voxels of leaf li; returns true when one of them became the best.
inline bool vx_leaf(const VRay *r, __global const ushort *leaves, int li, float tmin, float tmax, ulong R,
                    Best *best) {
    __global const ushort *lv = leaves + 28 * li;
    __global const int *meta = (__global const int *)(lv + 24);
    int first = meta[0], count = meta[1];
    bool found = false;
    for (int k = 0; k < count; ++k) {
        float3 v = (float3)((float)lv[3 * k], (float)lv[3 * k + 1], (float)lv[3 * k + 2]);
        float2 s = vx_slab(r, v, v + 1.0f);
        float e = fmax(s.x, tmin);
        if (e < fmin(s.y, tmax)) {
            ulong key = (ulong)lv[3 * k] + R * ((ulong)lv[3 * k + 1] + R * (ulong)lv[3 * k + 2]);
            if (e < best->t || (e == best->t && key < best->key)) {
                best->t = e;
                best->x = fmin(s.y, tmax);
                best->key = key;
                best->idx = first + k;
                found = true;
            }
        }
    }
    return found;
}

// Short stack of (ref, a, b) entries.
typedef struct {
    int ref[STACK];
    float a[STACK], b[STACK];
    int head, size;
    bool dropped;
} ShortStack;

inline void st_push(ShortStack *s, int ref, float a, float b) {
    s->ref[s->head] = ref;
    s->a[s->head] = a;
    s->b[s->head] = b;
    s->head = (s->head + 1) % STACK;
    if (s->size < STACK) ++s->size; else s->dropped = true;
}

inline void st_pop(ShortStack *s, int *ref, float *a, float *b) {
    s->head = (s->head + STACK - 1) % STACK;
    --s->size;
    *ref = s->ref[s->head];
    *a = s->a[s->head];
    *b = s->b[s->head];
}

// Step record (RECORD builds): per ray the counts c = (interior steps, leaf tests, pops, restarts)
// and, with SEQ_LEN > 0, the first SEQ_LEN step kinds in order (1 interior, 2 leaf, 3 pop,
// 4 restart) for the lockstep (SIMD lane utilisation) model of viewer/bench/lockstep.py. Entries
// after a ray's last step are left as they were (readers take the length from the counts; the
// host's trace_arrays clears the buffer first), so a ray writes only the steps it takes.
#ifndef SEQ_LEN
#define SEQ_LEN 0
#endif
typedef struct {
    int4 c;
    int n;
    __global uchar *seq;
} Rec;
#define REC_KIND_x 1
#define REC_KIND_y 2
#define REC_KIND_z 3
#define REC_KIND_w 4
#ifdef RECORD
#define REC(k) do { ++rec->c.k; if (SEQ_LEN > 0 && rec->n < SEQ_LEN) rec->seq[rec->n] = REC_KIND_##k; ++rec->n; } while (0)
#define REC_STORE record[i] = rec.c;
#else
#define REC(k)
#define REC_STORE
#endif

// The short stack's pop-and-restart protocol, shared by the kd-tree, octree and BVH walks (Horn et
// al. 2007). st_reset starts a pass from the root. st_pop_live pops the nearest pending entry
// that can still hold the first hit (its entry a <= the best t so far), raising t_done to that
// entry; false when none is left (the pass ends). st_restart: the pass dropped entries (stack
// overflow) and the part of the ray before the hit is not done yet, so the walk starts again from
// the root with [t_done, t_end].
inline void st_reset(ShortStack *s) {
    s->head = 0;
    s->size = 0;
    s->dropped = false;
}

inline bool st_pop_live(ShortStack *s, const Best *best, float *t_done, int *ref, float *a, float *b, Rec *rec) {
    while (s->size > 0) {
        st_pop(s, ref, a, b);
        REC(z);
        if (*a <= best->t) {
            *t_done = fmax(*t_done, *a);
            return true;
        }
    }
    return false;
}

inline bool st_restart(const ShortStack *s, float t_done, const Best *best, float t_end, Rec *rec) {
    if (!(s->dropped && t_done < fmin(best->t, t_end))) return false;
    REC(w);
    return true;
}

// The ray in grid units; returns false for inactive rays. tmin is raised by `bias` voxel widths
// (the backend passes it for secondary rays, which start on the voxel surface they leave).
inline bool vx_ray(__constant float *hdr, float4 ot, float4 dt, float bias, VRay *r, float *tmin,
                   float *tmax) {
    float3 org = (float3)(hdr[0], hdr[1], hdr[2]);
    float sc = hdr[3];
    float3 o = (ot.xyz - org) * sc;
    float3 d = dt.xyz * sc;
    r->o = o;
    r->inv = (float3)(vx_rcp(d.x), vx_rcp(d.y), vx_rcp(d.z));
    r->neg = (int3)(signbit(r->inv.x) ? 1 : 0, signbit(r->inv.y) ? 1 : 0, signbit(r->inv.z) ? 1 : 0);
    r->len = length(d);
    *tmin = ot.w;
    *tmax = dt.w;
    if (bias > 0.0f) *tmin += bias / length(d);
    return isfinite(ot.x + ot.y + ot.z + ot.w + dt.x + dt.y + dt.z) && dt.w > ot.w && *tmax > *tmin;
}

#define VX_KERNEL_ARGS                                                                                     \
    __global const uint *nodes, __global const ushort *leaves, __global const int *voxel_tri,             \
    __constant float *hdr, const int root, const int R, const float4 root_lo, const float4 root_hi,      \
    __global const float4 *ray_o, __global const float4 *ray_d, __global float *out_t, __global int *out_tri, \
    __global int *out_vox, __global int4 *record, __global uchar *seq, const int n, const int any_hit,            \
    const float bias, const int leave, const float gap

#define VX_KERNEL_BODY(TRAVERSE)                                                                           \
    int i = get_global_id(0);                                                                               \
    if (i >= n) return;                                                                                     \
    Rec rec;                                                                                                \
    rec.c = (int4)(0, 0, 0, 0);                                                                             \
    rec.n = 0;                                                                                              \
    rec.seq = seq + (size_t)i * (SEQ_LEN > 0 ? SEQ_LEN : 1);                                                \
    VRay r;                                                                                                 \
    float tmin, tmax;                                                                                       \
    Best best;                                                                                              \
    best.idx = -1;                                                                                          \
    best.key = 0;                                                                                           \
    if (vx_ray(hdr, ray_o[i], ray_d[i], bias, &r, &tmin, &tmax)) {                                          \
        float t0 = tmin;                                                                                    \
        for (int pass = 0; pass < LEAVE_MAX; ++pass) {                                                      \
            best.t = tmax;                                                                                  \
            best.idx = -1;                                                                                  \
            tmin = t0;                                                                                      \
            TRAVERSE;                                                                                       \
            if (!leave || best.idx < 0 || best.t > t0 + gap / r.len) break;                                 \
            t0 = best.x;                                                                                    \
            if (pass == LEAVE_MAX - 1) best.idx = -1;                                                       \
        }                                                                                                   \
    }                                                                                                       \
    out_t[i] = best.idx >= 0 ? best.t : INFINITY;                                                           \
    out_tri[i] = best.idx >= 0 ? voxel_tri[best.idx] : -1;                                                  \
    out_vox[i] = best.idx;                                                                                  \
    REC_STORE

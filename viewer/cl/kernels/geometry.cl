// Ray/box and ray/triangle tests shared by the OpenCL backends; the same conventions and the
// same float operations as viewer/shaders/intersect.glsl, so glsl and the CL backends agree
// bit for bit wherever the compilers do (FP contraction is off here: no fused multiply-adds).
//  * Watertight ray/triangle test (Woop, Benthin, Wald 2013); when an edge function U, V or W
//    is exactly 0 the three are recomputed in double (cl_khr_fp64), so rays through shared
//    edges and vertices never leak. Distance from the plane equation (as accurate as Embree for
//    grazing rays) with a correctly rounded normal (rt_cross_rounded: float32 edge products are exact
//    in double, only the difference rounds; a float32 cross product cancels on needles and slivers),
//    T/det when dot(n, d) == 0. Hits only for tmin < t < tmax.
//  * Conservative slab test: far distance scaled by 1 + 2*gamma(3) (Ize 2013); reciprocals of
//    zero direction components replaced by +-1e30 with the component's sign (no 0 * inf).
//    Near/far planes are picked by the direction's sign (same values as glsl's min/max for
//    real boxes), so an empty box (min = +inf, max = -inf) never hits.
#pragma OPENCL FP_CONTRACT OFF
#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define RT_HAVE_FP64 1
#endif

#define RT_GAMMA3_SCALE (1.0f + 2.0f * (3.0f * 5.960464477539063e-08f) / (1.0f - 3.0f * 5.960464477539063e-08f))

typedef struct {
    float3 o;
    float3 d;
    float3 inv;      // safe reciprocals of d
    int3 neg;        // 1 where inv < 0 (near plane = max)
    int kx, ky, kz;  // watertight test: kz = dominant axis, kx/ky the others (swapped if d[kz] < 0)
    float Sx, Sy, Sz;
} RayPre;

inline float rt_safe_rcp(float x) {
    float s = signbit(x) ? -1.0f : 1.0f;  // keeps the sign of -0.0
    return fabs(x) < 1e-30f ? s * 1e30f : 1.0f / x;
}

inline float rt_comp(float3 v, int k) {
    return k == 0 ? v.x : (k == 1 ? v.y : v.z);
}

inline RayPre rt_prepare_ray(float3 o, float3 d) {
    RayPre r;
    r.o = o;
    r.d = d;
    r.inv = (float3)(rt_safe_rcp(d.x), rt_safe_rcp(d.y), rt_safe_rcp(d.z));
    r.neg = (int3)(signbit(r.inv.x) ? 1 : 0, signbit(r.inv.y) ? 1 : 0, signbit(r.inv.z) ? 1 : 0);
    float3 ad = fabs(d);
    int kz = (ad.x > ad.y) ? ((ad.x > ad.z) ? 0 : 2) : ((ad.y > ad.z) ? 1 : 2);
    int kx = (kz + 1) % 3;
    int ky = (kx + 1) % 3;
    if (rt_comp(d, kz) < 0.0f) { int tmp = kx; kx = ky; ky = tmp; }
    r.kx = kx; r.ky = ky; r.kz = kz;
    float dz = rt_comp(d, kz);
    r.Sx = rt_comp(d, kx) / dz;
    r.Sy = rt_comp(d, ky) / dz;
    r.Sz = 1.0f / dz;
    return r;
}

inline float3 rt_cross(float3 a, float3 b) {
    return (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

// cross(a, b) rounded once per component (see intersect.glsl: crossRounded)
inline float3 rt_cross_rounded(float3 a, float3 b) {
#ifdef RT_HAVE_FP64
    double3 da = convert_double3(a), db = convert_double3(b);
    return convert_float3((double3)(da.y * db.z - da.z * db.y, da.z * db.x - da.x * db.z,
                                    da.x * db.y - da.y * db.x));
#else
    return rt_cross(a, b);
#endif
}

inline float rt_dot(float3 a, float3 b) {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

// A triangle with two equal vertices (a point or a segment; common far from the origin, where
// float32 snaps a small mesh onto a coarse lattice: 91% of the dragon at 1e6) is never hit: with
// A == B the watertight test's W is exactly 0 and U == -V, so (in float and in the double fallback)
// det = U + V + W = 0 and the test below rejects it. Acceleration structures skip binning it.
inline bool rt_two_equal_vertices(float3 a, float3 b, float3 c) {
    return all(a == b) || all(b == c) || all(c == a);
}

// True and *t (tmin < *t < tmax) on a hit; *bary (when not null): the barycentric weights (V, W) / det
// of v1 and v2, as intersect.glsl's intersectTriangle returns them.
inline bool rt_intersect_triangle_bary(const RayPre *r, float3 v0, float3 v1, float3 v2, float tmin, float tmax,
                                       float *t, float2 *bary) {
    float3 A = v0 - r->o, B = v1 - r->o, C = v2 - r->o;
    float Akz = rt_comp(A, r->kz), Bkz = rt_comp(B, r->kz), Ckz = rt_comp(C, r->kz);
    float Ax = rt_comp(A, r->kx) - r->Sx * Akz, Ay = rt_comp(A, r->ky) - r->Sy * Akz;
    float Bx = rt_comp(B, r->kx) - r->Sx * Bkz, By = rt_comp(B, r->ky) - r->Sy * Bkz;
    float Cx = rt_comp(C, r->kx) - r->Sx * Ckz, Cy = rt_comp(C, r->ky) - r->Sy * Ckz;
    float U = Cx * By - Cy * Bx;
    float V = Ax * Cy - Ay * Cx;
    float W = Bx * Ay - By * Ax;
#ifdef RT_HAVE_FP64
    if (U == 0.0f || V == 0.0f || W == 0.0f) {
        double CxBy = (double)Cx * (double)By, CyBx = (double)Cy * (double)Bx;
        double AxCy = (double)Ax * (double)Cy, AyCx = (double)Ay * (double)Cx;
        double BxAy = (double)Bx * (double)Ay, ByAx = (double)By * (double)Ax;
        U = (float)(CxBy - CyBx);
        V = (float)(AxCy - AyCx);
        W = (float)(BxAy - ByAx);
    }
#endif
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f)) return false;
    float det = U + V + W;
    if (det == 0.0f) return false;
    float3 n = rt_cross_rounded(v1 - v0, v2 - v0);
    float dn = rt_dot(n, r->d);
    float tt;
    if (dn != 0.0f) {
        tt = rt_dot(n, A) / dn;
    } else {
        float Az = r->Sz * Akz, Bz = r->Sz * Bkz, Cz = r->Sz * Ckz;
        tt = (U * Az + V * Bz + W * Cz) / det;
    }
    if (!(tt > tmin && tt < tmax)) return false;
    *t = tt;
    if (bary) *bary = (float2)(V, W) / det;
    return true;
}

// True and *t (tmin < *t < tmax) on a hit.
inline bool rt_intersect_triangle(const RayPre *r, float3 v0, float3 v1, float3 v2, float tmin, float tmax,
                                  float *t) {
    return rt_intersect_triangle_bary(r, v0, v1, v2, tmin, tmax, t, 0);
}

// One box: conservative slab test, *t_entry = max(entry, tmin).
inline bool rt_intersect_box(const RayPre *r, float3 bmin, float3 bmax, float tmin, float tmax, float *t_entry) {
    float3 t0 = (bmin - r->o) * r->inv;
    float3 t1 = (bmax - r->o) * r->inv;
    float3 tn = (float3)(r->neg.x ? t1.x : t0.x, r->neg.y ? t1.y : t0.y, r->neg.z ? t1.z : t0.z);
    float3 tf = (float3)(r->neg.x ? t0.x : t1.x, r->neg.y ? t0.y : t1.y, r->neg.z ? t0.z : t1.z);
    float enter = fmax(fmax(tn.x, tn.y), fmax(tn.z, tmin));
    float exit = fmin(fmin(tf.x, tf.y), tf.z) * RT_GAMMA3_SCALE;
    exit = fmin(exit, tmax);
    *t_entry = enter;
    return enter <= exit;
}

// Four boxes in SoA form: bounds[0..5] = minx, maxx, miny, maxy, minz, maxz (one lane per box).
// Returns the hit mask (-1 = hit) and the entry distances in *t_entry.
inline int4 rt_intersect_box4(const RayPre *r, __global const float4 *bounds, float tmin, float tmax,
                              float4 *t_entry) {
    float4 nx = (bounds[r->neg.x] - r->o.x) * r->inv.x;
    float4 fx = (bounds[1 - r->neg.x] - r->o.x) * r->inv.x;
    float4 ny = (bounds[2 + r->neg.y] - r->o.y) * r->inv.y;
    float4 fy = (bounds[3 - r->neg.y] - r->o.y) * r->inv.y;
    float4 nz = (bounds[4 + r->neg.z] - r->o.z) * r->inv.z;
    float4 fz = (bounds[5 - r->neg.z] - r->o.z) * r->inv.z;
    float4 enter = fmax(fmax(nx, ny), fmax(nz, (float4)(tmin)));
    float4 exit = fmin(fmin(fx, fy), fz) * RT_GAMMA3_SCALE;
    exit = fmin(exit, (float4)(tmax));
    *t_entry = enter;
    return enter <= exit;
}

// Helpers of the four-wide test (kept out of its macro body: they hold the fp64 #ifdefs).
// Edge functions that came out exactly 0 recomputed in double (as rt_intersect_triangle does).
inline void rt_uvw4_exact(int4 zero, float4 Ax, float4 Ay, float4 Bx, float4 By, float4 Cx, float4 Cy, float4 *U,
                          float4 *V, float4 *W) {
#ifdef RT_HAVE_FP64
    if (any(zero)) {
        double4 dAx = convert_double4(Ax), dAy = convert_double4(Ay), dBx = convert_double4(Bx);
        double4 dBy = convert_double4(By), dCx = convert_double4(Cx), dCy = convert_double4(Cy);
        *U = select(*U, convert_float4(dCx * dBy - dCy * dBx), zero);
        *V = select(*V, convert_float4(dAx * dCy - dAy * dCx), zero);
        *W = select(*W, convert_float4(dBx * dAy - dBy * dAx), zero);
    }
#endif
}

// Correctly rounded normals of four triangles from their edges (float32 products are exact in double).
inline void rt_normal4(float4 e1x, float4 e1y, float4 e1z, float4 e2x, float4 e2y, float4 e2z, float4 *nx,
                       float4 *ny, float4 *nz) {
#ifdef RT_HAVE_FP64
    double4 d1x = convert_double4(e1x), d1y = convert_double4(e1y), d1z = convert_double4(e1z);
    double4 d2x = convert_double4(e2x), d2y = convert_double4(e2y), d2z = convert_double4(e2z);
    *nx = convert_float4(d1y * d2z - d1z * d2y);
    *ny = convert_float4(d1z * d2x - d1x * d2z);
    *nz = convert_float4(d1x * d2y - d1y * d2x);
#else
    *nx = e1y * e2z - e1z * e2y;
    *ny = e1z * e2x - e1x * e2z;
    *nz = e1x * e2y - e1y * e2x;
#endif
}

// Four triangles at once, structure of arrays: v[0..8] = v0x, v0y, v0z, v1x, v1y, v1z, v2x, v2y, v2z
// (one lane per triangle). Lane by lane the same float operations as rt_intersect_triangle, so the
// same answers; the ray's axis permutation picks whole float4 rows (no per-lane shuffles).
// `lanes` masks the lanes that hold triangles (-1). Returns the lane of the nearest hit with
// tmin < t < tmax (the lowest such lane on equal t, as a sequential loop would keep), or -1.
// Defined for triangles in global memory (rt_intersect_triangle4) and for triangles staged in
// local memory (rt_intersect_triangle4_local): one body, two address spaces.
#define RT_DEFINE_TRIANGLE4(NAME, SPACE) \
inline int NAME(const RayPre *r, SPACE const float4 *v, int4 lanes, float tmin, float tmax, float *t_out) { \
    float okx = rt_comp(r->o, r->kx), oky = rt_comp(r->o, r->ky), okz = rt_comp(r->o, r->kz); \
    float4 Akz = v[r->kz] - okz, Bkz = v[3 + r->kz] - okz, Ckz = v[6 + r->kz] - okz; \
    float4 Ax = (v[r->kx] - okx) - r->Sx * Akz, Ay = (v[r->ky] - oky) - r->Sy * Akz; \
    float4 Bx = (v[3 + r->kx] - okx) - r->Sx * Bkz, By = (v[3 + r->ky] - oky) - r->Sy * Bkz; \
    float4 Cx = (v[6 + r->kx] - okx) - r->Sx * Ckz, Cy = (v[6 + r->ky] - oky) - r->Sy * Ckz; \
    float4 U = Cx * By - Cy * Bx; \
    float4 V = Ax * Cy - Ay * Cx; \
    float4 W = Bx * Ay - By * Ax; \
    rt_uvw4_exact(((U == 0.0f) | (V == 0.0f) | (W == 0.0f)) & lanes, Ax, Ay, Bx, By, Cx, Cy, &U, &V, &W); \
    int4 outside = ((U < 0.0f) | (V < 0.0f) | (W < 0.0f)) & ((U > 0.0f) | (V > 0.0f) | (W > 0.0f)); \
    float4 det = U + V + W; \
    int4 ok = lanes & ~outside & (det != 0.0f); \
    if (!any(ok)) return -1; \
    float4 nx, ny, nz; \
    rt_normal4(v[3] - v[0], v[4] - v[1], v[5] - v[2], v[6] - v[0], v[7] - v[1], v[8] - v[2], &nx, &ny, &nz); \
    float4 dn = nx * r->d.x + ny * r->d.y + nz * r->d.z; \
    float4 t = (nx * (v[0] - r->o.x) + ny * (v[1] - r->o.y) + nz * (v[2] - r->o.z)) / dn; \
    int4 flat = dn == 0.0f; \
    if (any(flat & ok)) { \
        float4 tw = (U * (r->Sz * Akz) + V * (r->Sz * Bkz) + W * (r->Sz * Ckz)) / det; \
        t = select(t, tw, flat); \
    } \
    ok &= (t > tmin) & (t < tmax); \
    if (!any(ok)) return -1; \
    float4 tm = select((float4)(INFINITY), t, ok); \
    float best = fmin(fmin(tm.x, tm.y), fmin(tm.z, tm.w)); \
    int lane = (ok.x && tm.x == best) ? 0 : (ok.y && tm.y == best) ? 1 : (ok.z && tm.z == best) ? 2 : 3; \
    *t_out = best; \
    return lane; \
}

RT_DEFINE_TRIANGLE4(rt_intersect_triangle4, __global)
RT_DEFINE_TRIANGLE4(rt_intersect_triangle4_local, __local)

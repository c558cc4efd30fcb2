/* The device-resident frame (viewer/cl/frame.py): ray generation and accumulation as OpenCL
 * kernels, so rays and hits never leave the CL device. Each kernel mirrors its GLSL twin line by
 * line: raygen mirrors viewer/shaders/raygen.frag (with camera.glsl, sampling.glsl), accumulate
 * mirrors accumulate.frag (with lighting.glsl); the exact hit of a pixel's primary ray is
 * recomputed from the G-buffer's triangle id with geometry.cl's watertight test, as
 * gbuffer.frag / raygen.frag do with intersect.glsl.
 *
 * Buffers: gid int[n] (the G-buffer id texture, row 0 = bottom, -1 = background); tris float4[3N]
 * in GPU_TRI_DTYPE layout (v0.xyz + id, v1.xyz + mat, v2.xyz + pad: the GL scene buffer's bytes);
 * mats float4[M] (albedo rgb, a = mirror); P float4[P_COUNT] the frame's camera and lights (layout
 * in frame.py: FRAME_PARAMS); rays and hits as viewer/cl/transfer.py lays them out. */
#include "geometry.cl"

#define RAY_PRIMARY 0
#define RAY_SHADOW 1
#define RAY_SOFT 2
#define RAY_AO 3
#define RAY_DIFFUSE 4
#define RAY_REFLECT 5

#define P_CAM_POS 0     /* xyz, w = tanHalfFov */
#define P_CAM_RIGHT 1   /* xyz, w = viewport width */
#define P_CAM_UP 2      /* xyz, w = viewport height */
#define P_CAM_FWD 3     /* xyz, w = ambient */
#define P_SKY 4         /* xyz, w = lightRadius */
#define P_COUNTS 5      /* x = point lights, y = rect lights */
#define P_POINT_POS 6
#define P_POINT_INT 14
#define P_RECT_CORNER 22
#define P_RECT_U 26
#define P_RECT_V 30
#define P_RECT_RAD 34

#define PI_F 3.14159265358979f
#define LIGHT_EPS 1e-4f

inline float3 v3(__constant float4 *P, int i) { return P[i].xyz; }

inline float3 fr_normalize(float3 v) { return v / sqrt(rt_dot(v, v)); }

inline float3 tri_v(__global const float4 *tris, int id, int k) { return tris[3 * id + k].xyz; }

inline int tri_mat(__global const float4 *tris, int id) { return as_int(tris[3 * id + 1].w); }

/* camera.glsl: primaryDir */
inline float3 primary_dir(__constant float4 *P, float2 frag) {
    float2 viewport = (float2)(P[P_CAM_RIGHT].w, P[P_CAM_UP].w);
    float2 ndc = frag / viewport * 2.0f - 1.0f;
    float aspect = viewport.x / viewport.y;
    float th = P[P_CAM_POS].w;
    float3 d = v3(P, P_CAM_RIGHT) * (ndc.x * th * aspect) + v3(P, P_CAM_UP) * (ndc.y * th) + v3(P, P_CAM_FWD);
    return fr_normalize(d);
}

/* sampling.glsl */
inline uint pcg_hash(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

inline float2 pixel_random2(int2 px, uint stream) {
    uint h = pcg_hash((uint)px.x * 73856093u ^ (uint)px.y * 19349663u ^ stream * 83492791u);
    uint h2 = pcg_hash(h);
    return (float2)((float)(h >> 8) * (1.0f / 16777216.0f), (float)(h2 >> 8) * (1.0f / 16777216.0f));
}

inline void make_basis(float3 n, float3 *t, float3 *b) {
    float s = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (s + n.z);
    float c = n.x * n.y * a;
    *t = (float3)(1.0f + s * n.x * n.x * a, s * c, -s * n.x);
    *b = (float3)(c, s + n.y * n.y * a, -n.y);
}

inline float3 cosine_hemisphere(float2 u) {
    float r = sqrt(u.x);
    float phi = 2.0f * PI_F * u.y;
    return (float3)(r * cos(phi), r * sin(phi), sqrt(fmax(0.0f, 1.0f - u.x)));
}

inline float3 perturb_in_cone(float3 d, float maxAngle, float2 u) {
    if (maxAngle <= 0.0f) return d;
    float cosMax = cos(maxAngle);
    float cosT = 1.0f - u.x * (1.0f - cosMax);
    float sinT = sqrt(fmax(0.0f, 1.0f - cosT * cosT));
    float phi = 2.0f * PI_F * u.y;
    float3 t, b;
    make_basis(d, &t, &b);
    return fr_normalize(t * (sinT * cos(phi)) + b * (sinT * sin(phi)) + d * cosT);
}

/* Wächter & Binder (Ray Tracing Gems 6), as sampling.glsl: offsetRayOrigin */
inline float offset1(float p, float n) {
    const float originEps = 1.0f / 32.0f;
    const float floatScale = 1.0f / 65536.0f;
    const float intScale = 256.0f;
    int ofi = (int)(intScale * n);
    float pi = as_float(as_int(p) + (p < 0.0f ? -ofi : ofi));
    return fabs(p) < originEps ? p + floatScale * n : pi;
}

inline float3 offset_ray_origin(float3 p, float3 n) {
    return (float3)(offset1(p.x, n.x), offset1(p.y, n.y), offset1(p.z, n.z));
}

inline float fract1(float x) { return x - floor(x); }

/* The pixel's primary hit on triangle `id` (the G-buffer's), from one watertight test: the facing
 * normal, the hit point as raygen.frag makes it (returned: the barycentric point of the exact hit)
 * and as gbuffer.frag stores it (*gp_out: cam + dPrim * t); both are the plane point where the
 * test misses (a pixel centre covered by rasterization but on the far side of an edge). */
inline float3 primary_hit(__global const float4 *tris, int id, float3 cam, float3 dPrim, float3 *gp_out,
                          float3 *n_out) {
    float3 v0 = tri_v(tris, id, 0), v1 = tri_v(tris, id, 1), v2 = tri_v(tris, id, 2);
    float3 n = fr_normalize(rt_cross(v1 - v0, v2 - v0));
    RayPre r = rt_prepare_ray(cam, dPrim);
    float t;
    float2 b;
    float3 p;
    if (rt_intersect_triangle_bary(&r, v0, v1, v2, 0.0f, 1e30f, &t, &b)) {
        p = v0 * (1.0f - b.x - b.y) + v1 * b.x + v2 * b.y;
        *gp_out = cam + dPrim * t;
    } else {
        p = cam + dPrim * (rt_dot(v0 - cam, n) / rt_dot(dPrim, n));
        *gp_out = p;
    }
    if (rt_dot(n, dPrim) > 0.0f) n = -n;  /* face the viewer */
    *n_out = n;
    return p;
}

/* Once per frame: per pixel of the G-buffer, the facing normal (w = 1 where the pixel has a
 * surface), the secondary rays' origin (raygen.frag: the barycentric hit point moved off the surface
 * by offsetRayOrigin) and gbuffer.frag's position (cam + dPrim * t, accumulate.frag's gPos). Every
 * pass then reads them instead of intersecting again. */
__kernel void surface(__global const int *gid, __global const float4 *tris, __constant float4 *P, int w, int h,
                      __global float4 *out_n, __global float4 *out_po, __global float4 *out_gp) {
    int i = (int)get_global_id(0);
    if (i >= w * h) return;
    int id = gid[i];
    if (id < 0) {
        out_n[i] = (float4)(0.0f);
        return;
    }
    int2 px = (int2)(i % w, i / w);
    float3 cam = v3(P, P_CAM_POS);
    float3 dPrim = primary_dir(P, (float2)((float)px.x + 0.5f, (float)px.y + 0.5f));
    float3 n, gp;
    float3 p = primary_hit(tris, id, cam, dPrim, &gp, &n);
    out_n[i] = (float4)(n, 1.0f);
    out_po[i] = (float4)(offset_ray_origin(p, n), 0.0f);
    out_gp[i] = (float4)(gp, 0.0f);
}

__kernel void raygen(__global const int *gid, __global const float4 *tris, __global const float4 *mats,
                     __global const float4 *surf_n, __global const float4 *surf_po, __constant float4 *P, int w, int h, int rayType, int lightIndex, float2 sampleUV,
                     float perturbAngle, float rayLength, uint stream, __global float4 *out_o,
                     __global float4 *out_d, __global uint *counters) {
    __local uint group_active;
    __local float4 group_loc;  /* the pass's hemisphere sample (sampleUV is uniform): once per work-group */
    if (get_local_id(0) == 0) {
        group_active = 0u;
        if (rayType == RAY_AO || rayType == RAY_DIFFUSE) group_loc = (float4)(cosine_hemisphere(sampleUV), 0.0f);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int i = (int)get_global_id(0);
    bool active = false;
    if (i < w * h) {
        int2 px = (int2)(i % w, i / w);
        float3 cam = v3(P, P_CAM_POS);
        float3 dPrim = primary_dir(P, (float2)((float)px.x + 0.5f, (float)px.y + 0.5f));
        float3 o = cam, d = dPrim;
        float tmin = 0.0f, tmax = -1.0f;
        if (rayType == RAY_PRIMARY) {
            tmax = 1e30f;
        } else {
            int id = gid[i];
            if (id >= 0) {
                float3 n = surf_n[i].xyz;  /* the surface kernel's, once per frame */
                float3 po = surf_po[i].xyz;
                float2 rnd = pixel_random2(px, stream);
                if (rayType == RAY_SHADOW) {
                    float3 l = v3(P, P_POINT_POS + lightIndex) - po;
                    float dist = sqrt(rt_dot(l, l));
                    if (rt_dot(l, n) > 0.0f && dist > 0.0f) { o = po; d = l / dist; tmax = dist * (1.0f - LIGHT_EPS); }
                } else if (rayType == RAY_SOFT) {
                    float shift = perturbAngle / PI_F;
                    float2 uv = (float2)(fract1(sampleUV.x + (rnd.x - 0.5f) * shift),
                                         fract1(sampleUV.y + (rnd.y - 0.5f) * shift));
                    float3 ru = v3(P, P_RECT_U + lightIndex), rv = v3(P, P_RECT_V + lightIndex);
                    float3 q = v3(P, P_RECT_CORNER + lightIndex) + uv.x * ru + uv.y * rv;
                    float3 nl = rt_cross(ru, rv);
                    float3 l = q - po;
                    float dist = sqrt(rt_dot(l, l));
                    if (rt_dot(l, n) > 0.0f && rt_dot(nl, -l) > 0.0f && dist > 0.0f) {
                        o = po; d = l / dist; tmax = dist * (1.0f - LIGHT_EPS);
                    }
                } else if (rayType == RAY_AO || rayType == RAY_DIFFUSE) {
                    float3 t, bb;
                    make_basis(n, &t, &bb);
                    float3 loc = group_loc.xyz;
                    float3 dir = perturb_in_cone(fr_normalize(t * loc.x + bb * loc.y + n * loc.z), perturbAngle, rnd);
                    float c = rt_dot(dir, n);
                    if (c <= 0.0f) dir = fr_normalize(dir - 2.0f * c * n);
                    o = po; d = dir; tmax = rayLength;
                } else if (rayType == RAY_REFLECT) {
                    if (mats[tri_mat(tris, id)].w > 0.5f) {
                        o = po; d = fr_normalize(dPrim - 2.0f * rt_dot(n, dPrim) * n); tmax = 1e30f;
                    }
                }
            }
        }
        active = tmax > 0.0f;
        out_o[i] = (float4)(o, tmin);
        out_d[i] = (float4)(d, tmax);
    }
    if (active) atomic_inc(&group_active);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (get_local_id(0) == 0 && group_active) atomic_add(&counters[rayType], group_active);
}

/* lighting.glsl */
inline float3 point_irradiance(__constant float4 *P, int i, float3 p, float3 n) {
    float3 l = v3(P, P_POINT_POS + i) - p;
    float d2 = fmax(rt_dot(l, l), 1e-30f);
    float r = P[P_SKY].w;
    return v3(P, P_POINT_INT + i) * fmax(0.0f, rt_dot(n, l)) * rsqrt(d2) / fmax(d2, r * r);
}

inline float3 rect_sample_irradiance(__constant float4 *P, int i, float3 q, float3 p, float3 n) {
    float3 nl = rt_cross(v3(P, P_RECT_U + i), v3(P, P_RECT_V + i));
    float area = sqrt(rt_dot(nl, nl));
    nl /= area;
    float3 l = q - p;
    float d2 = fmax(rt_dot(l, l), 1e-30f);
    float3 ld = l * rsqrt(d2);
    float cosS = fmax(0.0f, rt_dot(n, ld));
    float cosL = fmax(0.0f, -rt_dot(nl, ld));
    float r = P[P_SKY].w;
    return v3(P, P_RECT_RAD + i) * area * cosS * cosL / fmax(d2, r * r);
}

inline float3 direct_irradiance(__constant float4 *P, float3 p, float3 n) {
    float3 e = (float3)(0.0f);
    int np = (int)P[P_COUNTS].x, nr = (int)P[P_COUNTS].y;
    for (int i = 0; i < np; ++i) e += point_irradiance(P, i, p, n);
    for (int i = 0; i < nr; ++i) {
        float3 c = v3(P, P_RECT_CORNER + i) + 0.5f * v3(P, P_RECT_U + i) + 0.5f * v3(P, P_RECT_V + i);
        e += rect_sample_irradiance(P, i, c, p, n);
    }
    return e;
}

inline float3 shade_secondary_hit(__constant float4 *P, float3 p, float3 n, float3 albedo) {
    return albedo / PI_F * direct_irradiance(P, p, n) + albedo * v3(P, P_SKY) * P[P_CAM_FWD].w;
}

/* accumulate.frag: acc[i] += this pass's contribution (the GL pass blends ONE, ONE). */
__kernel void accumulate(__global const int *gid, __global const float4 *tris, __global const float4 *mats,
                         __global const float4 *surf_n, __global const float4 *surf_gp, __constant float4 *P, int w, int h, int effect, int lightIndex, float weight,
                         __global const float4 *ray_o, __global const float4 *ray_d, __global const float *hit_t,
                         __global const int *hit_id, __global float4 *acc) {
    int i = (int)get_global_id(0);
    if (i >= w * h) return;
    float4 ot = ray_o[i], dt = ray_d[i];
    if (!(dt.w > ot.w)) return;
    float t = hit_t[i];
    int id = hit_id[i];
    float vis = id < 0 ? 1.0f : 0.0f;
    /* the G-buffer's position and facing normal of the pixel (gbuffer.frag), from its triangle id */
    float3 p = surf_gp[i].xyz, n = surf_n[i].xyz;  /* zero where the pixel has no surface (as the G-buffer) */
    if (gid[i] < 0) p = (float3)(0.0f);
    float4 out;
    if (effect == RAY_SHADOW) {
        out = (float4)(point_irradiance(P, lightIndex, p, n) * vis, vis) * weight;
    } else if (effect == RAY_SOFT) {
        float3 q = ot.xyz + dt.xyz * (dt.w / (1.0f - LIGHT_EPS));
        out = (float4)(rect_sample_irradiance(P, lightIndex, q, p, n) * vis, vis) * weight;
    } else if (effect == RAY_AO) {
        out = (float4)(vis) * weight;
    } else {
        float3 rad;
        if (id < 0) {
            rad = v3(P, P_SKY) * P[P_CAM_FWD].w;
        } else {
            float3 q = ot.xyz + dt.xyz * t;
            float3 v0 = tri_v(tris, id, 0);
            float3 nn = fr_normalize(rt_cross(tri_v(tris, id, 1) - v0, tri_v(tris, id, 2) - v0));
            if (rt_dot(nn, dt.xyz) > 0.0f) nn = -nn;
            rad = shade_secondary_hit(P, q, nn, mats[tri_mat(tris, id)].xyz);
        }
        out = (float4)(rad, 1.0f) * weight;
    }
    acc[i] += out;
}

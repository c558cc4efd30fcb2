// Point-centred (spherical) grid: angular tiles x distance slabs around a centre E through which
// every ray of a pass passes (a point light for shadow rays, the eye for primary rays), after
// Guntury & Narayanan 2010 (per-light spherical grids) and Patidar & Narayanan 2008 (perspective
// grid). Layout: PGRID_DTYPE in viewer/accel/pointgrid.py. A direction u from E has azimuth
// alpha = atan2(u.right, u.fwd) and elevation theta = asin(u.up); the forward axis points at the
// rays (away from the poles +-up). Tiles cover the angular rectangle of the rays (grown by the
// margin): tile (ia, it) = floor((alpha - alpha0) * rect.z), floor((theta - theta0) * rect.w).
// Slab s holds the triangles whose distance from E is at least d0 + s * slab width (a lower
// bound; d0 = distance from E to the scene box, so the slabs span only the geometry).
#include "geometry.cl"

#ifndef WG
#define WG 64
#endif

typedef struct {
    float4 centre;  // xyz = E, w = angular margin (radians)
    float4 fwd;
    float4 up;
    float4 right;
    float4 rect;    // alpha0, theta0, tiles per radian (alpha), tiles per radian (theta)
    float4 slab;    // slab width, 1 / slab width, tan(margin), d0 (distance from E to the scene box)
    int4 res;       // tiles in alpha, tiles in theta, slabs, tiles * slabs
} PGrid;


// atan2 by an 11th-order minimax polynomial on [0, 1] after octant reduction: |error| <= 2e-6 rad
// (1.8e-6 measured in float32 over [0, 1]; tests/test_grid.py checks it), so bounds from it get
// PG_ATAN_SLACK. Five of these per triangle instead of libm's atan2 halve the binning time.
#define PG_ATAN_SLACK 4e-6f
inline float pg_atan2_fast(float y, float x) {
    float ax = fabs(x), ay = fabs(y);
    float mx = fmax(ax, ay), mn = fmin(ax, ay);
    float a = mx > 0.0f ? mn / mx : 0.0f;
    float s = a * a;
    float r = a * (0.99997726f + s * (-0.33262347f + s * (0.19354346f + s * (-0.11643287f + s * (0.05265332f
              + s * -0.01172120f)))));
    if (ay > ax) r = M_PI_2_F - r;
    if (x < 0.0f) r = M_PI_F - r;
    return y < 0.0f ? -r : r;
}


// A ray's angles (alpha, theta) by the polynomial atan2 (libm's atan2 and asin cost 3x the whole
// classification on CPU devices): off by at most 2e-6 rad each (plus float rounding of u's
// coordinates), which the host adds to the grid's margin (RAY_ANGLE_ERR in pointgrid.py).
inline float2 pg_angles(const PGrid *g, float3 u) {
    float x = rt_dot(u, g->right.xyz), z = rt_dot(u, g->fwd.xyz), y = rt_dot(u, g->up.xyz);
    return (float2)(pg_atan2_fast(x, z), pg_atan2_fast(y, sqrt(x * x + z * z)));
}

// A ray's place in the grid: false when its segment does not stay within the margin cap
// (slab.z = tan of the largest margin allowed) of one direction u from E (then it is traced
// another way). Only segment points at least d0 (slab.w: distance from E to the scene box) from E
// can meet a triangle, so the deviation that matters is *dev = h / max(lambda_min, sqrt(d0^2 - h^2)),
// with h the distance of the ray's line from E and lambda_min the nearest along-ray distance of
// the segment (rounded up; an upper bound of the angle). Computed in double.
inline bool pg_ray(const PGrid *g, float4 ot, float4 dt, float3 *u_out, float *dev) {
    if (!(dt.w > ot.w) || !isfinite(ot.x) || !isfinite(ot.y) || !isfinite(ot.z) || !isfinite(ot.w) ||
        !isfinite(dt.x) || !isfinite(dt.y) || !isfinite(dt.z) || isnan(dt.w))
        return false;
    // a ray leaving from E itself (every primary ray: E is the eye) lies on its own direction:
    // h = 0, so its deviation is 0 (what the double path below gives), and u in float is off by
    // a few ulps (~3e-7 rad), within the grid's 1e-6 rad slack (pointgrid.py)
    if (ot.x == g->centre.x && ot.y == g->centre.y && ot.z == g->centre.z && ot.w >= 0.0f) {
        float len = length(dt.xyz);
        if (len > 0.0f && isfinite(len)) {  // else (under- or overflow) the double path decides
            *u_out = dt.xyz / len;
            *dev = 1e-30f;
            return true;
        }
    }
#ifdef RT_HAVE_FP64
    double3 w = convert_double3(ot.xyz) - convert_double3(g->centre.xyz);
    double3 d = convert_double3(dt.xyz);
    double len = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    if (len == 0.0) return false;
    double3 dh = d / len;
    double base = w.x * dh.x + w.y * dh.y + w.z * dh.z;
    double l0 = base + (double)ot.w * len, l1 = base + (double)fmin(dt.w, 3.0e38f) * len;
    double3 cr = (double3)(w.y * dh.z - w.z * dh.y, w.z * dh.x - w.x * dh.z, w.x * dh.y - w.y * dh.x);
    double h = sqrt(cr.x * cr.x + cr.y * cr.y + cr.z * cr.z) * (1.0 + 1e-12);
    double lmin;
    if (l0 >= 0.0) { lmin = l0; *u_out = convert_float3(dh); }
    else if (l1 <= 0.0) { lmin = -l1; *u_out = convert_float3(-dh); }
    else return false;
    double d0 = (double)g->slab.w;
    double lam = fmax(lmin, sqrt(fmax(d0 * d0 - h * h, 0.0)));
    double dv = h == 0.0 ? 0.0 : (lam > 0.0 ? h / lam : INFINITY);
    if (!(dv <= (double)g->slab.z)) return false;
    *dev = (float)(dv * (1.0 + 1e-6)) + 1e-30f;
    return true;
#else
    return false;  // without doubles every ray takes the other way (still exact)
#endif
}

// Order-preserving map float -> uint (atomic_min / atomic_max on floats); pointgrid.py decodes it.
inline uint pg_ord(float f) {
    uint u = as_uint(f);
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

inline float pg_unord(uint k) {
    return as_float((k & 0x80000000u) ? (k & 0x7fffffffu) : ~k);
}

// Indices into the grid's statistics buffer (host-initialised before pg_classify, read in two
// batches): counts by atomic add, reductions by atomic min / max on pg_ord keys.
#define PG_ST_OUTSIDE 0   // rays traced another way (also the length of the outside list)
#define PG_ST_INACTIVE 1
#define PG_ST_DEV 2       // max deviation bound of a ray in the grid
#define PG_ST_A0 3        // min / max alpha, min / max theta of the rays in the grid
#define PG_ST_A1 4
#define PG_ST_T0 5
#define PG_ST_T1 6
#define PG_ST_CULLED 7    // triangles culled (pg_tri_count)
#define PG_ST_WIDENED 8   // triangles widened to every azimuth
#define PG_ST_BACK 9      // triangles culled as back faces (among the culled)
#define PG_ST_DNEAR 10    // min over the binned triangles of their distance lower bound from E

// Per ray: angles of u (0 for rays not in the grid) and outside: 0 in the grid, 1 outside it
// (traced another way: its index appended to out_idx), 2 inactive (nothing to trace). The counts
// and the rays' angular rectangle and largest deviation go to `st` in the same launch (one local
// reduction per work-group, then one global atomic per value): no separate reduce / compact passes.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_classify(__global const PGrid *grid, __global const float4 *ray_o, __global const float4 *ray_d, const uint n,
                 __global float *alpha, __global float *theta, __global uint *outside, __global uint *st,
                 __global uint *out_idx) {
    __local float la[WG], lt[WG], ld[WG];
    __local uint lk[WG];
    uint i = get_global_id(0), lid = get_local_id(0);
    uint kind = 2u;
    float2 at = (float2)(0.0f);
    float dv = 0.0f;
    if (i < n) {
        PGrid g = *grid;
        float3 u;
        float4 ot = ray_o[i], dt = ray_d[i];
        bool ok = pg_ray(&g, ot, dt, &u, &dv);
        at = ok ? pg_angles(&g, u) : (float2)(0.0f);
        alpha[i] = at.x;
        theta[i] = at.y;
        kind = ok ? 0u : (dt.w > ot.w ? 1u : 2u);
        outside[i] = kind;
        if (kind == 1u) out_idx[atomic_inc(&st[PG_ST_OUTSIDE])] = i;  // order within the list does not matter
    }
    la[lid] = at.x;
    lt[lid] = at.y;
    ld[lid] = dv;
    lk[lid] = kind;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) {  // the group's reductions by one work-item (64 entries), then one atomic per value
        float dmax = 0.0f, a0 = INFINITY, a1 = -INFINITY, t0 = INFINITY, t1 = -INFINITY;
        uint in_grid = 0u, inactive = 0u;
        for (uint k = 0; k < WG; ++k) {
            if (lk[k] == 0u) {
                ++in_grid;
                dmax = fmax(dmax, ld[k]);
                a0 = fmin(a0, la[k]); a1 = fmax(a1, la[k]);
                t0 = fmin(t0, lt[k]); t1 = fmax(t1, lt[k]);
            } else if (lk[k] == 2u && get_group_id(0) * WG + k < n) {
                ++inactive;
            }
        }
        if (inactive) atomic_add(&st[PG_ST_INACTIVE], inactive);
        if (in_grid) {
            atomic_max(&st[PG_ST_DEV], pg_ord(dmax));
            atomic_min(&st[PG_ST_A0], pg_ord(a0));
            atomic_max(&st[PG_ST_A1], pg_ord(a1));
            atomic_min(&st[PG_ST_T0], pg_ord(t0));
            atomic_max(&st[PG_ST_T1], pg_ord(t1));
        }
    }
}

// The rays' sort keys: their tile, ntiles for rays outside the grid, ntiles + 1 for inactive
// ones. When the triangle pairs overflowed their buffers (*pairs > cap: the grid holds nothing),
// every ray of the grid is sent the other way too (appended to the outside list, st[PG_ST_OUTSIDE]
// counting it), so the pass stays exact and the next one gets room.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_ray_keys(__global const PGrid *grid, __global const float *alpha, __global const float *theta,
                 __global const uint *outside, const uint n, __global uint *keys, __global uint *vals,
                 __global const uint *pairs, const uint cap, __global uint *st, __global uint *out_idx) {
    uint i = get_global_id(0);
    if (i >= n) return;
    PGrid g = *grid;
    uint ntiles = (uint)(g.res.x * g.res.y);
    uint key = ntiles + outside[i] - 1u;  // after every tile: outside rays, then inactive ones
    if (!outside[i] && *pairs > cap) {
        out_idx[atomic_inc(&st[PG_ST_OUTSIDE])] = i;
    } else if (!outside[i]) {
        int ia = clamp((int)floor((alpha[i] - g.rect.x) * g.rect.z), 0, g.res.x - 1);
        int it = clamp((int)floor((theta[i] - g.rect.y) * g.rect.w), 0, g.res.y - 1);
        key = (uint)(ia + g.res.x * it);
    }
    keys[i] = key;
    vals[i] = i;
}

// Tile range [ia0, ia1] x [it0, it1] and slab of triangle i; false: culled (outside the rays'
// rectangle, or not finite). *full: the triangle surrounds the up axis, comes close to it, or
// crosses the azimuth seam behind the centre (alpha range widened to everything).
// In the frame (x = right, y = up, z = fwd) around E: azimuth alpha = atan2(x, z) is the polar angle
// of the triangle's projection onto the (z, x) plane; when that 2D triangle misses the origin its
// angular range (< pi) is reached at vertices. Elevation theta = atan2(y, rho), rho = sqrt(x^2 + z^2)
// >= rho_min (distance of the 2D triangle from the origin; rho is convex, so its maximum is at a
// vertex): theta <= atan2(y_max, rho_min) when y_max > 0, else atan2(y_max, rho_max); the lower
// bound likewise. Float32 with explicit slack: coordinates relative to E are off by at most
// ~4e-7 |v|max, so rho_min is lowered by that, azimuths get 4e-7 |v|max / rho_min, elevations 1e-6
// radians; a triangle within 1e-3 |v|max of the up axis takes the full azimuth range; the angles come
// from pg_atan2_fast (PG_ATAN_SLACK). The box is then grown by the rays' margin m (in azimuth by
// asin(sin m / cos theta): the same angle nearer the poles).
inline float pg_seg_dist2(float2 p, float2 q) {  // squared distance from the origin to segment pq
    float2 d = q - p;
    float dd = d.x * d.x + d.y * d.y;
    float t = dd > 0.0f ? clamp(-(p.x * d.x + p.y * d.y) / dd, 0.0f, 1.0f) : 0.0f;
    float2 c = p + t * d;
    return c.x * c.x + c.y * c.y;
}

// A lower bound of cos(largest |theta| in [tlo, thi]) without libm's cos (slow on CPU devices): the
// Taylor series cut after a negative term, 1 - t^2/2 + t^4/24 - t^6/720 <= cos t, less float slack.
// With sin m <= m and asin x <= x / sqrt(1 - x^2) (tan y >= y), x = m / ct bounds the azimuth a
// margin m spans at those elevations without asin.
inline float pg_cos_lower(float tlo, float thi) {
    float tm = fmax(fabs(tlo), fabs(thi)), t2 = tm * tm;
    return (1.0f - t2 * (0.5f - t2 * (1.0f / 24.0f - t2 * (1.0f / 720.0f)))) * 0.9999f - 1e-6f;
}

inline bool pg_tri(const PGrid *g, __global const float4 *tris, uint i, int4 *range, int *slab, bool *full,
                   bool *back, float *dmin_out, float4 *box) {
    float3 E = g->centre.xyz;
    float4 w0 = tris[3 * i], w1 = tris[3 * i + 1], w2 = tris[3 * i + 2];
    float3 v0 = w0.xyz - E, v1 = w1.xyz - E, v2 = w2.xyz - E;
    *full = false;
    *back = false;
    if (!(all(isfinite(v0)) && all(isfinite(v1)) && all(isfinite(v2)))) return false;
    if (rt_two_equal_vertices(w0.xyz, w1.xyz, w2.xyz)) return false;  // never hit (geometry.cl): culling is exact
#ifdef RT_HAVE_FP64
    if (g->fwd.w > 0.0f) {  // back-face culling (closed outward geometry seen from outside): E clearly
        // behind the triangle's plane, in double as the camera grid decides it (camgrid_build.cl)
        double3 Ed = convert_double3(E);
        double3 d0 = convert_double3(w0.xyz) - Ed, d1 = convert_double3(w1.xyz) - Ed,
                d2 = convert_double3(w2.xyz) - Ed;
        double3 nd = cross(d1 - d0, d2 - d0);
        if (dot(nd, d0) > 1e-9 * length(nd) * length(d0)) { *back = true; return false; }
    }
#endif
    float m = g->centre.w;
    // slab: a lower bound of the triangle's distance from E (the plane's distance, needed for
    // large triangles only: a small one's bounding sphere is nearly as tight)
    float3 ctr = (v0 + v1 + v2) / 3.0f;
    float3 e0 = v0 - ctr, e1 = v1 - ctr, e2 = v2 - ctr;
    float rad = sqrt(fmax(fmax(rt_dot(e0, e0), rt_dot(e1, e1)), rt_dot(e2, e2)));
    float dc = length(ctr);
    float rr = rad * 1.00001f + 4e-7f * (dc + rad) + 1e-6f * dc;
    // small: under a quarter of its distance and of a tile (rect.zw: tiles per radian), so the
    // ball's looser box rarely reaches another tile (the dragon's triangles, near a tile's
    // size, keep their exact boxes: 1.3-1.8x the pairs otherwise)
    bool small = rr < 0.25f * dc && rr * fmax(g->rect.z, g->rect.w) < 0.25f * dc;
    float dplane = 0.0f;
    if (!small) {
        float3 nrm = rt_cross(v1 - v0, v2 - v0);
        float nl = length(nrm);
        dplane = nl > 0.0f ? fabs(rt_dot(nrm, v0)) / nl : 0.0f;
    }
    float dmin = fmax(fmax(dplane, dc - rad), 0.0f) * (1.0f - 1e-5f);
    *slab = clamp((int)floor((dmin - g->slab.w) * g->slab.y), 0, g->res.z - 1);
    *dmin_out = dmin;
    float3 R = g->right.xyz, U = g->up.xyz, F = g->fwd.xyz;
    float amin = -M_PI_F, amax = M_PI_F, tlo, thi;
    // A small triangle (a detailed mesh seen from afar: 69k bunny triangles fill 8% of the mixed
    // scene's view) is boxed through its bounding sphere (centroid, radius rr grown by the
    // coordinates' error 4e-7 (dc + rad) and the centre's rounding 1e-6 dc): a cone of half-angle
    // asin(rr / dc) around the centre's direction, so elevation tc +- asin(rr / dc), azimuth
    // ac +- asin(rr / rho) (the projected disk at distance rho from the up axis), each bounded by
    // x / sqrt(1 - x^2) >= asin x. Two atan2 instead of five and no segment distances: half the
    // binning time, for a box at most ~2x the triangle's own (the trace tests rays against it).
    if (small) {
        float cx = rt_dot(ctr, R), cy = rt_dot(ctr, U), cz = rt_dot(ctr, F);
        float rho = sqrt(cx * cx + cz * cz);
        float sb = rr / dc, beta = sb / sqrt(1.0f - sb * sb) * 1.001f;
        float tc = pg_atan2_fast(cy, rho);
        tlo = fmax(tc - beta - m - 1e-6f - PG_ATAN_SLACK, -M_PI_2_F);
        thi = fmin(tc + beta + m + 1e-6f + PG_ATAN_SLACK, M_PI_2_F);
        float ct = pg_cos_lower(tlo, thi), x = m / ct;
        if (rho - rr <= 1e-3f * (dc + rad) || !(ct > 0.0f && x < 0.999f)) {  // near the up axis
            *full = true;
        } else {
            float sa = rr / rho;
            float da = sa / sqrt(1.0f - sa * sa) * 1.001f + x / sqrt(1.0f - x * x) * 1.001f + 1e-6f +
                       2.0f * PG_ATAN_SLACK;
            float ac = pg_atan2_fast(cx, cz);
            amin = ac - da;
            amax = ac + da;
            if (amin <= -M_PI_F || amax >= M_PI_F) { amin = -M_PI_F; amax = M_PI_F; *full = true; }
        }
    } else {
        float2 p0 = (float2)(rt_dot(v0, F), rt_dot(v0, R)), p1 = (float2)(rt_dot(v1, F), rt_dot(v1, R));
        float2 p2 = (float2)(rt_dot(v2, F), rt_dot(v2, R));
        float y0 = rt_dot(v0, U), y1 = rt_dot(v1, U), y2 = rt_dot(v2, U);
        float vmax = fmax(fmax(length(v0), length(v1)), length(v2));
        float err = 4e-7f * vmax;
        float c0 = p0.x * p1.y - p0.y * p1.x, c1 = p1.x * p2.y - p1.y * p2.x, c2 = p2.x * p0.y - p2.y * p0.x;
        // the origin inside the projected triangle (rho_min = 0). All three products zero: the
        // projection is a point or a segment on a line through the origin, whose distance from the
        // origin the segment distances give (0 when it reaches the origin); treating it as
        // "around" widened every such triangle to all azimuths
        bool flat = c0 == 0.0f && c1 == 0.0f && c2 == 0.0f;
        bool around = !flat && ((c0 >= 0.0f && c1 >= 0.0f && c2 >= 0.0f) || (c0 <= 0.0f && c1 <= 0.0f && c2 <= 0.0f));
        float rho_min = around ? 0.0f : sqrt(fmin(fmin(pg_seg_dist2(p0, p1), pg_seg_dist2(p1, p2)),
                                                  pg_seg_dist2(p2, p0)));
        bool near_axis = rho_min <= 1e-3f * vmax;
        float rho_lo = fmax(rho_min - err, 0.0f);
        float rho_max = fmax(fmax(length(p0), length(p1)), length(p2)) + err;
        float ymax = fmax(fmax(y0, y1), y2) + err, ymin = fmin(fmin(y0, y1), y2) - err;
        thi = ymax > 0.0f ? (rho_lo > 0.0f ? pg_atan2_fast(ymax, rho_lo) : M_PI_2_F) : pg_atan2_fast(ymax, rho_max);
        tlo = ymin < 0.0f ? (rho_lo > 0.0f ? pg_atan2_fast(ymin, rho_lo) : -M_PI_2_F) : pg_atan2_fast(ymin, rho_max);
        tlo = fmax(tlo - m - 1e-6f - PG_ATAN_SLACK, -M_PI_2_F);
        thi = fmin(thi + m + 1e-6f + PG_ATAN_SLACK, M_PI_2_F);
        float ct = pg_cos_lower(tlo, thi), x = m / ct;
        if (near_axis || !(ct > 0.0f && x < 0.999f)) {  // cos(pi / 2) is -4e-8 in float32
            *full = true;
        } else {
            float a0 = pg_atan2_fast(p0.y, p0.x), lo = 0.0f, hi = 0.0f;
            float d1 = pg_atan2_fast(p1.y, p1.x) - a0, d2 = pg_atan2_fast(p2.y, p2.x) - a0;
            d1 = d1 > M_PI_F ? d1 - 2.0f * M_PI_F : (d1 < -M_PI_F ? d1 + 2.0f * M_PI_F : d1);
            d2 = d2 > M_PI_F ? d2 - 2.0f * M_PI_F : (d2 < -M_PI_F ? d2 + 2.0f * M_PI_F : d2);
            lo = fmin(lo, fmin(d1, d2));
            hi = fmax(hi, fmax(d1, d2));
            float da = x / sqrt(1.0f - x * x) * 1.001f + 1e-6f + 2.0f * PG_ATAN_SLACK + err / rho_min;
            amin = a0 + lo - da;
            amax = a0 + hi + da;
            if (amin <= -M_PI_F || amax >= M_PI_F) { amin = -M_PI_F; amax = M_PI_F; *full = true; }
        }
    }
    *box = (float4)(amin, amax, tlo, thi);
    float fa0 = (amin - g->rect.x) * g->rect.z, fa1 = (amax - g->rect.x) * g->rect.z;
    float ft0 = (tlo - g->rect.y) * g->rect.w, ft1 = (thi - g->rect.y) * g->rect.w;
    if (fa1 < 0.0f || ft1 < 0.0f || fa0 >= (float)g->res.x || ft0 >= (float)g->res.y) return false;
    *range = (int4)(clamp((int)floor(fa0), 0, g->res.x - 1), clamp((int)floor(fa1), 0, g->res.x - 1),
                    clamp((int)floor(ft0), 0, g->res.y - 1), clamp((int)floor(ft1), 0, g->res.y - 1));
    return true;
}

// counts[i] = tiles of triangle i; flags[i]: bit 0 culled, bit 1 widened (pole or seam), also
// counted into st (one local count per work-group, one global add); place[i] = (tile range ia0,
// ia1, it0, it1) and place_slab[i] for pg_tri_write; box[i] = the triangle's angular box (alpha
// min, max, theta min, max, grown by the margin), which the trace tests each ray's angles against
// before the triangle itself (the tile test at full resolution)
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_tri_count(__global const PGrid *grid, __global const float4 *tris, const uint n, __global uint *counts,
                  __global uint *flags, __global int4 *place, __global int *place_slab, __global float *tri_dmin,
                  __global uint *st, __global float4 *tri_box) {
    __local uint tally[4];
    uint i = get_global_id(0), lid = get_local_id(0);
    if (lid == 0) { tally[0] = 0u; tally[1] = 0u; tally[2] = 0u; tally[3] = 0xffffffffu; }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (i < n) {
        PGrid g = *grid;
        int4 r = (int4)(0);
        int slab = 0;
        bool full, back;
        float dmin = 0.0f;
        float4 box = (float4)(0.0f);
        bool ok = pg_tri(&g, tris, i, &r, &slab, &full, &back, &dmin, &box);
        tri_dmin[i] = dmin;
        tri_box[i] = box;
        if (ok) atomic_min(&tally[3], pg_ord(dmin));
        counts[i] = ok ? (uint)(r.y - r.x + 1) * (uint)(r.w - r.z + 1) : 0u;
        flags[i] = (ok ? 0u : 1u) | (full ? 2u : 0u);
        place[i] = r;
        place_slab[i] = slab;
        if (!ok) atomic_inc(&tally[0]);
        if (full) atomic_inc(&tally[1]);
        if (back) atomic_inc(&tally[2]);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) {
        if (tally[0]) atomic_add(&st[PG_ST_CULLED], tally[0]);
        if (tally[1]) atomic_add(&st[PG_ST_WIDENED], tally[1]);
        if (tally[2]) atomic_add(&st[PG_ST_BACK], tally[2]);
        if (tally[3] != 0xffffffffu) atomic_min(&st[PG_ST_DNEAR], tally[3]);
    }
}

// Distance levels within a cell: QB = up.w bits (0: none) of the triangles' distance lower bounds
// from dnear (the nearest, PG_ST_DNEAR) to the end of the last slab, on the float's own bit
// pattern (monotone in a positive float and close to log2: no libm log / exp, which are slow on CPU
// devices): level = (bits(d) - bits(dnear)) >> shift, with shift fitting the span into QB bits.
// The pair key is (cell << QB) | level, so the sort leaves every cell's triangles nearest first and
// a closest-hit ray can stop inside a cell (trace.cl): every triangle of level >= q is at least
// as_float(bits(dnear) + (q << shift)) from E, exactly. levels[0] = (dnear, shift, 0, 0).
inline float2 pg_levels(const PGrid *g, __global const uint *st) {
    uint qb = (uint)g->up.w;
    float dmax = g->slab.w + (float)g->res.z * g->slab.x;
    float dnear = pg_unord(st[PG_ST_DNEAR]);
    if (!(dnear > 0.0f && dnear < dmax && isfinite(dmax)) || qb == 0u) return (float2)(0.0f, -1.0f);
    uint span = as_uint(dmax) - as_uint(dnear);
    int bits = 32 - (int)clz(span);
    return (float2)(dnear, (float)max(0, bits - (int)qb));
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_tri_write(__global const PGrid *grid, const uint n, __global const uint *offsets,
                  __global const int4 *place, __global const int *place_slab, __global const uint *flags,
                  __global const float *tri_dmin, __global const uint *st, __global float4 *levels,
                  __global uint *keys, __global uint *vals, __global const uint *pairs, const uint cap) {
    uint i = get_global_id(0);
    PGrid g = *grid;
    float2 lv = pg_levels(&g, st);
    if (i == 0) levels[0] = (float4)(lv.x, lv.y, 0.0f, 0.0f);
    if (i >= n || *pairs > cap) return;  // overflow: nothing is written (pg_ray_keys sends the rays elsewhere)
    if (flags[i] & 1u) return;
    int4 r = place[i];
    int slab = place_slab[i];
    uint qb = (uint)g.up.w, q = 0u;
    float d = tri_dmin[i];
    if (lv.y >= 0.0f && d > lv.x)
        q = min((1u << qb) - 1u, (as_uint(d) - as_uint(lv.x)) >> (uint)lv.y);
    uint o = offsets[i];
    for (int it = r.z; it <= r.w; ++it)
        for (int ia = r.x; ia <= r.y; ++ia) {
            keys[o] = ((uint)((ia + g.res.x * it) * g.res.z + slab) << qb) | q;
            vals[o] = i;
            ++o;
        }
}

// counts per cell from the segments of the sorted pair keys (zero-filled before; a cell's
// segments are its distance levels)
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_cell_counts(__global const PGrid *grid, __global const uint *seg_key, __global const uint *seg_len,
                    __global const uint *m_ptr, __global uint *counts) {
    uint i = get_global_id(0);
    if (i >= *m_ptr) return;  // the segment count, on the device (launched for a bound)
    atomic_add(&counts[seg_key[i] >> (uint)grid->up.w], seg_len[i]);  // up.w: the distance level bits
}

// The pairs the sort and the cell ranges take: the total, or 0 when it overflowed the buffers.
__kernel void pg_pairs_clamp(__global const uint *pairs, const uint cap, __global uint *n_eff) {
    n_eff[0] = *pairs <= cap ? *pairs : 0u;
}

// The grid's frame from a strided sample of the rays (one work-group of WG): fwd = the mean
// direction from E of the sampled active rays (the direction of their segments, turned away from
// E), so the rays lie far from the poles +-up of the spherical mapping; up = the world axis least
// aligned with fwd, made orthogonal to it; right = up x fwd. Any orthonormal frame is exact (the
// boxes are conservative in every frame); this one keeps tiles and boxes tight. The host's
// choose_frame (pointgrid.py) is the same in float64.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void pg_frame(__global PGrid *grid, __global const float4 *ray_o, __global const float4 *ray_d, const uint step,
              const uint count) {
#ifdef RT_HAVE_FP64
    typedef double real;
    typedef double3 real3;
#define TO_REAL3 convert_double3
#else
    typedef float real;
    typedef float3 real3;
#define TO_REAL3(v) (v)
#endif
    __local real sx[WG], sy[WG], sz[WG];
    __local uint sn[WG];
    uint lid = get_local_id(0);
    real3 E = TO_REAL3(grid->centre.xyz);
    real3 acc = (real3)(0);
    uint act = 0u;
    for (uint k = lid; k < count; k += WG) {
        float4 ot = ray_o[(size_t)k * step], dt = ray_d[(size_t)k * step];
        if (!(dt.w > ot.w) || !all(isfinite(ot)) || !all(isfinite(dt.xyz))) continue;
        real3 d = TO_REAL3(dt.xyz);
        real len = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
        if (!(len > 0)) continue;
        real3 dn = d / len;
        real3 p = TO_REAL3(ot.xyz) + (real)ot.w * d - E;
        real lam = p.x * dn.x + p.y * dn.y + p.z * dn.z;
        acc += lam >= 0 ? dn : -dn;
        ++act;
    }
    sx[lid] = acc.x; sy[lid] = acc.y; sz[lid] = acc.z; sn[lid] = act;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid != 0) return;
    real3 m = (real3)(0);
    uint total = 0u;
    for (uint k = 0; k < WG; ++k) { m += (real3)(sx[k], sy[k], sz[k]); total += sn[k]; }
    real ml = sqrt(m.x * m.x + m.y * m.y + m.z * m.z);
    real3 f = (total && ml > (real)1e-9 * (real)total) ? m / ml : (real3)(0, 0, -1);
    real3 af = fabs(f);
    real3 axis = (af.x <= af.y && af.x <= af.z) ? (real3)(1, 0, 0) : (af.y <= af.z ? (real3)(0, 1, 0) : (real3)(0, 0, 1));
    real3 up = axis - f * (axis.x * f.x + axis.y * f.y + axis.z * f.z);
    up /= sqrt(up.x * up.x + up.y * up.y + up.z * up.z);
    real3 right = (real3)(up.y * f.z - up.z * f.y, up.z * f.x - up.x * f.z, up.x * f.y - up.y * f.x);
    grid->fwd.xyz = convert_float3(f);
    grid->up.xyz = convert_float3(up);
    grid->right.xyz = convert_float3(right);
#undef TO_REAL3
}

// The grid's placement from the rays' statistics (pg_classify's st), in one work-item, so no
// count comes back to the host: the margin (the largest deviation of a ray in the grid, at most
// spec.x, plus the angles' error err), the rays' angular rectangle grown by twice the margin, the
// tiles over it (pointgrid.py tile_counts: ~spec.y rays per tile, or spec.z tiles on the longer
// side, or tiles of spec.w radians; at most 1024 per axis and tiles_cap in all: the bound the
// host sized its buffers by), cells = tiles * slabs, and the distance level bits (key_bits less
// the cell bits). n_cells[0] = cells + 1 (the cell_start scan's length).
__kernel void pg_place(__global PGrid *grid, __global const uint *st, const uint n, const float4 spec,
                       const float err, const uint tiles_cap, const uint key_bits, __global uint *n_cells) {
    PGrid g = *grid;
    uint in_grid = n - st[PG_ST_OUTSIDE] - st[PG_ST_INACTIVE];
    float m = in_grid ? pg_unord(st[PG_ST_DEV]) * (1.0f + 1e-4f) + 1e-6f : spec.x;
    m = fmin(m, spec.x) + err;
    float a0 = 0.0f, a1 = 0.0f, e0 = 0.0f, e1 = 0.0f;
    if (in_grid) {
        a0 = pg_unord(st[PG_ST_A0]); a1 = pg_unord(st[PG_ST_A1]);
        e0 = pg_unord(st[PG_ST_T0]); e1 = pg_unord(st[PG_ST_T1]);
    }
    a0 = fmax(a0 - 2.0f * m, -M_PI_F); a1 = fmin(a1 + 2.0f * m, M_PI_F);
    e0 = fmax(e0 - 2.0f * m, -M_PI_2_F); e1 = fmin(e1 + 2.0f * m, M_PI_2_F);
    float span_a = fmax((a1 - a0) * (e0 * e1 > 0.0f ? cos(fmin(fabs(e0), fabs(e1))) : 1.0f), 1e-9f);
    float span_t = fmax(e1 - e0, 1e-9f);
    float k;
    if (spec.w > 0.0f) k = 1.0f / spec.w;
    else if (spec.z > 0.0f) k = spec.z / fmax(span_a, span_t);
    else k = sqrt((float)max(in_grid, 1u) / fmax(spec.y, 1.0f) / (span_a * span_t));
    int na = (int)clamp(round(span_a * k), 1.0f, 1024.0f), nt = (int)clamp(round(span_t * k), 1.0f, 1024.0f);
    if ((uint)(na * nt) > tiles_cap) nt = max(1, (int)(tiles_cap / (uint)na));  // never, by the host's bound
    int ns = g.res.z;
    uint ncells = (uint)(na * nt * ns);
    uint cell_bits = max(1u, 32u - clz(ncells - 1u));
    grid->centre.w = m;
    grid->rect = (float4)(a0, e0, (float)na / (a1 - a0), (float)nt / (e1 - e0));
    grid->res = (int4)(na, nt, ns, (int)ncells);
    grid->up.w = (float)(key_bits > cell_bits ? key_bits - cell_bits : 0u);
    n_cells[0] = ncells + 1u;
}

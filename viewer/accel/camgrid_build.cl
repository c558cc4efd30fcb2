// Camera perspective grid build (layout: viewer/cl/kernels/camgrid.cl; host: camgrid.py).
// Per triangle, in double: back-face culling (when enabled), the triangle clipped to the view
// frustum grown by `margin` pixels (Sutherland-Hodgman in projective space, so triangles with no
// vertex inside the frustum and triangles crossing the eye plane are handled exactly), the
// clipped polygon's pixel rectangle (grown by the margin) and depth range give the tiles and
// slabs it overlaps: one (cell, triangle) pair per cell of that tile x slab box.
#include "camgrid.cl"

#ifndef WG
#define WG 64
#endif

#define CG_CULL_BACK 1u
#define CG_CULL_FRUSTUM 2u
#define CG_NEAR_EYE 4u

// The float32 intersection test (geometry.cl) decides hit or miss from vertex coordinates taken
// relative to the ray origin (here the eye), each rounded, so near an edge its answer is that of
// the triangle moved by up to a few float32 ulps of the vertices' distance from the eye: far away
// in absolute terms when a huge triangle passes close to the eye (a 2e4 ground 1e-3 below it: the
// two ground triangles' shared edge lies 1e-3 from the eye and float32 puts hits 1.1e-3 on the far
// side of it). A grid that binned the exact triangle would lose those hits (the other triangle's
// float test misses them: watertight, one of the two is hit). So every triangle is binned grown by
// CG_FLOAT_REACH * (largest vertex coordinate relative to the eye): 32 ulps (2^-24 each), several
// times the test's bound (about 6 ulps: the sheared coordinates' rounding, 3 ulps each, through
// the edge functions' products), and tiny for ordinary triangles (2e-6 of their distance).
#define CG_FLOAT_REACH (32.0 / 16777216.0)

#ifdef RT_HAVE_FP64
// The part of the convex polygon p[0..n) with dot(plane, x) + off >= 0, written to out; its size.
inline int cg_clip(const double3 *p, int n, double3 plane, double off, double3 *out) {
    int m = 0;
    for (int i = 0; i < n; ++i) {
        double3 a = p[i], b = p[(i + 1) % n];
        double da = dot(plane, a) + off, db = dot(plane, b) + off;
        if (da >= 0.0) out[m++] = a;
        if ((da >= 0.0) != (db >= 0.0)) out[m++] = a + (da / (da - db)) * (b - a);
    }
    return m;
}

// Grows (x0, x1, y0, y1) to hold the pixel points of the box q +- (dx, dy, dz) (q.z - dz > 0): the
// extremes lie at its corners; along a polygon edge these bounds are linear-fractional, so the
// vertices' boxes bound the edge's too. The double rounding is far inside the pixel margin.
inline void cg_vertex_box(double3 q, double dx, double dy, double dz, double *x0, double *x1, double *y0,
                          double *y1) {
    double in = 1.0 / (q.z - dz), jf = 1.0 / (q.z + dz);
    double xl = q.x - dx, xh = q.x + dx, yl = q.y - dy, yh = q.y + dy;
    *x0 = fmin(*x0, fmin(xl * in, xl * jf));
    *x1 = fmax(*x1, fmax(xh * in, xh * jf));
    *y0 = fmin(*y0, fmin(yl * in, yl * jf));
    *y1 = fmax(*y1, fmax(yh * in, yh * jf));
}

// Tile range (tx0, tx1, ty0, ty1), pixel rectangle (x0, x1, y0, y1, grown by the margin: no ray
// from the eye outside it can meet the triangle, in float32 either) and depth range of triangle i;
// false when culled (*flag says why).
inline bool cg_tri(const CGrid *g, __global const float4 *tris, uint i, int4 *range, double4 *rect, double2 *depth,
                   uint *flag) {
    double3 E = g->eye.xyz;
    double3 v0 = convert_double3(tris[3 * i].xyz) - E, v1 = convert_double3(tris[3 * i + 1].xyz) - E,
            v2 = convert_double3(tris[3 * i + 2].xyz) - E;
    *flag = 0u;
    if (!(g->cells.w & CG_VALID)) { *flag = CG_CULL_FRUSTUM; return false; }  // no camera: no grid
    if (!(all(isfinite(v0)) && all(isfinite(v1)) && all(isfinite(v2)))) { *flag = CG_CULL_FRUSTUM; return false; }
    if (rt_two_equal_vertices(tris[3 * i].xyz, tris[3 * i + 1].xyz, tris[3 * i + 2].xyz)) {  // never hit
        *flag = CG_CULL_FRUSTUM;
        return false;
    }
    if (g->cells.w & 1) {  // back-face culling: the eye is behind the triangle's plane (clearly)
        double3 nrm = cross(v1 - v0, v2 - v0);
        if (dot(nrm, v0) > 1e-9 * length(nrm) * length(v0)) { *flag = CG_CULL_BACK; return false; }
    }
    double W = g->screen.x, H = g->screen.y, m = g->screen.z;
    // the float test's reach (CG_FLOAT_REACH) in world units, and what it moves q = M^-1 v by
    // (g->norms: |rows of M^-1|, from the host)
    double big_v = fmax(fmax(fmax(fabs(v0.x), fabs(v0.y)), fmax(fabs(v0.z), fabs(v1.x))),
                        fmax(fmax(fabs(v1.y), fabs(v1.z)), fmax(fabs(v2.x), fmax(fabs(v2.y), fabs(v2.z)))));
    double reach = CG_FLOAT_REACH * big_v;
    double dx = reach * g->norms.x, dy = reach * g->norms.y, dz = reach * g->norms.z;
    double3 q0 = cg_project(g, v0), q1 = cg_project(g, v1), q2 = cg_project(g, v2);
    // the frustum grown by the margin (pixels) and by the reach (world: the plane moved by reach *
    // |M^-T p|, bounded by the triangle inequality over the rows)
    double3 pl[4] = {(double3)(1.0, 0.0, m), (double3)(-1.0, 0.0, W + m), (double3)(0.0, 1.0, m),
                     (double3)(0.0, -1.0, H + m)};
    double off[4] = {dx + m * dz, dx + (W + m) * dz, dy + m * dz, dy + (H + m) * dz};
    bool inside = true;
    for (int k = 0; k < 4; ++k) {  // most triangles lie inside every plane (no clip) or outside one
        double d0 = dot(pl[k], q0) + off[k], d1 = dot(pl[k], q1) + off[k], d2 = dot(pl[k], q2) + off[k];
        if (d0 < 0.0 && d1 < 0.0 && d2 < 0.0) { *flag = CG_CULL_FRUSTUM; return false; }
        inside = inside && d0 >= 0.0 && d1 >= 0.0 && d2 >= 0.0;
    }
    double zmin, zmax, big;
    double x0 = 0.0, x1 = W, y0 = 0.0, y1 = H;
    if (inside) {  // the common case, without the polygon arrays
        zmin = fmin(fmin(q0.z, q1.z), q2.z) - dz;
        zmax = fmax(fmax(q0.z, q1.z), q2.z) + dz;
        double3 aq0 = fabs(q0), aq1 = fabs(q1), aq2 = fabs(q2);
        double3 mq = fmax(fmax(aq0, aq1), aq2);
        big = fmax(fmax(mq.x, mq.y), mq.z);
        if (!(zmax > 0.0)) { *flag = CG_CULL_FRUSTUM; return false; }
        if (zmin > 1e-9 * big) {
            x0 = INFINITY; x1 = -INFINITY; y0 = INFINITY; y1 = -INFINITY;
            cg_vertex_box(q0, dx, dy, dz, &x0, &x1, &y0, &y1);
            cg_vertex_box(q1, dx, dy, dz, &x0, &x1, &y0, &y1);
            cg_vertex_box(q2, dx, dy, dz, &x0, &x1, &y0, &y1);
        } else {
            *flag = CG_NEAR_EYE;
        }
    } else {
        double3 a[7], b[7];
        a[0] = q0;
        a[1] = q1;
        a[2] = q2;
        int n = 3;
        n = cg_clip(a, n, pl[0], off[0], b);
        n = cg_clip(b, n, pl[1], off[1], a);
        n = cg_clip(a, n, pl[2], off[2], b);
        n = cg_clip(b, n, pl[3], off[3], a);
        if (n == 0) { *flag = CG_CULL_FRUSTUM; return false; }
        zmin = INFINITY; zmax = -INFINITY; big = 0.0;
        for (int k = 0; k < n; ++k) {
            zmin = fmin(zmin, a[k].z);
            zmax = fmax(zmax, a[k].z);
            big = fmax(big, fmax(fabs(a[k].x), fmax(fabs(a[k].y), fabs(a[k].z))));
        }
        zmin -= dz;
        zmax += dz;
        if (!(zmax > 0.0)) { *flag = CG_CULL_FRUSTUM; return false; }
        if (zmin > 1e-9 * big) {  // else the grown polygon reaches the eye: it may cover any pixel
            x0 = INFINITY; x1 = -INFINITY; y0 = INFINITY; y1 = -INFINITY;
            for (int k = 0; k < n; ++k) cg_vertex_box(a[k], dx, dy, dz, &x0, &x1, &y0, &y1);
        } else {
            *flag = CG_NEAR_EYE;
        }
    }
    double T = (double)g->tiles.x;
    *rect = (double4)(x0 - m, x1 + m, y0 - m, y1 + m);
    *range = (int4)((int)clamp(floor((x0 - m) / T), 0.0, (double)(g->tiles.y - 1)),
                    (int)clamp(floor((x1 + m) / T), 0.0, (double)(g->tiles.y - 1)),
                    (int)clamp(floor((y0 - m) / T), 0.0, (double)(g->tiles.z - 1)),
                    (int)clamp(floor((y1 + m) / T), 0.0, (double)(g->tiles.z - 1)));
    *depth = (double2)(fmax(zmin, 0.0), zmax);
    return true;
}

#endif

// Pass 1 per triangle: flags[i] (CG_* bits), place[i] = tile range, rect[i] = pixel rectangle
// (float, rounded outwards; everything for a triangle reaching the eye), depth range
// zlo[i]..zhi[i] (+inf / -inf when culled).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void cg_tri_clip(__global const CGrid *grid, __global const float4 *tris, const uint n, __global uint *flags,
                 __global int4 *place, __global float4 *rect, __global float *zlo, __global float *zhi) {
    uint i = get_global_id(0);
    if (i >= n) return;
    CGrid g = *grid;
    int4 r = (int4)(0);
    uint flag = CG_CULL_FRUSTUM;
    bool ok = false;
    float z0 = INFINITY, z1 = -INFINITY;
    float4 box = (float4)(INFINITY, -INFINITY, INFINITY, -INFINITY);
#ifdef RT_HAVE_FP64
    double2 z = (double2)(0.0);
    double4 b = (double4)(0.0);
    ok = cg_tri(&g, tris, i, &r, &b, &z, &flag);
    if (ok) {
        z0 = cg_down(z.x);
        z1 = cg_up(z.y);
        box = flag == CG_NEAR_EYE ? (float4)(-INFINITY, INFINITY, -INFINITY, INFINITY)
                                  : (float4)(cg_down(b.x), cg_up(b.y), cg_down(b.z), cg_up(b.w));
    }
#endif
    flags[i] = flag;
    place[i] = r;
    rect[i] = box;
    zlo[i] = z0;
    zhi[i] = z1;
}

// Slab placement, on the device (no wait), by one work-group: a strided sample of at most
// DEPTH_SAMPLES triangles' nearest depths zlo (+inf when culled) is sorted in local memory (bitonic)
// and the S - 1 inner bounds are put at its quantiles among the visible ones: slabs of about equal
// triangle counts, however spread the depths are (a 1e-3 object before a 1e4 wall gets all the
// slabs). Where the bounds lie is only a heuristic; binning and trace read the same bounds.
#define DEPTH_SAMPLES 2048
#define BOUNDS_WG 256
__kernel __attribute__((reqd_work_group_size(BOUNDS_WG, 1, 1)))
void cg_slab_bounds(const uint n, const int S, __global const float *zlo, __global cg_bound *bounds) {
    __local float z[DEPTH_SAMPLES];
    __local uint visible;
    uint lid = get_local_id(0);
    uint m = min(n, (uint)DEPTH_SAMPLES), stride = max(1u, n / (uint)DEPTH_SAMPLES);
    for (uint k = lid; k < DEPTH_SAMPLES; k += BOUNDS_WG) {
        float v = k < m ? zlo[k * stride] : INFINITY;
        z[k] = v == v ? v : INFINITY;
    }
    if (lid == 0) visible = 0u;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (uint size = 2; size <= DEPTH_SAMPLES; size <<= 1)
        for (uint j = size >> 1; j > 0; j >>= 1) {
            for (uint p = lid; p < DEPTH_SAMPLES / 2; p += BOUNDS_WG) {
                uint i = 2u * j * (p / j) + (p % j), l = i + j;
                bool up = (i & size) == 0u;
                float x = z[i], y = z[l];
                if ((x > y) == up) { z[i] = y; z[l] = x; }
            }
            barrier(CLK_LOCAL_MEM_FENCE);
        }
    uint mine = 0u;
    for (uint k = lid; k < DEPTH_SAMPLES; k += BOUNDS_WG) mine += isfinite(z[k]) ? 1u : 0u;
    atomic_add(&visible, mine);
    barrier(CLK_LOCAL_MEM_FENCE);
#ifdef RT_HAVE_FP64
    uint vis = visible;
    for (int s = (int)lid; s <= S; s += BOUNDS_WG) {
        double b;
        if (s == S) b = INFINITY;
        else if (vis == 0u) b = 1.0 + (double)s / (double)S;  // nothing visible: any increasing bounds
        else b = (double)z[(uint)(((ulong)s * vis) / (ulong)S)];
        bounds[s] = b;
    }
#endif
}

// Pass 2, once the slabs are placed: counts[i] = cells of triangle i (0 when culled), place_slab[i]
// (its slab range; (-1, -1): the big list). A triangle reaching more than CG_BIG_SPAN slabs (a floor
// or wall seen along its length, a triangle near the eye) goes into its tiles' big lists instead,
// which the trace tests once before the slabs: listed in every slab it would be tested once per
// slab by a ray crossing them all (2 ground triangles x 16 slabs: most tests of the mixed scene).
#define CG_BIG_SPAN 2
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void cg_tri_count(__global const CGrid *grid, const uint n, __global const uint *flags, __global const int4 *place,
                  __global const float *zlo, __global const float *zhi, __global const cg_bound *bounds,
                  __global uint *counts, __global int2 *place_slab) {
    uint i = get_global_id(0);
    if (i >= n) return;
    CGrid g = *grid;
    uint c = 0u;
    int2 s = (int2)(0);
#ifdef RT_HAVE_FP64
    if (flags[i] == 0u || flags[i] == CG_NEAR_EYE) {
        int4 r = place[i];
        s = (int2)(cg_slab(bounds, g.tiles.w, (double)zlo[i]), cg_slab(bounds, g.tiles.w, (double)zhi[i]));
        if (s.y - s.x + 1 > CG_BIG_SPAN) s = (int2)(-1);  // the tile's big list, tested once
        c = (uint)(r.y - r.x + 1) * (uint)(r.w - r.z + 1) * (uint)(s.y - s.x + 1);
    }
#endif
    counts[i] = c;
    place_slab[i] = s;
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void cg_tri_write(__global const CGrid *grid, const uint n, __global const uint *pairs, const uint capacity,
                  __global const uint *offsets,
                  __global const uint *counts,
                  __global const int4 *place, __global const int2 *place_slab, __global uint *keys,
                  __global uint *vals) {
    uint i = get_global_id(0);
    if (i >= n || counts[i] == 0u || *pairs > capacity) return;  // overflow: no grid (n_eff is 0)
    CGrid g = *grid;
    int4 r = place[i];
    int2 s = place_slab[i];
    uint o = offsets[i];
    int S1 = g.tiles.w + 1;  // cells per tile: the big list (0), then slab s at s + 1
    for (int ty = r.z; ty <= r.w; ++ty)
        for (int tx = r.x; tx <= r.y; ++tx)
            for (int sl = s.x; sl <= s.y; ++sl) {
                keys[o] = (uint)((ty * g.tiles.y + tx) * S1 + sl + 1);
                vals[o] = i;
                ++o;
            }
}

// Cell ranges from the segments of the sorted keys (cells zero-filled before).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void cg_ranges(__global const uint *seg_key, __global const uint *seg_start, __global const uint *seg_len,
               __global const uint *m_ptr, __global uint2 *cells) {
    uint i = get_global_id(0);
    if (i >= *m_ptr) return;  // the segment count, on the device (launched for a bound)
    cells[seg_key[i]] = (uint2)(seg_start[i], seg_len[i]);
}

// Per ray: outside[i] = 1 when ray i cannot be traced through the grid: it does not start at the
// eye, or its direction does not pass within margin / 2 pixels of its own tile (a ray that is not
// the pixel ray of its index), or there is no grid this pass (no camera fits the batch, or the
// pairs outgrew the buffer sized from the last frame: the caller grows it for the next one). Inactive rays stay inside (the trace writes a miss for them).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void cg_classify(__global const CGrid *grid, __global const float4 *ray_o, __global const float4 *ray_d,
                 const uint n, __global const uint *pairs, const uint capacity, __global uint *outside) {
    uint i = get_global_id(0);
    if (i >= n) return;
    CGrid g = *grid;
    float4 ot = ray_o[i], dt = ray_d[i];
    uint out = 1u;
    if (!(dt.w > ot.w)) {
        out = 0u;
    } else if (!(g.cells.w & CG_VALID) || *pairs > capacity) {
        out = 1u;  // no camera fits the rays, or the pairs overflowed their buffer: no grid this pass
    } else {
#ifdef RT_HAVE_FP64
        float3 e = convert_float3(g.eye.xyz);
        if (ot.x == e.x && ot.y == e.y && ot.z == e.z && ot.w >= 0.0f && all(isfinite(dt.xyz))) {
            double3 q = cg_project(&g, convert_double3(dt.xyz));
            int W = g.cells.y;
            double T = (double)g.tiles.x, h = 0.5 * g.screen.z;
            double tx = (double)(((int)i % W) / g.tiles.x), ty = (double)(((int)i / W) / g.tiles.x);
            if (q.z > 0.0) {
                double x = q.x / q.z, y = q.y / q.z;
                if (x >= tx * T - h && x <= (tx + 1.0) * T + h && y >= ty * T - h && y <= (ty + 1.0) * T + h)
                    out = 0u;
            }
        }
#endif
    }
    outside[i] = out;
}

#ifdef RT_HAVE_FP64
inline double cg_det3(double3 a, double3 b, double3 c) { return dot(a, cross(b, c)); }
#endif

// One work-item: the pinhole camera of a w x h image of rays from its four corner rays, on the
// device (fit_camera in camgrid.py is the same algebra on the host): the un-normalised corner
// directions s_k d_k form a parallelogram (s_00 = 1), which fixes M = (dx, dy, c) with
// direction(x, y) ~ M (x, y, 1). Writes eye, M^-1, its row norms and the flags (CG_VALID when the
// corners share one finite origin and span a pinhole image; back-face culling when the scene is
// closed and faces outwards and the eye is outside the scene box [lo, hi]). The host never waits
// for the camera.
__kernel void cg_fit(__global CGrid *g, __global const float4 *ray_o, __global const float4 *ray_d, const int w,
                     const int h, const int closed, const float4 lo, const float4 hi) {
    if (get_global_id(0) != 0) return;
#ifdef RT_HAVE_FP64
    int idx[4] = {0, w - 1, (h - 1) * w, h * w - 1};
    float4 o0 = ray_o[idx[0]];
    bool ok = w >= 2 && h >= 2;
    double3 d[4];
    for (int k = 0; k < 4; ++k) {
        float4 o = ray_o[idx[k]], dk = ray_d[idx[k]];
        ok = ok && all(isfinite(o)) && all(isfinite(dk.xyz)) && dk.w > o.w && o.x == o0.x && o.y == o0.y &&
             o.z == o0.z;
        d[k] = convert_double3(dk.xyz);
    }
    double3 ca = d[3], cb = -d[1], cc = -d[2], rhs = -d[0];
    double det = cg_det3(ca, cb, cc);
    ok = ok && fabs(det) >= 1e-12 * length(ca) * length(cb) * length(cc);
    double s11 = cg_det3(rhs, cb, cc) / det, s10 = cg_det3(ca, rhs, cc) / det, s01 = cg_det3(ca, cb, rhs) / det;
    ok = ok && s11 > 0.0 && s10 > 0.0 && s01 > 0.0;
    double3 p00 = d[0], p10 = s10 * d[1], p01 = s01 * d[2];
    double3 dx = (p10 - p00) / (double)(w - 1), dy = (p01 - p00) / (double)(h - 1);
    double3 c = p00 - 0.5 * dx - 0.5 * dy;
    double dm = cg_det3(dx, dy, c);  // M's columns dx, dy, c: M^-1's rows are the cross products / det
    ok = ok && isfinite(dm) && fabs(dm) > 1e-300;
    double3 r0 = cross(dy, c) / dm, r1 = cross(c, dx) / dm, r2 = cross(dx, dy) / dm;
    ok = ok && all(isfinite(r0)) && all(isfinite(r1)) && all(isfinite(r2));
    g->eye = (double4)(convert_double3(o0.xyz), 0.0);
    g->minv[0] = (double4)(r0, 0.0);
    g->minv[1] = (double4)(r1, 0.0);
    g->minv[2] = (double4)(r2, 0.0);
    g->norms = (double4)(length(r0), length(r1), length(r2), 0.0) * (1.0 + 1e-12);  // rounded up
    bool outside_box = any(o0.xyz < lo.xyz) || any(o0.xyz > hi.xyz);
    g->cells.w = (ok ? CG_VALID : 0) | (ok && closed && outside_box ? 1 : 0);
#else
    g->cells.w = 0;
#endif
}

// n_eff: the count the sort and the segments read, 0 when the pairs overflowed the buffer (no
// pair is written then, and the pass's rays all go the other way).
__kernel void cg_pairs_clamp(__global const uint *pairs, const uint capacity, __global uint *n_eff) {
    if (get_global_id(0) == 0) *n_eff = *pairs > capacity ? 0u : *pairs;
}

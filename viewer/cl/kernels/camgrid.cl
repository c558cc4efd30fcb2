// Camera perspective grid (Patidar & Narayanan 2008; Guntury & Narayanan 2010): image tiles x
// depth slabs in the camera's projective space. viewer/accel/camgrid.py owns the layout.
//
// Header (CGRID_DTYPE, 224 bytes): eye (xyz), minv (rows of M^-1, where the un-normalised
// direction of the ray through pixel point (x, y) is M (x, y, 1)), screen (width, height, margin in
// pixels, 0), norms (|rows of M^-1|: what a world offset moves q by; 0), tiles (pixels per tile side
// T, tiles in x, tiles in y, slabs S), cells (tiles * (slabs + 1), image width, image height, flags:
// bit 0 back-face culling, bit 1 CG_VALID: a camera fits the rays, else no grid this pass). Ray i
// is the ray of pixel (i % width, i / width), through pixel point (x + 0.5, y + 0.5). A point P maps to q = M^-1 (P - eye): pixel (q.x / q.z, q.y / q.z),
// depth q.z (proportional to the distance along the viewing axis). Slab bounds: double (S + 1,),
// slab s holds depths in [bounds[s], bounds[s + 1]); slab 0 also holds everything nearer, the last
// everything farther; placed per frame at quantiles of the visible triangles' nearest depths
// (camgrid_build.cl: cg_slab_bounds), so every slab holds about as many triangles
// wherever they are (a 1e-3 object before a 1e4 wall gets all the slabs, not one).
// Cell id = (ty * tiles_x + tx) * (S + 1) + c: c = 0 the tile's big list (triangles reaching
// more than two slabs, tested once before the slabs), c = s + 1 slab s (a tile's cells, so its
// refs, are contiguous and in that order); cells: uint2 (first ref, ref count); refs:
// uint triangle slots grouped by cell.
// Without cl_khr_fp64 nothing is binned and every ray is "outside" (traced another way).
#include "geometry.cl"

typedef struct {
#ifdef RT_HAVE_FP64
    double4 eye;
    double4 minv[3];
    double4 screen;
    double4 norms;
#else
    float4 pad[12];
#endif
    int4 tiles;
    int4 cells;
} CGrid;

#define CG_VALID 2

// slab bounds' element type (double; without fp64 nothing is binned and the bounds are unused)
#ifdef RT_HAVE_FP64
typedef double cg_bound;
#else
typedef float cg_bound;
#endif

#ifdef RT_HAVE_FP64
inline double3 cg_project(const CGrid *g, double3 v) {
    return (double3)(dot(g->minv[0].xyz, v), dot(g->minv[1].xyz, v), dot(g->minv[2].xyz, v));
}

// float32 bounds of a double, rounded down / up (one ulp step by the bits, not libm's nextafter:
// a call a CPU device cannot run in SIMD; +-inf and NaN pass through)
inline float cg_step(float f, bool up) {
    int b = as_int(f);
    int s = (f > 0.0f) == up ? 1 : -1;
    float g = f == 0.0f ? (up ? 1.401298464e-45f : -1.401298464e-45f) : as_float(b + s);
    return isfinite(f) ? g : f;
}
inline float cg_down(double x) { float f = (float)x; return (double)f > x ? cg_step(f, false) : f; }
inline float cg_up(double x) { float f = (float)x; return (double)f < x ? cg_step(f, true) : f; }

// Slab of depth z: the largest s in [0, S) with bounds[s] <= z (slab 0 also holds everything
// nearer, the last everything farther). Exact comparisons of doubles, so a triangle whose depth
// range [zlo, zhi] (rounded outwards) is binned into cg_slab(zlo)..cg_slab(zhi) is in every slab it
// reaches, and a ray whose hit depth is below bounds[s + 1] has met every nearer triangle by slab s.
inline int cg_slab(__global const cg_bound *bounds, int S, double z) {
    int lo = 0, hi = S - 1;
    while (lo < hi) {
        int mid = (lo + hi + 1) >> 1;
        if (bounds[mid] <= z) lo = mid; else hi = mid - 1;
    }
    return lo;
}
#endif

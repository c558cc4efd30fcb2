// Two-level grid (Kalojanov, Billeter & Slusallek 2011; viewer/accel/grid2.py owns the layout):
// the uniform grid of grid.cl on top, unchanged, and for each dense top cell a sub-grid fitted to
// the box of the cell's small triangles plus a short list of the cell's big triangles.
//
// sub_of : int per top cell: its sub-grid, or -1 (the cell's own top-level blocks are tested)
// subs   : SubGrid per sub-grid (64 bytes)
// scells : uint2 per sub-cell (first ref, count), sub-cell id = res.w + x + res.x * (y + res.y * z)
// sblocks, scb: the sub-cells' SoA blocks and block starts (as the top grid's blocks)
// bblocks: the big triangles' SoA blocks; sub-grid s's big.y triangles start at block big.x
//
// The sub-grid lives in world coordinates minus its own float32 corner `lo` (not the top grid's:
// a 1e-3 object in a 2e4 grid would lose its detail to the top grid's local rounding). The walk
// computes that local origin and its plane distances in double where the device has it
// (cl_khr_fp64): a float32 walk of a ray from 1e4 away is off by ulp(1e4) = 1e-3 in position,
// far more than the object's sub-cells; in double the error is ~1e-12 and the binning margin
// (eps sub-cells, as the top grid's: 1e-3 + 32 ulp(extent) / cell) covers it.
#include "grid.cl"

typedef struct {
    float4 lo;    // world corner (float32 exactly), w = eps (binning margin, sub-cell units)
    float4 cell;  // cell size per axis, rounded up so that res * cell covers the box; w unused
    int4 res;     // cells per axis; w = the sub-grid's first sub-cell id
    uint4 big;    // x = first big block, y = big triangles; z, w unused
} SubGrid;

#ifdef RT_HAVE_FP64
typedef double g2real;
typedef double3 g2real3;
#define convert_g2real3 convert_double3
#define G2_INF ((double)INFINITY)
#else
typedef float g2real;
typedef float3 g2real3;
#define convert_g2real3 convert_float3
#define G2_INF INFINITY
#endif

// Sub-cell of local point p (clamped to the grid: the eps margin covers rounding at its faces).
inline int3 g2_cell_of(g2real3 p, g2real3 cell, int3 res) {
    g2real3 c = floor(p / cell);
    g2real3 top = convert_g2real3(res - 1);
    c = fmin(fmax(c, (g2real3)(0)), top);
    return convert_int3(c);
}

// One axis of the slab test in local coordinates; false when the ray is parallel and outside.
inline bool g2_slab(g2real o, g2real d, g2real hi, g2real *t0, g2real *t1) {
    if (d == (g2real)0) return o >= (g2real)0 && o <= hi;
    g2real a = -o / d, b = (hi - o) / d;
    *t0 = fmax(*t0, fmin(a, b));
    *t1 = fmin(*t1, fmax(a, b));
    return true;
}

inline g2real g2_next_plane(g2real o, g2real d, g2real cell, int c, int step) {
    if (step == 0) return G2_INF;
    return ((g2real)(c + (step > 0 ? 1 : 0)) * cell - o) / d;
}

// First sub-cell and boundary distances of the ray segment (t0, t1) inside sub-grid s; false when
// the segment misses its box.
typedef struct {
    int3 cell;
    int3 step;
    g2real3 o, d;
    g2real3 tnext;
    g2real t_exit;
} SubWalk;

inline bool g2_walk_begin(const SubGrid *s, const RayPre *r, float tmin, float tmax, SubWalk *w) {
    g2real3 cell = convert_g2real3(s->cell.xyz);
    g2real3 hi = cell * convert_g2real3(s->res.xyz);
    w->o = convert_g2real3(r->o) - convert_g2real3(s->lo.xyz);
    w->d = convert_g2real3(r->d);
    g2real t0 = (g2real)tmin, t1 = (g2real)tmax;
    if (!g2_slab(w->o.x, w->d.x, hi.x, &t0, &t1) || !g2_slab(w->o.y, w->d.y, hi.y, &t0, &t1) ||
        !g2_slab(w->o.z, w->d.z, hi.z, &t0, &t1) || !(t0 <= t1))
        return false;
    w->t_exit = t1;
    w->cell = g2_cell_of(w->o + t0 * w->d, cell, s->res.xyz);
    w->step = (int3)(w->d.x > 0 ? 1 : (w->d.x < 0 ? -1 : 0), w->d.y > 0 ? 1 : (w->d.y < 0 ? -1 : 0),
                     w->d.z > 0 ? 1 : (w->d.z < 0 ? -1 : 0));
    w->tnext = (g2real3)(g2_next_plane(w->o.x, w->d.x, cell.x, w->cell.x, w->step.x),
                         g2_next_plane(w->o.y, w->d.y, cell.y, w->cell.y, w->step.y),
                         g2_next_plane(w->o.z, w->d.z, cell.z, w->cell.z, w->step.z));
    return true;
}

inline int g2_cell_id(const SubGrid *s, int3 c) {
    return s->res.w + c.x + s->res.x * (c.y + s->res.y * c.z);
}

inline g2real g2_cell_exit(const SubWalk *w) {
    return fmin(fmin(fmin(w->tnext.x, w->tnext.y), w->tnext.z), w->t_exit);
}

// Next sub-cell; false when the ray leaves the sub-grid or passes t_limit.
inline bool g2_walk_step(const SubGrid *s, SubWalk *w, float t_limit) {
    g2real tx = w->tnext.x, ty = w->tnext.y, tz = w->tnext.z;
    int axis = (tx <= ty) ? ((tx <= tz) ? 0 : 2) : ((ty <= tz) ? 1 : 2);
    g2real t = axis == 0 ? tx : (axis == 1 ? ty : tz);
    if (!(t < (g2real)t_limit) || !(t <= w->t_exit)) return false;
    g2real3 cell = convert_g2real3(s->cell.xyz);
    if (axis == 0) {
        w->cell.x += w->step.x;
        if (w->cell.x < 0 || w->cell.x >= s->res.x) return false;
        w->tnext.x = g2_next_plane(w->o.x, w->d.x, cell.x, w->cell.x, w->step.x);
    } else if (axis == 1) {
        w->cell.y += w->step.y;
        if (w->cell.y < 0 || w->cell.y >= s->res.y) return false;
        w->tnext.y = g2_next_plane(w->o.y, w->d.y, cell.y, w->cell.y, w->step.y);
    } else {
        w->cell.z += w->step.z;
        if (w->cell.z < 0 || w->cell.z >= s->res.z) return false;
        w->tnext.z = g2_next_plane(w->o.z, w->d.z, cell.z, w->cell.z, w->step.z);
    }
    return true;
}

// Uniform grid shared by the grid builders and walkers (viewer/accel/grid.py owns the layout).
//
// Header (GRID_DTYPE, 96 bytes): lo, hi (grid bounds, w unused), cell (cell size per axis),
// inv (1 / cell size), eps (binning margin per axis in cell units: a triangle's box is grown by
// eps before it is binned, so that float rounding in the walk never skips a cell a hit lies in),
// res (cells per axis, w = total cells). Cells: uint2 (first ref, ref count) per cell, cell id
// x + res.x * (y + res.y * z); refs: uint triangle slots sorted by cell.
// Walk (Amanatides & Woo 3D-DDA): the next boundary distance per axis is recomputed from the
// plane position each step (no accumulated drift); axes with a zero direction component never
// step; a ray lying in a cell plane is binned to one side and the eps margin puts triangles
// touching that plane from the other side into its cells too.
// Local coordinates: the walk works on the ray origin minus the grid corner lo (as the build
// works on vertices minus lo) and cell planes at c * cell from it, so its rounding is relative to
// the grid's extent and the ray's distance, not to the absolute position (a scene at 1e6 walks
// as precisely as at the origin and eps need not grow with the coordinates).
#include "geometry.cl"

typedef struct {
    float4 lo;
    float4 hi;
    float4 cell;
    float4 inv;
    float4 eps;
    int4 res;
} Grid;

inline int grid_cell_id(const Grid *g, int3 c) {
    return c.x + g->res.x * (c.y + g->res.y * c.z);
}

typedef struct {
    int3 cell;
    int3 step;
    float3 tnext;   // distance to the next cell boundary per axis (INFINITY: never)
    float t_exit;   // where the ray leaves the grid (conservative), clipped to tmax
} GridWalk;

// Ray origin in grid-local coordinates.
inline float3 grid_local_origin(const Grid *g, const RayPre *r) {
    return r->o - g->lo.xyz;
}

inline float grid_next_plane(const Grid *g, const RayPre *r, int axis, int c, int step) {
    if (step == 0) return INFINITY;
    float plane = (float)(c + (step > 0 ? 1 : 0)) * rt_comp(g->cell.xyz, axis);
    float o = rt_comp(r->o, axis) - rt_comp(g->lo.xyz, axis);
    return (plane - o) * rt_comp(r->inv, axis);
}

// Starts a walk for the ray segment (tmin, tmax); false when the segment misses the grid box.
// *t_enter: where the walk starts (>= tmin).
inline bool grid_walk_begin(const Grid *g, const RayPre *r, float tmin, float tmax, GridWalk *w, float *t_enter) {
    float enter;
    if (!rt_intersect_box(r, g->lo.xyz, g->hi.xyz, tmin, tmax, &enter)) return false;
    float3 box_exit_t;
    {
        float3 t0 = (g->lo.xyz - r->o) * r->inv;
        float3 t1 = (g->hi.xyz - r->o) * r->inv;
        box_exit_t = fmax(t0, t1);
    }
    w->t_exit = fmin(fmin(fmin(box_exit_t.x, box_exit_t.y), box_exit_t.z) * RT_GAMMA3_SCALE, tmax);
    float3 p = grid_local_origin(g, r) + enter * r->d;
    float3 fc = floor(p * g->inv.xyz);
    float3 top = convert_float3(g->res.xyz - 1);
    fc = fmin(fmax(fc, (float3)(0.0f)), top);
    w->cell = convert_int3(fc);
    w->step = (int3)(r->d.x > 0.0f ? 1 : (r->d.x < 0.0f ? -1 : 0), r->d.y > 0.0f ? 1 : (r->d.y < 0.0f ? -1 : 0),
                     r->d.z > 0.0f ? 1 : (r->d.z < 0.0f ? -1 : 0));
    w->tnext = (float3)(grid_next_plane(g, r, 0, w->cell.x, w->step.x), grid_next_plane(g, r, 1, w->cell.y, w->step.y),
                        grid_next_plane(g, r, 2, w->cell.z, w->step.z));
    *t_enter = enter;
    return true;
}

// Distance at which the ray leaves the current cell (never beyond the grid exit).
inline float grid_cell_exit(const GridWalk *w) {
    return fmin(fmin(fmin(w->tnext.x, w->tnext.y), w->tnext.z), w->t_exit);
}

// Moves to the next cell along the ray; false when the ray leaves the grid or passes t_limit.
inline bool grid_walk_step(const Grid *g, const RayPre *r, GridWalk *w, float t_limit) {
    float tx = w->tnext.x, ty = w->tnext.y, tz = w->tnext.z;
    int axis = (tx <= ty) ? ((tx <= tz) ? 0 : 2) : ((ty <= tz) ? 1 : 2);
    float t = axis == 0 ? tx : (axis == 1 ? ty : tz);
    if (!(t < t_limit) || !(t <= w->t_exit)) return false;
    if (axis == 0) {
        w->cell.x += w->step.x;
        if (w->cell.x < 0 || w->cell.x >= g->res.x) return false;
        w->tnext.x = grid_next_plane(g, r, 0, w->cell.x, w->step.x);
    } else if (axis == 1) {
        w->cell.y += w->step.y;
        if (w->cell.y < 0 || w->cell.y >= g->res.y) return false;
        w->tnext.y = grid_next_plane(g, r, 1, w->cell.y, w->step.y);
    } else {
        w->cell.z += w->step.z;
        if (w->cell.z < 0 || w->cell.z >= g->res.z) return false;
        w->tnext.z = grid_next_plane(g, r, 2, w->cell.z, w->step.z);
    }
    return true;
}

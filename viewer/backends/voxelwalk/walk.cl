// voxelwalk: walking the shared uniform grid (viewer/accel/grid.py, layout and 3D-DDA in
// viewer/cl/kernels/grid.cl) one non-empty cell at a time, and the packed hit keys of EC mode.
//
// A walk can be resumed from a cell id alone: grid.cl's walk recomputes every boundary distance
// from the cell's planes (no accumulated state), so (ray, cell) gives exactly the state the walk
// had when it entered that cell. EC mode keeps only the next cell per ray between iterations.
#include "geometry.cl"
#include "grid.cl"

#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable

#define VW_NONE 0xffffffffu
#define VW_MISS_KEY 0xffffffffffffffffUL

// Walk state of ray r entering cell `id` (as grid_walk_begin would have left it there).
inline void vw_walk_at(const Grid *g, const RayPre *r, uint id, float tmax, GridWalk *w) {
    int rx = g->res.x, ry = g->res.y;
    int cid = (int)id;
    w->cell = (int3)(cid % rx, (cid / rx) % ry, cid / (rx * ry));
    float3 t0 = (g->lo.xyz - r->o) * r->inv;
    float3 t1 = (g->hi.xyz - r->o) * r->inv;
    float3 box_exit_t = fmax(t0, t1);
    w->t_exit = fmin(fmin(fmin(box_exit_t.x, box_exit_t.y), box_exit_t.z) * RT_GAMMA3_SCALE, tmax);
    w->step = (int3)(r->d.x > 0.0f ? 1 : (r->d.x < 0.0f ? -1 : 0), r->d.y > 0.0f ? 1 : (r->d.y < 0.0f ? -1 : 0),
                     r->d.z > 0.0f ? 1 : (r->d.z < 0.0f ? -1 : 0));
    w->tnext = (float3)(grid_next_plane(g, r, 0, w->cell.x, w->step.x), grid_next_plane(g, r, 1, w->cell.y, w->step.y),
                        grid_next_plane(g, r, 2, w->cell.z, w->step.z));
}

// Moves w forward to the first non-empty cell at or after the current one; false when the walk
// ends first (leaves the grid or passes t_limit). *cr: the cell's (first ref, count).
inline bool vw_next_nonempty(const Grid *g, __global const uint2 *cells, const RayPre *r, GridWalk *w,
                             float t_limit, uint2 *cr) {
    while (true) {
        uint2 c = cells[grid_cell_id(g, w->cell)];
        if (c.y) { *cr = c; return true; }
        if (!grid_walk_step(g, r, w, t_limit)) return false;
    }
}

// Hit keys: (distance, triangle) packed so that the unsigned 64-bit order is the order of the
// distances, then of the triangle slots; the minimum is the nearest hit, ties to the lowest slot.
inline ulong vw_pack(float t, uint slot) {
    uint u = as_uint(t);
    u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    return ((ulong)u << 32) | (ulong)slot;
}

inline float vw_key_t(ulong key) {
    if (key == VW_MISS_KEY) return INFINITY;
    uint u = (uint)(key >> 32);
    u = (u & 0x80000000u) ? (u & 0x7fffffffu) : ~u;
    return as_float(u);
}

inline int vw_key_id(ulong key) {
    return key == VW_MISS_KEY ? -1 : (int)(uint)(key & 0xffffffffUL);
}

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

// Empty-space skipping: two levels of blocks, 4^3 and 16^3 cells of the grid (clipped at its far
// faces); for each level one uchar per block (bx + brx * (by + bry * bz)) says whether any of its
// cells is non-empty (vw_macro_build). Primary rays that miss the scene spend most of their walk
// stepping through empty cells; a walk entering an empty block jumps straight to the first cell
// past it, with the exact state the cell-by-cell walk would have there.
#ifndef VW_SHIFT_FINE
#define VW_SHIFT_FINE 3
#endif
#ifndef VW_SHIFT_COARSE
#define VW_SHIFT_COARSE 0  // 0: one level (a 16^3 level over 4^3 measured no faster on the dragon)
#endif

inline int3 vw_block_res(const Grid *g, int shift) {
    return (g->res.xyz + ((1 << shift) - 1)) >> shift;
}

inline bool vw_block_empty(const Grid *g, __global const uchar *occ, int shift, int3 c) {
    int3 br = vw_block_res(g, shift), b = c >> shift;
    return occ[b.x + br.x * (b.y + br.y * b.z)] == 0;
}

// Moves w from a cell of an empty block (2^shift cells on a side) to the first cell past the
// block, as grid_walk_step repeated would (false where that walk ends first: leaving the grid,
// passing t_limit or the grid exit). The cell-by-cell walk is a merge of each axis's boundary
// crossings in time order (each axis's crossing distances grow with the cell index: the plane is
// recomputed from the index by monotone float operations), ties going to the lowest axis. The
// block is left at the first of the crossings of its three far faces (in that order); every other
// axis has made exactly its crossings that come before that one (found from an estimate of the
// cell at that distance, corrected against the crossings themselves), and the boundary distances
// are a function of the cell index, so the state there is the walk's own.
inline bool vw_skip_block(const Grid *g, const RayPre *r, GridWalk *w, float t_limit, int shift) {
    int c[3] = {w->cell.x, w->cell.y, w->cell.z};
    int st[3] = {w->step.x, w->step.y, w->step.z};
    int res[3] = {g->res.x, g->res.y, g->res.z};
    float tn[3] = {w->tnext.x, w->tnext.y, w->tnext.z};
    int far[3];
    float tf[3];
    for (int a = 0; a < 3; ++a) {
        int lo = (c[a] >> shift) << shift;
        far[a] = st[a] > 0 ? min(res[a] - 1, lo + (1 << shift) - 1) : lo;
        tf[a] = st[a] == 0 ? INFINITY : (far[a] == c[a] ? tn[a] : grid_next_plane(g, r, a, far[a], st[a]));
    }
    int ax = (tf[0] <= tf[1]) ? ((tf[0] <= tf[2]) ? 0 : 2) : ((tf[1] <= tf[2]) ? 1 : 2);
    float t = tf[ax];
    if (!(t < t_limit) || !(t <= w->t_exit)) return false;
    for (int b = 0; b < 3; ++b) {
        if (b == ax || st[b] == 0 || c[b] == far[b] || !(tn[b] < t || (tn[b] == t && b < ax))) continue;
        // the crossing out of c[b] comes first: the cell at distance t, then corrected
        int cur = c[b];
        float p = (rt_comp(r->o, b) - rt_comp(g->lo.xyz, b)) + t * rt_comp(r->d, b);
        int e = (int)clamp(floor(p * rt_comp(g->inv.xyz, b)), -1.0f, (float)res[b]);
        e = st[b] > 0 ? clamp(e, cur + 1, far[b]) : clamp(e, far[b], cur - 1);
        float te = grid_next_plane(g, r, b, e, st[b]);
        while (e != far[b] && (te < t || (te == t && b < ax))) {  // e's crossing comes first too: on
            e += st[b];
            te = grid_next_plane(g, r, b, e, st[b]);
        }
        while (e - st[b] != cur) {  // back while the crossing out of the previous cell does not come first
            float tp = grid_next_plane(g, r, b, e - st[b], st[b]);
            if (tp < t || (tp == t && b < ax)) break;
            e -= st[b];
            te = tp;
        }
        c[b] = e;
        tn[b] = te;
    }
    c[ax] = far[ax] + st[ax];
    if (c[ax] < 0 || c[ax] >= res[ax]) return false;
    tn[ax] = grid_next_plane(g, r, ax, c[ax], st[ax]);
    w->cell = (int3)(c[0], c[1], c[2]);
    w->tnext = (float3)(tn[0], tn[1], tn[2]);
    return true;
}

// vw_next_nonempty with empty blocks skipped whole (the coarse level first): the same non-empty
// cells, in the same order, with the same walk state. A block's occupancy is looked up once, when
// the walk enters it (a lookup on every step costs as much as the skipping saves).
inline bool vw_next_nonempty_skip(const Grid *g, __global const uint2 *cells, __global const uchar *occ_fine,
                                  __global const uchar *occ_coarse, const RayPre *r, GridWalk *w, float t_limit,
                                  uint2 *cr) {
    int3 seen = (int3)(-1);  // the fine block last found occupied
    while (true) {
        int3 fb = w->cell >> VW_SHIFT_FINE;
        if (any(fb != seen)) {
#if VW_SHIFT_COARSE
            if (vw_block_empty(g, occ_coarse, VW_SHIFT_COARSE, w->cell)) {
                if (!vw_skip_block(g, r, w, t_limit, VW_SHIFT_COARSE)) return false;
                continue;
            }
#endif
            if (vw_block_empty(g, occ_fine, VW_SHIFT_FINE, w->cell)) {
                if (!vw_skip_block(g, r, w, t_limit, VW_SHIFT_FINE)) return false;
                continue;
            }
            seen = fb;
        }
        uint2 c = cells[grid_cell_id(g, w->cell)];
        if (c.y) { *cr = c; return true; }
        if (!grid_walk_step(g, r, w, t_limit)) return false;
    }
}

// The walks' "next non-empty cell": with VW_SKIP, empty blocks skipped whole; without it, cell by
// cell (the same cells in the same order either way; skipping measured slower on the mixed-scale
// and dragon benches, docs/backends/voxelwalk.md).
#ifdef VW_SKIP
#define VW_NEXT(g, cells, occ_fine, occ_coarse, r, w, t_limit, cr) \
    vw_next_nonempty_skip(g, cells, occ_fine, occ_coarse, r, w, t_limit, cr)
#else
#define VW_NEXT(g, cells, occ_fine, occ_coarse, r, w, t_limit, cr) vw_next_nonempty(g, cells, r, w, t_limit, cr)
#endif

// Camera perspective grid (Patidar & Narayanan 2008; Guntury & Narayanan 2010): image tiles x
// depth slabs in the camera's projective space. viewer/accel/camgrid.py owns the layout.
//
// Header (CGRID_DTYPE, 224 bytes): eye (xyz), minv (rows of M^-1, where the un-normalised
// direction of the ray through pixel point (x, y) is M (x, y, 1)), screen (width, height, margin in
// pixels, 0), slab (log z_lo, slabs per unit of log z, z_lo, z_hi), tiles (pixels per tile side T,
// tiles in x, tiles in y, slabs S), cells (tiles * slabs, image width, image height, flags: bit 0
// back-face culling). Ray i is the ray of pixel (i % width, i / width), through pixel point
// (x + 0.5, y + 0.5). A point P maps to q = M^-1 (P - eye): pixel (q.x / q.z, q.y / q.z),
// depth q.z (proportional to the distance along the viewing axis). Slab s holds depths in
// [z_lo * r^s, z_lo * r^(s+1)) with r = (z_hi / z_lo)^(1 / S); slab 0 also holds everything
// nearer, the last everything farther. Cell id = (ty * tiles_x + tx) * S + s; cells: uint2
// (first ref, ref count); refs: uint triangle slots grouped by cell.
// Without cl_khr_fp64 nothing is binned and every ray is "outside" (traced another way).
#include "geometry.cl"

typedef struct {
#ifdef RT_HAVE_FP64
    double4 eye;
    double4 minv[3];
    double4 screen;
    double4 slab;
#else
    float4 pad[12];
#endif
    int4 tiles;
    int4 cells;
} CGrid;

#ifdef RT_HAVE_FP64
inline double3 cg_project(const CGrid *g, double3 v) {
    return (double3)(dot(g->minv[0].xyz, v), dot(g->minv[1].xyz, v), dot(g->minv[2].xyz, v));
}

// Continuous slab coordinate of depth z (may lie outside [0, S)).
inline double cg_slab_f(const CGrid *g, double z) {
    return z > 0.0 ? (log(z) - g->slab.x) * g->slab.y : -1.0e30;
}

// Slab index of depth z, pushed by `bias` slab units (+: round up, -: round down) before the floor,
// so that the float error of log() never moves a triangle out of a slab it reaches.
inline int cg_slab(const CGrid *g, double z, double bias) {
    double f = cg_slab_f(g, z) + bias;
    return (int)clamp(floor(f), 0.0, (double)(g->tiles.w - 1));
}
#endif

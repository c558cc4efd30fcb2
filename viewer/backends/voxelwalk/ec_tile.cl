// voxelwalk EC in one launch (Enforced Coherence, Guntury 2011 ch. 5, the iterations run on the
// device). Units (what one iteration of a ray tests, below) of at most INLINE_MAX triangles are
// not sorted: the walk tests them on its way, in walk order with the nearest hit as the bound, as
// IVW does (sorting a one-block unit costs more than its test; on bench-grids' mixed scene 96% of
// the reflection rays' units were ground cells of 2-3 triangles). ec_tile_first walks each ray,
// one work-item per ray in the rays' own order, to its first unit to sort; rays that finish on
// the way write their hit there. The others (compacted in screen-tile order) are sorted: one
// work-group per partition of at most P of them runs every EC iteration of its rays, with only
// work-group barriers:
//   walk     each active ray moves to its next non-empty cell (3D-DDA resumed from a cell id,
//            walk.cl; with TWO_LEVEL its next unit: a top cell, a sub-grid's big list or one of
//            its non-empty sub-cells, below) and inserts it into a local hash table (atomic
//            compare-and-swap on the key, atomic increment for its rank in the cell)
//   sort     a counting sort by cell: a scan over the table (only 2 entries per active ray) gives
//            each cell its offset and its chunks (at most WG rays of one cell); the rays are
//            scattered into cell order, which is also the compaction (resolved rays inserted
//            nothing)
//   process  cells holding at least STAGE_MIN of the partition's rays, chunk by chunk: the cell's
//            SoA triangle blocks (grid.py GRID_BLOCK_DTYPE) are staged in local memory WG at a
//            time and every ray of the chunk tests them (the float4 watertight test of
//            geometry.cl); cells with fewer rays: consecutive work-items take the cell-sorted rays
//            and read the blocks from global memory (staging a cell for one or two rays costs more
//            than it saves). Either way rays of the same cell are processed together.
//   resolve  a ray is done when its hit lies inside the cell (the hit-inside-cell rule) or its
//            walk leaves the grid; then it writes its hit. The others walk on (next iteration).
// The loop ends on the partition's own active count (local), so the host never looks between
// iterations and the launch count does not depend on the iteration count. Each ray tests its
// cells in walk order with its nearest hit as the bound, exactly as IVW does (ivw.cl), so EC and
// IVW return bit-identical hits. Per-group totals (ECT_TOTALS uints: iterations, units tested,
// chunks, rays walked, units and rays sorted; group 0 adds ec_tile_first's) go to `totals`: the
// host reads them once per pass.
#include "walk.cl"
// with TWO_LEVEL: grid2.cl's sub-walk and G2_PARAMS / G2_ARGS
#include "grid2_walk.cl"

#ifndef WG
#define WG 64
#endif
#ifndef P
#define P 1024  // rays per partition (work-group)
#endif
#define H (2 * P)  // hash table entries (power of two, load <= 1/2)
#define SB WG  // triangle blocks staged per round
#define ECT_TOTALS 6  // per work-group: iterations, units (pairs), chunks, rays walked, units sorted, rays sorted
#ifndef STAGE_MIN
#define STAGE_MIN 8  // a cell with fewer rays in the partition is not staged: its rays test from global memory
#endif
#ifndef TAIL
#define TAIL 0  // a partition with fewer active rays finishes them walking alone (0: never)
#endif
#ifndef INLINE_MAX
#define INLINE_MAX 0  // units of at most this many triangles are tested in the walk, not sorted (0: none)
#endif

// Table entries in use for m rays: a power of two >= 2m (at least WG), so the table's scan shrinks
// with the active rays (entries past it were cleared while they were in use).
inline uint ect_size(uint m) {
    uint s = WG;
    while (s < 2u * m) s <<= 1;
    return s;
}

// Inserts cell c into a table of `size` entries; returns its entry, *rank = the ray's position
// among the cell's rays.
inline uint ect_insert(__local volatile uint *hkey, __local volatile uint *hcnt, uint c, uint size, uint *rank) {
    uint h = (c * 2654435761u) & (size - 1u);
    while (true) {
        uint old = atomic_cmpxchg(&hkey[h], VW_NONE, c);
        if (old == VW_NONE || old == c) break;
        h = (h + 1u) & (size - 1u);
    }
    *rank = atomic_inc(&hcnt[h]);
    return h;
}

// Units: what one EC iteration of a ray tests, the sort key. A top cell without a sub-grid is
// unit c (< ncells: its own list). With TWO_LEVEL a top cell with sub-grid s is walked as IVW's
// test_cell walks it (grid2_walk.cl): its big list first (unit ncells + nsubc + s, when it has
// one), then its non-empty sub-cells in sub-walk order (unit ncells + global sub-cell id), so rays
// reaching a dense object are sorted by its sub-cells, not by the one top cell holding all of it.
// The ray's top cell is kept beside its unit (top[j]).
#ifdef TWO_LEVEL
#define ECT_G2 G2_PARAMS, const uint nsubc
#define ECT_G2_ARGS G2_ARGS, nsubc
#else
#define ECT_G2
#define ECT_G2_ARGS
#endif

// The unit's triangle blocks (10 float4 per block of 4) and its triangle count.
inline __global const float4 *ect_unit(uint u, uint ncells, __global const uint2 *cells,
                                       __global const float4 *blocks, __global const uint *cell_blocks
                                       ECT_G2, uint *cnt) {
#ifdef TWO_LEVEL
    if (u >= ncells) {
        uint v = u - ncells;
        if (v < nsubc) {
            *cnt = scells[v].y;
            return sblocks + 10u * scb[v];
        }
        uint4 big = subs[v - nsubc].big;
        *cnt = big.y;
        return bblocks + 10u * big.x;
    }
#endif
    *cnt = cells[u].y;
    return blocks + 10u * cell_blocks[u];
}

// Tests nt triangles from the SoA blocks at blk (global memory) against r, keeping the nearest
// hit: the small units' tests in the walk, in IVW's order with IVW's bound.
__attribute__((always_inline)) inline void ect_test(const RayPre *r, __global const float4 *blk, uint nt, float tmin, float *hit_t,
                     uint *hit_slot) {
    for (uint q = 0; q < nt; q += 4, blk += 10) {
        int4 slots = as_int4(blk[9]);
        float t;
        int lane = rt_intersect_triangle4(r, blk, slots >= (int4)(0), tmin, *hit_t, &t);
        if (lane >= 0) {
            *hit_t = t;
            *hit_slot = (uint)(lane == 0 ? slots.x : (lane == 1 ? slots.y : (lane == 2 ? slots.z : slots.w)));
        }
    }
}

#ifdef TWO_LEVEL
// Sub-walk state of ray r in sub-cell `sid` (global id) of sub-grid s, as g2_walk_begin and its
// steps left it there: every plane distance is a function of the sub-cell index (g2_next_plane),
// and the exit t1 = min(tmax, box exit) acts only through t < hit_t <= tmax, so the current hit
// distance as tmax gives the same steps and the same hit-inside checks.
inline void ect_sub_at(const SubGrid *s, const RayPre *r, uint sid, float tmax, SubWalk *w) {
    g2real3 cell = convert_g2real3(s->cell.xyz);
    g2real3 hi = cell * convert_g2real3(s->res.xyz);
    w->o = convert_g2real3(r->o) - convert_g2real3(s->lo.xyz);
    w->d = convert_g2real3(r->d);
    g2real t0 = -G2_INF, t1 = (g2real)tmax;
    g2_slab(w->o.x, w->d.x, hi.x, &t0, &t1);
    g2_slab(w->o.y, w->d.y, hi.y, &t0, &t1);
    g2_slab(w->o.z, w->d.z, hi.z, &t0, &t1);
    w->t_exit = t1;
    int loc = (int)sid - s->res.w;
    w->cell = (int3)(loc % s->res.x, (loc / s->res.x) % s->res.y, loc / (s->res.x * s->res.y));
    w->step = (int3)(w->d.x > 0 ? 1 : (w->d.x < 0 ? -1 : 0), w->d.y > 0 ? 1 : (w->d.y < 0 ? -1 : 0),
                     w->d.z > 0 ? 1 : (w->d.z < 0 ? -1 : 0));
    w->tnext = (g2real3)(g2_next_plane(w->o.x, w->d.x, cell.x, w->cell.x, w->step.x),
                         g2_next_plane(w->o.y, w->d.y, cell.y, w->cell.y, w->step.y),
                         g2_next_plane(w->o.z, w->d.z, cell.z, w->cell.z, w->step.z));
}

// The next sub-cell to sort from w's (the current one included when `here`), as a unit; VW_NONE
// when the sub-walk ends first. Sub-cells of at most INLINE_MAX triangles are tested on the way
// (ect_test), and the walk stops after one that holds the hit, as IVW's sub-walk does; IVW's
// sub-walk also stops at an empty sub-cell holding the hit, but there its next step fails too
// (t >= hit_t or t > t_exit): the same tests.
inline uint ect_sub_next(const SubGrid *s, SubWalk *w, bool here, const RayPre *r, float tmin, float *hit_t,
                         uint *hit_slot, __global const uint2 *scells, __global const float4 *sblocks,
                         __global const uint *scb, uint ncells, uint lim, uint *nu) {
    if (!here && !g2_walk_step(s, w, *hit_t)) return VW_NONE;
    while (true) {
        int sid = g2_cell_id(s, w->cell);
        uint cnt = scells[sid].y;
        if (cnt > lim) return ncells + (uint)sid;
        if (cnt > 0u) {
            ect_test(r, sblocks + 10u * scb[sid], cnt, tmin, hit_t, hit_slot);
            ++*nu;
            if (*hit_slot != VW_NONE && (g2real)*hit_t <= g2_cell_exit(w)) return VW_NONE;
        }
        if (!g2_walk_step(s, w, *hit_t)) return VW_NONE;
    }
}
#endif

// The first unit to sort of the walk w from its current top cell on (w is moved to that unit's top
// cell, *topc); VW_NONE when the walk ends first: it leaves the grid or passes the hit, or a top
// cell whose remaining units were all tested on the way holds the hit (IVW's hit-inside-cell rule,
// checked there too). Units of at most INLINE_MAX triangles (a top cell's list, a big list, a
// sub-cell) are tested on the way, in walk order with the nearest hit as the bound (*hit_t,
// *hit_slot), as IVW tests them: sorting a unit of one block of triangles costs more than testing
// it. *nv counts the non-empty top cells entered (IVW's iterations; *first: the first of them).
__attribute__((always_inline)) inline uint ect_find_ai(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                     __global const uint *cell_blocks, __global const uchar *occ_fine,
                     __global const uchar *occ_coarse ECT_G2, const RayPre *r, GridWalk *w, float tmin,
                     float *hit_t, uint *hit_slot, uint ncells, uint *topc, uint *nv, uint *first, uint lim,
                     uint *nu) {
    uint2 cr;
    while (VW_NEXT(g, cells, occ_fine, occ_coarse, r, w, *hit_t, &cr)) {
        int c = grid_cell_id(g, w->cell);
        *topc = (uint)c;
        if ((*nv)++ == 0u) *first = (uint)c;
#ifdef TWO_LEVEL
        int si = sub_of[c];
        if (si >= 0) {
            SubGrid sg = subs[si];
            if (sg.big.y > 0u) {
                if (sg.big.y > lim) return ncells + nsubc + (uint)si;
                ect_test(r, bblocks + 10u * sg.big.x, sg.big.y, tmin, hit_t, hit_slot);
                ++*nu;
            }
            SubWalk sw;
            if (g2_walk_begin(&sg, r, tmin, *hit_t, &sw)) {
                uint u = ect_sub_next(&sg, &sw, true, r, tmin, hit_t, hit_slot, scells, sblocks, scb, ncells, lim, nu);
                if (u != VW_NONE) return u;
            }
        } else
#endif
        {
            if (cr.y > lim) return (uint)c;
            ect_test(r, blocks + 10u * cell_blocks[c], cr.y, tmin, hit_t, hit_slot);
            ++*nu;
        }
        if (*hit_slot != VW_NONE && *hit_t <= grid_cell_exit(w)) return VW_NONE;
        if (!grid_walk_step(g, r, w, *hit_t)) return VW_NONE;
    }
    return VW_NONE;
}

// ect_find_ai out of line, for the sort loop's resolve (ec_tile): inlined there at each call it
// measured slower (the loop's code grows); ec_tile_first inlines it.
__attribute__((noinline)) uint ect_find(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                                        __global const uint *cell_blocks, __global const uchar *occ_fine,
                                        __global const uchar *occ_coarse ECT_G2, const RayPre *r, GridWalk *w,
                                        float tmin, float *hit_t, uint *hit_slot, uint ncells, uint *topc, uint *nv,
                                        uint *first, uint lim, uint *nu) {
    return ect_find_ai(g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, r, w, tmin, hit_t, hit_slot,
                       ncells, topc, nv, first, lim, nu);
}

// The ray's next unit to sort after the tests of unit u in top cell c (VW_NONE: it is done), as
// IVW's walk goes on: within c's sub-walk (after the big list: its first non-empty sub-cell; after
// a sub-cell: stop there when it holds the hit, else the next non-empty one), then past c (done
// when c holds the hit), then the next top cell's first unit; units of at most INLINE_MAX
// triangles on the way are tested there (ect_find).
inline uint ect_next(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                     __global const uint *cell_blocks, __global const uchar *occ_fine,
                     __global const uchar *occ_coarse ECT_G2, const RayPre *r, uint u, uint *c, float tmin,
                     float *hit_t, uint *hit_slot, uint ncells, uint *nv, uint lim, uint *nu) {
#ifdef TWO_LEVEL
    if (u >= ncells) {
        SubGrid sg = subs[sub_of[*c]];
        SubWalk sw;
        uint v = VW_NONE;
        if (u - ncells >= nsubc) {  // the big list: the sub-walk begins
            if (g2_walk_begin(&sg, r, tmin, *hit_t, &sw))
                v = ect_sub_next(&sg, &sw, true, r, tmin, hit_t, hit_slot, scells, sblocks, scb, ncells, lim, nu);
        } else {
            ect_sub_at(&sg, r, u - ncells, *hit_t, &sw);
            if (!(*hit_slot != VW_NONE && (g2real)*hit_t <= g2_cell_exit(&sw)))
                v = ect_sub_next(&sg, &sw, false, r, tmin, hit_t, hit_slot, scells, sblocks, scb, ncells, lim, nu);
        }
        if (v != VW_NONE) return v;
    }
#endif
    GridWalk w;
    vw_walk_at(g, r, *c, *hit_t, &w);
    if (*hit_slot != VW_NONE && *hit_t <= grid_cell_exit(&w)) return VW_NONE;
    if (!grid_walk_step(g, r, &w, *hit_t)) return VW_NONE;
    uint first;
    return ect_find(g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, r, &w, tmin, hit_t, hit_slot,
                    ncells, c, nv, &first, lim, nu);
}

// Resolve of ray j (list position k) after the tests of its unit: done when its walk ends (the hit
// lies inside its cell, or it leaves the grid), then it writes its result; else it moves to its
// next unit to sort (testing the small units on the way) and inserts it into the table (size
// entries) for the next iteration.
inline void ect_resolve(const Grid *g, __global const uint2 *cells, __global const float4 *blocks,
                        __global const uint *cell_blocks, __global const uchar *occ_fine,
                        __global const uchar *occ_coarse ECT_G2, const RayPre *r, float tmin, uint ncells, uint i,
                        uint j, uint k, float hit_t, uint hit_slot, uint size, __local uint *cur,
                        __local uint *top, __local uint *nit, __local float *hit, __local uint *slot,
                        __local uint *bucket, __local uint *rank, __local volatile uint *hkey,
                        __local volatile uint *hcnt, __global float *out_t, __global int *out_id,
                        __global int *iters_out, uint lim, uint *nu) {
    uint c = top[j], nv = nit[j];
    uint u = ect_next(g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, r, cur[j], &c, tmin, &hit_t,
                      &hit_slot, ncells, &nv, lim, nu);
    bool got = hit_slot != VW_NONE;
    if (u == VW_NONE) {
        out_t[i] = got ? hit_t : INFINITY;
        out_id[i] = got ? (int)hit_slot : -1;
        iters_out[i] = (int)nv;
        bucket[k] = VW_NONE;
    } else {
        cur[j] = u;
        top[j] = c;
        nit[j] = nv;
        hit[j] = hit_t;
        slot[j] = hit_slot;
        uint rk;
        bucket[k] = ect_insert(hkey, hcnt, u, size, &rk);
        rank[k] = rk;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void ec_tile(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,
             __global const uint *cell_blocks ECT_G2, __global const float4 *ray_o, __global const float4 *ray_d,
             __global const uint *act, __global const uint *m_ptr, __global const uint *unit_in,
             __global const uint *top_in, __global float *out_t, __global int *out_id, __global int *iters_out,
             __global uint *totals, __global volatile uint *first_acc, __global const uchar *occ_fine,
             __global const uchar *occ_coarse) {
    __local uint ray[P], cur[P], top[P], slot[P], nit[P];
    __local float hit[P];
    __local uint lst_a[P], lst_b[P], bucket[P], rank[P];
    __local volatile uint hkey[H], hcnt[H];
    __local uint hoff[H];
    __local uint ch_cell[P], ch_start[P], ch_len[P];
    __local uint part_n[WG], part_c[WG], part_b[WG];
    __local uint sh[4];  // active rays, chunks, previous list length, rays in staged cells
    __local volatile uint small_cells;  // cells processed from global memory, over the iterations
    __local volatile uint inl_units;  // units tested in the walk (resolve), over the iterations
    __local float4 sv[10 * SB];

    const uint lid = get_local_id(0), grp = get_group_id(0);
    const uint m_all = *m_ptr;
    const uint base = grp * (uint)P;
    const uint m0 = base < m_all ? min((uint)P, m_all - base) : 0u;
    Grid g = *grid;
    const uint ncells = (uint)(g.res.x * g.res.y * g.res.z);
    uint t_iters = 0, t_pairs = 0, t_chunks = 0, t_inl = 0;

    for (uint h = lid; h < H; h += WG) { hkey[h] = VW_NONE; hcnt[h] = 0u; }
    if (lid == 0) {
        small_cells = 0u;
        inl_units = 0u;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    // every ray of the partition has a unit to sort (ec_tile_first walked it there): its state in
    for (uint j = lid; j < m0; j += WG) {
        uint i = act[base + j];
        uint c = unit_in[i];
        ray[j] = i;
        hit[j] = out_t[i];
        slot[j] = (uint)out_id[i];  // -1: VW_NONE
        cur[j] = c;
        top[j] = top_in[i];
        nit[j] = (uint)iters_out[i];
        lst_a[j] = j;
        uint rk;
        bucket[j] = ect_insert(hkey, hcnt, c, ect_size(m0), &rk);
        rank[j] = rk;
    }
    if (lid == 0) sh[2] = m0;
    __local uint *lst = lst_a, *srt = lst_b;
    while (true) {
        barrier(CLK_LOCAL_MEM_FENCE);
        // sort, 1: per work-item totals over its range of the table (rays in staged cells, in
        // other cells, staged chunks)
        const uint per_wi = ect_size(sh[2]) / WG, hb = lid * per_wi;
        uint sb = 0, sn = 0, sc = 0;
        for (uint h = hb; h < hb + per_wi; ++h) {
            uint k = hcnt[h];
            bool big = k >= STAGE_MIN;
            sb += big ? k : 0u;
            sn += big ? 0u : k;
            sc += big ? (k + WG - 1) / WG : 0u;
        }
        part_b[lid] = sb;
        part_n[lid] = sn;
        part_c[lid] = sc;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {
            uint rb = 0, rn = 0, rc = 0;
            for (uint k = 0; k < WG; ++k) {
                uint a = part_b[k], b = part_n[k], c = part_c[k];
                part_b[k] = rb;
                part_n[k] = rn;
                part_c[k] = rc;
                rb += a;
                rn += b;
                rc += c;
            }
            sh[0] = rb + rn;
            sh[1] = rc;
            sh[3] = rb;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const uint m = sh[0], nch = sh[1], m_prev = sh[2], mb = sh[3];
        if (m == 0) break;
        t_iters += 1;
        t_pairs += m;
        // sort, 2: each cell's offset (staged cells first, then the others) and the staged cells'
        // chunks; the table is cleared for the next iteration
        uint ob = part_b[lid], on = mb + part_n[lid], oc = part_c[lid], ns = 0;
        for (uint h = hb; h < hb + per_wi; ++h) {
            uint k = hcnt[h];
            if (k >= STAGE_MIN) {
                uint c = hkey[h];
                hoff[h] = ob;
                for (uint s = 0; s < k; s += WG) {
                    ch_cell[oc] = c;
                    ch_start[oc] = ob + s;
                    ch_len[oc] = min((uint)WG, k - s);
                    ++oc;
                }
                ob += k;
            } else if (k) {
                hoff[h] = on;
                on += k;
                ++ns;
            }
            hkey[h] = VW_NONE;
            hcnt[h] = 0u;
        }
        if (ns) atomic_add(&small_cells, ns);
        barrier(CLK_LOCAL_MEM_FENCE);
        // sort, 3: scatter into cell order (rays that found no cell are left out: the compaction)
        for (uint j = lid; j < m_prev; j += WG) {
            uint b = bucket[j];
            if (b != VW_NONE) srt[hoff[b] + rank[j]] = lst[j];
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        // process and resolve, cells with few rays: in cell order, each ray its cell's blocks from
        // global memory (consecutive work-items share a cell; staging would cost more than the
        // tests it feeds)
        const uint hsize = ect_size(m);
        // a partition down to fewer than TAIL active rays finishes them walking alone (every unit
        // tested in the walk): a handful of rays sorted by unit gathers no coherence to pay for
        // an iteration
        const uint lim = m < (uint)TAIL ? 0xffffffffu : (uint)INLINE_MAX;
        for (uint k = mb + lid; k < m; k += WG) {
            uint j = srt[k], i = ray[j];
            float4 ot = ray_o[i], dt = ray_d[i];
            RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
            float hit_t = hit[j];
            uint hit_slot = slot[j], nt;
            __global const float4 *blk = ect_unit(cur[j], ncells, cells, blocks, cell_blocks ECT_G2_ARGS, &nt);
            ect_test(&r, blk, nt, ot.w, &hit_t, &hit_slot);
            ect_resolve(&g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, &r, ot.w, ncells, i, j, k,
                        hit_t, hit_slot, hsize, cur, top, nit, hit, slot, bucket, rank, hkey, hcnt, out_t, out_id,
                        iters_out, lim, &t_inl);
        }
        // process, cells with many rays: one chunk (at most WG rays of one cell) at a time, the
        // cell's blocks staged in local memory (the thesis's chunk)
        t_chunks += nch;
        for (uint c = 0; c < nch; ++c) {
            uint start = ch_start[c], len = ch_len[c], nt;
            __global const float4 *ub = ect_unit(ch_cell[c], ncells, cells, blocks, cell_blocks ECT_G2_ARGS, &nt);
            uint nb = (nt + 3u) / 4u;
            bool mine = lid < len;
            uint j = mine ? srt[start + lid] : 0u;
            uint i = ray[j];
            float4 ot = mine ? ray_o[i] : (float4)(0.0f);
            float4 dt = mine ? ray_d[i] : (float4)(0.0f, 0.0f, 1.0f, -1.0f);
            RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
            float hit_t = mine ? hit[j] : -1.0f;
            uint hit_slot = mine ? slot[j] : VW_NONE;
            for (uint s = 0; s < nb; s += SB) {
                uint cnt = min((uint)SB, nb - s);
                barrier(CLK_LOCAL_MEM_FENCE);
                for (uint e = lid; e < 10u * cnt; e += WG) sv[e] = ub[10u * s + e];
                barrier(CLK_LOCAL_MEM_FENCE);
                if (mine) {
                    for (uint k = 0; k < cnt; ++k) {
                        __local const float4 *blk = sv + 10u * k;
                        int4 slots = as_int4(blk[9]);
                        float t;
                        int lane = rt_intersect_triangle4_local(&r, blk, slots >= (int4)(0), ot.w, hit_t, &t);
                        if (lane >= 0) {
                            hit_t = t;
                            hit_slot = (uint)(lane == 0 ? slots.x : (lane == 1 ? slots.y :
                                                                      (lane == 2 ? slots.z : slots.w)));
                        }
                    }
                }
            }
            if (mine) {
                hit[j] = hit_t;
                slot[j] = hit_slot;
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        // resolve the staged chunks' rays
        for (uint k = lid; k < mb; k += WG) {
            uint j = srt[k], i = ray[j];
            float4 ot = ray_o[i], dt = ray_d[i];
            RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
            ect_resolve(&g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, &r, ot.w, ncells, i, j, k,
                        hit[j], slot[j], hsize, cur, top, nit, hit, slot, bucket, rank, hkey, hcnt, out_t, out_id,
                        iters_out, lim, &t_inl);
        }
        if (lid == 0) sh[2] = m;
        __local uint *tmp = lst;
        lst = srt;
        srt = tmp;
    }
    if (t_inl) atomic_add(&inl_units, t_inl);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) {
        uint walked = 0u, first_units = 0u;
        if (grp == 0u) {  // ec_tile_first's totals (it ran before this launch), cleared for the next pass
            walked = first_acc[0];
            first_units = first_acc[1];
            first_acc[0] = 0u;
            first_acc[1] = 0u;
        }
        totals[ECT_TOTALS * grp] = t_iters;
        totals[ECT_TOTALS * grp + 1] = t_pairs + inl_units + first_units;
        totals[ECT_TOTALS * grp + 2] = t_chunks + small_cells;
        totals[ECT_TOTALS * grp + 3] = walked;
        totals[ECT_TOTALS * grp + 4] = t_pairs;
        totals[ECT_TOTALS * grp + 5] = m0;
    }
}

// ec_tile_first's ray i (position j of the screen-tile order).
inline void ect_first(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,
                      __global const uint *cell_blocks ECT_G2, __global const float4 *ray_o,
                      __global const float4 *ray_d, uint i, uint j, __global uint *flags, __global uint *unit_out,
                      __global uint *top_out, __global float *out_t, __global int *out_id, __global int *iters_out,
                      __global uint *first_out, __global const uchar *occ_fine, __global const uchar *occ_coarse,
                      __local volatile uint *acc) {
    Grid g = *grid;
    const uint ncells = (uint)(g.res.x * g.res.y * g.res.z);
    float4 ot = ray_o[i], dt = ray_d[i];
    uint c = VW_NONE, tc = VW_NONE, nv = 0u, first = VW_NONE, hs = VW_NONE, nu = 0u;
    float ht = dt.w;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        GridWalk w;
        float t_enter;
        if (grid_walk_begin(&g, &r, ot.w, dt.w, &w, &t_enter)) {
            c = ect_find_ai(&g, cells, blocks, cell_blocks, occ_fine, occ_coarse ECT_G2_ARGS, &r, &w, ot.w, &ht, &hs,
                            ncells, &tc, &nv, &first, INLINE_MAX, &nu);
            atomic_inc(&acc[0]);
            if (nu) atomic_add(&acc[1], nu);
        }
    }
    flags[j] = c != VW_NONE ? 1u : 0u;
    unit_out[i] = c;
    top_out[i] = tc;
    out_t[i] = c != VW_NONE || hs != VW_NONE ? ht : INFINITY;
    out_id[i] = (int)hs;  // VW_NONE: -1
    iters_out[i] = (int)nv;
    first_out[i] = first;
}

// Each ray's walk up to its first unit to sort (one work-item per ray i, in the rays' own order, as
// IVW walks them), testing the small units on the way (ect_find): flags[pos[i]] = 1 (its position
// in the screen-tile order, for the compaction) when it reaches one (its state for ec_tile: unit_out, top_out, the nearest hit so far in out_t/out_id,
// the top cells entered in iters_out); the others (no grid box, an empty walk, or one that ended
// on units tested on the way) write their result now and take no part in the sort.
__kernel void ec_tile_first(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,
                            __global const uint *cell_blocks ECT_G2, __global const float4 *ray_o,
                            __global const float4 *ray_d, __global const uint *pos, const uint n,
                            __global uint *flags, __global uint *unit_out, __global uint *top_out,
                            __global float *out_t, __global int *out_id, __global int *iters_out,
                            __global uint *first_out, __global volatile uint *first_acc,
                            __global const uchar *occ_fine, __global const uchar *occ_coarse) {
    __local volatile uint acc[2];  // the work-group's rays walked and units tested
    const uint i = get_global_id(0), lid = get_local_id(0);
    if (lid == 0) {
        acc[0] = 0u;
        acc[1] = 0u;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (i < n) ect_first(grid, cells, blocks, cell_blocks ECT_G2_ARGS, ray_o, ray_d, i, pos[i], flags, unit_out,
                         top_out, out_t, out_id, iters_out, first_out, occ_fine, occ_coarse, acc);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0 && (acc[0] | acc[1])) {
        atomic_add(&first_acc[0], acc[0]);
        atomic_add(&first_acc[1], acc[1]);
    }
}

// voxelwalk EC in one launch (Enforced Coherence, Guntury 2011 ch. 5, the iterations run on the
// device): one work-group per partition of at most P active rays (screen-tile order, compacted)
// runs every EC iteration of its rays, with only work-group barriers:
//   walk     each active ray moves to its next non-empty cell (3D-DDA resumed from a cell id,
//            walk.cl) and inserts that cell into a local hash table (atomic compare-and-swap on
//            the key, atomic increment for its rank in the cell)
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
// IVW return bit-identical hits. Per-group totals (iterations, ray-cell pairs, chunks, rays) go to
// `totals` (4 uints per group): the host reads them once per pass.
#include "walk.cl"

#ifndef WG
#define WG 64
#endif
#ifndef P
#define P 1024  // rays per partition (work-group)
#endif
#define H (2 * P)  // hash table entries (power of two, load <= 1/2)
#define SB WG  // triangle blocks staged per round
#ifndef STAGE_MIN
#define STAGE_MIN 8  // a cell with fewer rays in the partition is not staged: its rays test from global memory
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

// Resolve of ray j (list position k) after the tests of its cell: done when its hit lies inside
// the cell (the hit-inside-cell rule) or its walk ends, then it writes its result; else it walks
// on to its next non-empty cell and inserts it into the table (size entries) for the next iteration.
inline void ect_resolve(const Grid *g, __global const uint2 *cells, __global const uchar *occ_fine,
                        __global const uchar *occ_coarse, const RayPre *r, uint i, uint j, uint k, float hit_t,
                        uint hit_slot, uint size, __local uint *cur, __local uint *nit,
                        __local uint *bucket, __local uint *rank, __local volatile uint *hkey,
                        __local volatile uint *hcnt, __global float *out_t, __global int *out_id,
                        __global int *iters_out) {
    bool got = hit_slot != VW_NONE;
    GridWalk w;
    vw_walk_at(g, r, cur[j], hit_t, &w);
    uint c = VW_NONE;
    uint2 cr;
    if (!(got && hit_t <= grid_cell_exit(&w)) && grid_walk_step(g, r, &w, hit_t) &&
        vw_next_nonempty_skip(g, cells, occ_fine, occ_coarse, r, &w, hit_t, &cr))
        c = (uint)grid_cell_id(g, w.cell);
    if (c == VW_NONE) {
        out_t[i] = got ? hit_t : INFINITY;
        out_id[i] = got ? (int)hit_slot : -1;
        iters_out[i] = (int)nit[j];
        bucket[k] = VW_NONE;
    } else {
        cur[j] = c;
        nit[j] += 1u;
        uint rk;
        bucket[k] = ect_insert(hkey, hcnt, c, size, &rk);
        rank[k] = rk;
    }
}

__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void ec_tile(__global const Grid *grid, __global const uint2 *cells, __global const float4 *blocks,
             __global const uint *cell_blocks, __global const float4 *ray_o, __global const float4 *ray_d,
             __global const uint *act, __global const uint *m_ptr, __global float *out_t, __global int *out_id,
             __global int *iters_out, __global uint *first_out, __global uint *totals,
             __global const uchar *occ_fine, __global const uchar *occ_coarse) {
    __local uint ray[P], cur[P], slot[P], nit[P];
    __local float hit[P];
    __local uint lst_a[P], lst_b[P], bucket[P], rank[P];
    __local volatile uint hkey[H], hcnt[H];
    __local uint hoff[H];
    __local uint ch_cell[P], ch_start[P], ch_len[P];
    __local uint part_n[WG], part_c[WG], part_b[WG];
    __local uint sh[4];  // active rays, chunks, previous list length, rays in staged cells
    __local volatile uint small_cells;  // cells processed from global memory, over the iterations
    __local float4 sv[10 * SB];

    const uint lid = get_local_id(0), grp = get_group_id(0);
    const uint m_all = *m_ptr;
    const uint base = grp * (uint)P;
    const uint m0 = base < m_all ? min((uint)P, m_all - base) : 0u;
    Grid g = *grid;
    uint t_iters = 0, t_pairs = 0, t_chunks = 0;

    for (uint h = lid; h < H; h += WG) { hkey[h] = VW_NONE; hcnt[h] = 0u; }
    if (lid == 0) small_cells = 0u;
    barrier(CLK_LOCAL_MEM_FENCE);
    // first cells: every ray of the partition enters the grid (ec_tile_flags kept only those)
    for (uint j = lid; j < m0; j += WG) {
        uint i = act[base + j];
        float4 ot = ray_o[i], dt = ray_d[i];
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        GridWalk w;
        float t_enter;
        uint c = VW_NONE;
        uint2 cr;
        if (grid_walk_begin(&g, &r, ot.w, dt.w, &w, &t_enter) &&
            vw_next_nonempty_skip(&g, cells, occ_fine, occ_coarse, &r, &w, dt.w, &cr))
            c = (uint)grid_cell_id(&g, w.cell);
        ray[j] = i;
        hit[j] = dt.w;
        slot[j] = VW_NONE;
        cur[j] = c;
        nit[j] = c == VW_NONE ? 0u : 1u;
        first_out[i] = c;
        lst_a[j] = j;
        uint rk = 0u;
        bucket[j] = c == VW_NONE ? VW_NONE : ect_insert(hkey, hcnt, c, ect_size(m0), &rk);
        rank[j] = rk;
        if (c == VW_NONE) {
            out_t[i] = INFINITY;
            out_id[i] = -1;
            iters_out[i] = 0;
        }
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
        for (uint k = mb + lid; k < m; k += WG) {
            uint j = srt[k], i = ray[j];
            float4 ot = ray_o[i], dt = ray_d[i];
            RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
            float hit_t = hit[j];
            uint hit_slot = slot[j], cid = cur[j];
            uint nt = cells[cid].y;
            __global const float4 *blk = blocks + 10u * cell_blocks[cid];
            for (uint q = 0; q < nt; q += 4, blk += 10) {
                int4 slots = as_int4(blk[9]);
                float t;
                int lane = rt_intersect_triangle4(&r, blk, slots >= (int4)(0), ot.w, hit_t, &t);
                if (lane >= 0) {
                    hit_t = t;
                    hit_slot = (uint)(lane == 0 ? slots.x : (lane == 1 ? slots.y : (lane == 2 ? slots.z : slots.w)));
                }
            }
            hit[j] = hit_t;
            slot[j] = hit_slot;
            ect_resolve(&g, cells, occ_fine, occ_coarse, &r, i, j, k, hit_t, hit_slot, hsize, cur, nit, bucket,
                        rank, hkey, hcnt, out_t, out_id, iters_out);
        }
        // process, cells with many rays: one chunk (at most WG rays of one cell) at a time, the
        // cell's blocks staged in local memory (the thesis's chunk)
        t_chunks += nch;
        for (uint c = 0; c < nch; ++c) {
            uint cid = ch_cell[c], start = ch_start[c], len = ch_len[c];
            uint nb = (cells[cid].y + 3u) / 4u, b0 = cell_blocks[cid];
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
                for (uint e = lid; e < 10u * cnt; e += WG) sv[e] = blocks[10u * (b0 + s) + e];
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
            ect_resolve(&g, cells, occ_fine, occ_coarse, &r, i, j, k, hit[j], slot[j], hsize, cur, nit, bucket,
                        rank, hkey, hcnt, out_t, out_id, iters_out);
        }
        if (lid == 0) sh[2] = m;
        __local uint *tmp = lst;
        lst = srt;
        srt = tmp;
    }
    if (lid == 0) {
        totals[4 * grp] = t_iters;
        totals[4 * grp + 1] = t_pairs;
        totals[4 * grp + 2] = t_chunks + small_cells;
        totals[4 * grp + 3] = m0;
    }
}

// Active rays in screen-tile order: flags[j] for ray perm[j] (enters the grid box); every ray's
// outputs start as a miss (inactive rays keep it).
__kernel void ec_tile_flags(__global const Grid *grid, __global const float4 *ray_o, __global const float4 *ray_d,
                            __global const uint *perm, const uint n, __global uint *flags, __global float *out_t,
                            __global int *out_id, __global int *iters_out, __global uint *first_out) {
    uint j = get_global_id(0);
    if (j >= n) return;
    Grid g = *grid;
    uint i = perm[j];
    float4 ot = ray_o[i], dt = ray_d[i];
    uint keep = 0u;
    if (dt.w > ot.w) {
        RayPre r = rt_prepare_ray(ot.xyz, dt.xyz);
        float enter;
        keep = rt_intersect_box(&r, g.lo.xyz, g.hi.xyz, ot.w, dt.w, &enter) ? 1u : 0u;
    }
    flags[j] = keep;
    out_t[i] = INFINITY;
    out_id[i] = -1;
    iters_out[i] = 0;
    first_out[i] = VW_NONE;
}

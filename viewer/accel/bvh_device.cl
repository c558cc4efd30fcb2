// Device BVH build: Morton order + PLOC clustering + SAH leaf collapse (viewer/accel/bvh_device.py).
// Defines: WG (work-items per group of the per-element kernels), RADIUS (PLOC search radius),
// MAX_LEAF, MIN_LEAF (leaf sizes as in viewer/accel/bvh.py), PREFETCH (CPU devices only: how far
// ahead merge_scatter and level_place ask for the random records they will read, with clang's
// __builtin_prefetch; out-of-order cores then overlap those cache misses).
//
// Nodes 0..n-1 are the triangles in Morton order (node i = triangle perm[i]); merged (inner) nodes
// get ids n, n+1, ... from a node counter (per iteration, in cluster order), so a child's id is
// always below its parent's, and are stored at id - n (no per-triangle node records: a triangle's
// box is recomputed). Clusters are boxes carrying their node id (in the min's spare lane), in
// Morton order; an iteration is nearest (+ counts) -> scan -> merge+scatter, all reading the
// cluster count from the device (cnt[p]) so the host need not read it.

#define RING (RADIUS < 8 ? 8 : RADIUS < 16 ? 16 : RADIUS < 32 ? 32 : 64)

// Inner node records (node id v >= n at v - n), NODE_F4 float4 each: bits of (triangles, kept
// nodes of the subtree, height << 1 | leaf flag, SAH cost of the best subtree) -- what a merge reads
// of a child, in one 16-byte piece (one cache line) --, (box min, bits of left), (box max, bits of
// right). One record per node: the layout kernels read a node's fields together.
#define NODE_F4 3

inline float half_area(float4 lo, float4 hi) {
    float4 e = hi - lo;
    return e.x * e.y + e.y * e.z + e.z * e.x;
}

inline uint expand10(uint v) {
    v &= 0x3ffu;
    v = (v * 0x00010001u) & 0xFF0000FFu;
    v = (v * 0x00000101u) & 0x0F00F00Fu;
    v = (v * 0x00000011u) & 0xC30C30C3u;
    v = (v * 0x00000005u) & 0x49249249u;
    return v;
}

inline void block_range(uint b, uint nb, uint n, uint* s, uint* e) {
    *s = (uint)(((ulong)b * n) / nb);
    *e = (uint)(((ulong)(b + 1) * n) / nb);
}

inline void tri_box(__global const float* tri, uint t, float4* lo, float4* hi) {
    __global const float* v = tri + 9 * (size_t)t;
    float4 a = (float4)(v[0], v[1], v[2], 0.0f), b = (float4)(v[3], v[4], v[5], 0.0f),
           c = (float4)(v[6], v[7], v[8], 0.0f);
    *lo = fmin(fmin(a, b), c);
    *hi = fmax(fmax(a, b), c);
}

// Per block of triangles: the bounds of their box centres (part[2 b] min, part[2 b + 1] max; the
// host takes the blocks' min / max, exact) and whether a vertex coordinate is not finite (part[2 b].w
// 1, else 0: the build's input check, here in parallel instead of a pass over the array on the
// host). No centre arrays: `morton` recomputes the centres.
__kernel void centre_bounds(__global const float* tri, uint n, uint nb, __global float4* part) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint s, e;
    block_range(b, nb, n, &s, &e);
    float4 clo = (float4)(INFINITY), chi = (float4)(-INFINITY);
    int4 finite = (int4)(-1);
    for (uint i = s; i < e; ++i) {
        __global const float* v = tri + 9 * (size_t)i;
        float4 a = (float4)(v[0], v[1], v[2], 0.0f), c = (float4)(v[3], v[4], v[5], 0.0f),
               d = (float4)(v[6], v[7], v[8], 0.0f);
        finite &= isfinite(a) & isfinite(c) & isfinite(d);
        float4 lo = fmin(fmin(a, c), d), hi = fmax(fmax(a, c), d);
        float4 m = (lo + hi) * 0.5f;
        clo = fmin(clo, m);
        chi = fmax(chi, m);
    }
    clo.w = all(finite) ? 0.0f : 1.0f;
    part[2 * b] = clo;
    part[2 * b + 1] = chi;
}

// 30-bit Morton code of the box centre in the centroid box [lo, lo + 1024 / scale).
__kernel void morton(__global const float* tri, uint n, float4 lo, float4 scale, __global uint* keys,
                     __global uint* vals) {
    uint i = get_global_id(0);
    if (i >= n) return;
    float4 blo, bhi;
    tri_box(tri, i, &blo, &bhi);
    float4 q = ((blo + bhi) * 0.5f - lo) * scale;
    q = clamp(q, 0.0f, 1023.0f);
    keys[i] = (expand10((uint)q.x) << 2) | (expand10((uint)q.y) << 1) | expand10((uint)q.z);
    vals[i] = i;
}

// The first clusters: one per triangle in Morton order (node i = triangle perm[i]), with its exact box.
// A cluster is (min, bits of its node id), (max, unused): the id rides in the box's spare lane.
__kernel void init_leaves(__global const float* tri, __global const uint* perm, uint n, __global float4* cmin,
                          __global float4* cmax) {
    uint i = get_global_id(0);
    if (i >= n) return;
    float4 lo, hi;
    tri_box(tri, perm[i], &lo, &hi);
    cmin[i] = (float4)(lo.xyz, as_float(i));
    cmax[i] = hi;
}

// Nearest neighbour of each cluster within RADIUS by the surface area of the merged box. Ties go
// to the lower index: a total order on pairs, so the globally closest pair is always mutual.
__kernel void nearest(__global const uint* cnt, uint p, __global const float4* cmin, __global const float4* cmax,
                      __global uint* nn) {
    uint n = cnt[p];
    uint i = get_global_id(0);
    if (i >= n || n <= 1) return;
    float4 lo = cmin[i], hi = cmax[i];
    uint j0 = i > RADIUS ? i - RADIUS : 0;
    uint j1 = min(i + RADIUS, n - 1);
    float best = INFINITY;
    uint bj = i;
    for (uint j = j0; j <= j1; ++j) {
        if (j == i) continue;
        float a = half_area(fmin(lo, cmin[j]), fmax(hi, cmax[j]));
        if (isnan(a)) a = INFINITY;
        if (bj == i || a < best) {
            best = a;
            bj = j;
        }
    }
    nn[i] = bj;
}

// The same nearest neighbours, one work-item per block of clusters: each pair (i, j), i < j <= i +
// RADIUS, is measured once and offered to both ends (half the area computations). A ring of
// RING >= RADIUS + 1 candidates (a power of two: a mask, no division) holds the clusters i..i+RADIUS
// still open; ties again go to the lower index.
__kernel void nearest_block(__global const uint* cnt, uint p, __global const float4* cmin,
                            __global const float4* cmax, uint nb, __global uint* nn) {
    uint b = get_global_id(0);
    uint n = cnt[p];
    if (b >= nb || n <= 1) return;
    uint s, e;
    block_range(b, nb, n, &s, &e);
    if (s >= e) return;
    float best[RING];
    uint bj[RING];
    for (uint k = 0; k < RING; ++k) {  // clusters s .. s + RING - 1
        best[(s + k) & (RING - 1)] = INFINITY;
        bj[(s + k) & (RING - 1)] = 0xffffffffu;
    }
    // pairs from the RADIUS clusters before the block into it
    for (uint i = s > RADIUS ? s - RADIUS : 0; i < s; ++i) {
        float4 lo = cmin[i], hi = cmax[i];
        uint jend = min(min(i + RADIUS, e - 1), n - 1);
        for (uint j = s; j <= jend; ++j) {
            float a = half_area(fmin(lo, cmin[j]), fmax(hi, cmax[j]));
            if (isnan(a)) a = INFINITY;
            uint r = j & (RING - 1);
            if (a < best[r] || (a == best[r] && i < bj[r])) {
                best[r] = a;
                bj[r] = i;
            }
        }
    }
    for (uint i = s; i < e; ++i) {
        float4 lo = cmin[i], hi = cmax[i];
        uint ri = i & (RING - 1);
        uint jend = min(i + RADIUS, n - 1);
        for (uint j = i + 1; j <= jend; ++j) {
            float a = half_area(fmin(lo, cmin[j]), fmax(hi, cmax[j]));
            if (isnan(a)) a = INFINITY;
            if (a < best[ri] || (a == best[ri] && j < bj[ri])) {
                best[ri] = a;
                bj[ri] = j;
            }
            uint r = j & (RING - 1);
            if (j < e && (a < best[r] || (a == best[r] && i < bj[r]))) {
                best[r] = a;
                bj[r] = i;
            }
        }
        nn[i] = bj[ri];
        best[ri] = INFINITY;  // the slot now holds cluster i + RING
        bj[ri] = 0xffffffffu;
    }
}

#if RADIUS <= 8
// The same nearest neighbours as nearest_block, eight pairs at a time (RADIUS <= 8): a window of
// float8 boxes holds clusters i+1 .. i+8 (one new cluster shifted in per step), the merged areas of
// cluster i with all of them are one float8 expression (the same float operations as half_area, so
// the same values), and `lb`/`li` hold, for clusters i .. i+7, the best area and index offered by
// clusters before i (strict < keeps the earlier, lower index on ties).
// It also does count_blocks' work (no pass of its own): a block runs from 2 RADIUS clusters before
// its range to RADIUS after it, so it knows the neighbours of every cluster within RADIUS of its
// range (the values the neighbouring blocks write: the same offers reach them), keeps the last 32
// in a ring, and checks each of its clusters for a mutual pair RADIUS steps later: bsum[b] = the
// clusters kept, bsum[nb + b] = the pairs merged.
#define EMPTY8 ((float8)(INFINITY))
#define NN_RING 32
// One step of nearest_vec for cluster i; TAIL 0: i + 9 < n (no neighbour past the end: the masks
// are constants and fold away), 1: near the end.
#define NEAREST_VEC_STEP(TAIL)                                                                           \
        float4 lo = cmin[i], hi = cmax[i];                                                               \
        float8 ex = fmax((float8)(hi.x), whx) - fmin((float8)(lo.x), wlx);                               \
        float8 ey = fmax((float8)(hi.y), why) - fmin((float8)(lo.y), wly);                               \
        float8 ez = fmax((float8)(hi.z), whz) - fmin((float8)(lo.z), wlz);                               \
        float8 a = ex * ey + ey * ez + ez * ex;                                                          \
        uint8 j = (uint8)(i) + lane;                                                                     \
        int8 bad = (TAIL) ? (j > (uint8)(n - 1)) | (lane > (uint8)(RADIUS)) : (lane > (uint8)(RADIUS));  \
        a = select(a, EMPTY8, isnan(a) | bad);                                                           \
        uint8 jid = select(j, (uint8)(0xffffffffu), bad);                                                \
        /* cluster i: best to the right (first lowest), then against the left offer */                   \
        float4 m4 = fmin(a.lo, a.hi);                                                                    \
        float2 m2 = fmin(m4.lo, m4.hi);                                                                  \
        float rm = fmin(m2.x, m2.y);                                                                     \
        uint8 cand = select((uint8)(0xffffffffu), jid, a == (float8)(rm));                               \
        uint4 c4 = min(cand.lo, cand.hi);                                                                \
        uint2 c2 = min(c4.lo, c4.hi);                                                                    \
        uint rj = min(c2.x, c2.y);                                                                       \
        float l0 = lb.s0;                                                                                \
        uint lj = li.s0;                                                                                 \
        uint best = (l0 < rm || (l0 == rm && lj < rj)) ? lj : rj;                                        \
        ring[i & (NN_RING - 1)] = best;                                                                  \
        if (i >= s && i < e) nn[i] = best;                                                               \
        /* a cluster's mutual check needs the neighbours up to RADIUS after it */                        \
        for (; q < e && q + RADIUS <= i; ++q) {                                                          \
            uint jq = ring[q & (NN_RING - 1)];                                                           \
            bool mutual = ring[jq & (NN_RING - 1)] == q;                                                 \
            kept += !(jq < q && mutual);                                                                 \
            merged += jq > q && mutual;                                                                  \
        }                                                                                                \
        /* shift the offers to clusters i+1 .. i+8, then offer i to them */                              \
        lb = (float8)(lb.s1234, lb.s567, INFINITY);                                                      \
        li = (uint8)(li.s1234, li.s567, 0xffffffffu);                                                    \
        int8 better = (a < lb) | ((a == lb) & (li == (uint8)(0xffffffffu)) & ~bad);  /* INF ties too */  \
        lb = select(lb, a, better);                                                                      \
        li = select(li, (uint8)(i), better);                                                             \
        /* shift in cluster i+9 */                                                                       \
        uint jn = (TAIL) ? min(i + 9, n - 1) : i + 9;                                                    \
        float4 nlo = cmin[jn], nhi = cmax[jn];                                                           \
        wlx = (float8)(wlx.s1234, wlx.s567, nlo.x);                                                      \
        wly = (float8)(wly.s1234, wly.s567, nlo.y);                                                      \
        wlz = (float8)(wlz.s1234, wlz.s567, nlo.z);                                                      \
        whx = (float8)(whx.s1234, whx.s567, nhi.x);                                                      \
        why = (float8)(why.s1234, why.s567, nhi.y);                                                      \
        whz = (float8)(whz.s1234, whz.s567, nhi.z);                                                      \
    do {} while (0)

__kernel void nearest_vec(__global const uint* cnt, uint p, __global const float4* cmin,
                          __global const float4* cmax, uint nb, __global uint* nn, __global uint* bsum) {
    uint b = get_global_id(0);
    uint n = cnt[p];
    if (b >= nb) return;
    uint s, e;
    block_range(b, nb, n, &s, &e);
    if (s >= e || n <= 1) {  // nothing to pair: every cluster kept
        bsum[b] = e - s;
        bsum[nb + b] = 0;
        return;
    }
    uint i0 = s > 2 * RADIUS ? s - 2 * RADIUS : 0;
    uint i1 = min(e + RADIUS, n);
    const uint8 lane = (uint8)(1, 2, 3, 4, 5, 6, 7, 8);
    float8 wlx, wly, wlz, whx, why, whz;  // boxes of clusters i+1 .. i+8
    float lx[8], ly[8], lz[8], hx[8], hy[8], hz[8];
    for (uint k = 0; k < 8; ++k) {
        uint j = min(i0 + 1 + k, n - 1);
        float4 lo = cmin[j], hi = cmax[j];
        lx[k] = lo.x; ly[k] = lo.y; lz[k] = lo.z; hx[k] = hi.x; hy[k] = hi.y; hz[k] = hi.z;
    }
    wlx = vload8(0, lx); wly = vload8(0, ly); wlz = vload8(0, lz);
    whx = vload8(0, hx); why = vload8(0, hy); whz = vload8(0, hz);
    float8 lb = EMPTY8;  // best area offered to clusters i .. i+7 by clusters before i
    uint8 li = (uint8)(0xffffffffu);
    uint ring[NN_RING];  // neighbours of the last NN_RING clusters (valid from s - RADIUS on)
    uint q = s, kept = 0, merged = 0;  // q: the next cluster of the block to check for a mutual pair
    uint im = max(i0, min(i1, n > 9 ? n - 9 : 0));  // clusters from im on have a neighbour past the end
    for (uint i = i0; i < im; ++i) {
        NEAREST_VEC_STEP(0);
    }
    for (uint i = im; i < i1; ++i) {
        NEAREST_VEC_STEP(1);
    }
    for (; q < e; ++q) {  // the last clusters (i1 = n): every neighbour is known
        uint jq = ring[q & (NN_RING - 1)];
        bool mutual = ring[jq & (NN_RING - 1)] == q;
        kept += !(jq < q && mutual);
        merged += jq > q && mutual;
    }
    bsum[b] = kept;
    bsum[nb + b] = merged;
}
#endif

// Cluster k's box: from the cluster arrays, or (from_tri, the first iteration fused with
// init_leaves) triangle perm[k]'s box with its node id k in the min's spare lane, as init_leaves
// writes it. from_tri is a constant in each kernel, so the branch folds away.
inline void load_cluster(int from_tri, __global const float* tri, __global const uint* perm,
                         __global const float4* cmin, __global const float4* cmax, uint k, float4* lo, float4* hi) {
    if (from_tri) {
        tri_box(tri, perm[k], lo, hi);
        (*lo).w = as_float(k);
    } else {
        *lo = cmin[k];
        *hi = cmax[k];
    }
}

// Merged area of two clusters (NaN as infinity, as in the searches above).
inline float merged_area(float4 alo, float4 ahi, float4 blo, float4 bhi) {
    float a = half_area(fmin(alo, blo), fmax(ahi, bhi));
    return isnan(a) ? INFINITY : a;
}

// The nearest neighbours for radius 1 (the first PLOC iteration: on a Morton-ordered triangle soup
// nearly every triangle pairs with an adjacent one, e.g. 99.996% of the city's radius-8 choices):
// the cheaper of the pairs (i - 1, i) and (i, i + 1), ties to the lower index, one area a cluster
// (A(k), the area of clusters k and k + 1, slides along). Like nearest_vec it counts per block the
// clusters kept (bsum[b]) and the pairs merged (bsum[nb + b]): a block computes the neighbours from
// one cluster before its range to one after it, which its clusters' mutual checks read.
inline void nearest_r1_body(int from_tri, __global const float* tri, __global const uint* perm, uint n,
                            __global const float4* cmin, __global const float4* cmax, uint nb,
                            __global uint* nn, __global uint* bsum) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint s, e;
    block_range(b, nb, n, &s, &e);
    if (s >= e || n <= 1) {
        bsum[b] = e - s;
        bsum[nb + b] = 0;
        return;
    }
    uint i0 = s > 0 ? s - 1 : 0, i1 = min(e, n - 1);
    float4 lo, hi, nlo, nhi;  // clusters i and i + 1
    float aprev = INFINITY;  // A(i - 1)
    if (i0 > 0) {
        load_cluster(from_tri, tri, perm, cmin, cmax, i0 - 1, &lo, &hi);
        load_cluster(from_tri, tri, perm, cmin, cmax, i0, &nlo, &nhi);
        aprev = merged_area(lo, hi, nlo, nhi);
    } else {
        load_cluster(from_tri, tri, perm, cmin, cmax, i0, &nlo, &nhi);
    }
    uint n2 = 0xffffffffu, n1 = 0xffffffffu;  // the neighbours of clusters i - 2 and i - 1
    uint kept = 0, merged = 0;
    for (uint i = i0; i <= i1; ++i) {
        lo = nlo;
        hi = nhi;
        float acur = INFINITY;  // A(i)
#ifdef PREFETCH
        if (from_tri && i + 1 + 2 * PREFETCH < n) {  // the triangle gathered 2 PREFETCH clusters on
            __global const float* t = tri + 9 * (size_t)perm[i + 1 + 2 * PREFETCH];
            __builtin_prefetch(t);
            __builtin_prefetch(t + 8);
        }
#endif
        if (i + 1 < n) {
            load_cluster(from_tri, tri, perm, cmin, cmax, i + 1, &nlo, &nhi);
            acur = merged_area(lo, hi, nlo, nhi);
        }
        uint ni = (i > 0 && (i + 1 >= n || aprev <= acur)) ? i - 1 : i + 1;
        if (i >= s && i < e) nn[i] = ni;
        uint c = i - 1;  // cluster i - 1: its neighbours' neighbours are known now
        if (i >= 1 && c >= s && c < e) {
            kept += !(n1 == c - 1 && n2 == c);
            merged += n1 == c + 1 && ni == c;
        }
        n2 = n1;
        n1 = ni;
        aprev = acur;
    }
    if (e == n) {  // the last cluster (its neighbour is n - 2)
        kept += !(n2 == n - 1);
    }
    bsum[b] = kept;
    bsum[nb + b] = merged;
}

__kernel void nearest_r1(__global const uint* cnt, uint p, __global const float4* cmin,
                         __global const float4* cmax, uint nb, __global uint* nn, __global uint* bsum) {
    nearest_r1_body(0, 0, 0, cnt[p], cmin, cmax, nb, nn, bsum);
}

// nearest_r1 over the triangles in Morton order, before any cluster array exists (the first
// iteration fused with init_leaves: merge_leaves then writes only the merged clusters).
__kernel void nearest_r1_leaves(__global const float* tri, __global const uint* perm, uint n, uint nb,
                                __global uint* nn, __global uint* bsum) {
    nearest_r1_body(1, tri, perm, n, 0, 0, nb, nn, bsum);
}

inline bool dropped(uint i, uint n, __global const uint* nn) {
    if (n <= 1) return false;
    uint j = nn[i];
    return j < i && nn[j] == i;
}

inline bool merges(uint i, uint n, __global const uint* nn) {
    if (n <= 1) return false;
    uint j = nn[i];
    return j > i && nn[j] == i;
}

// Per block of clusters: the clusters kept (bsum[b]) and the pairs merged (bsum[nb + b]).
__kernel void count_blocks(__global const uint* cnt, uint p, __global const uint* nn, uint nb,
                           __global uint* bsum) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint n = cnt[p], s, e, k = 0, g = 0;
    block_range(b, nb, n, &s, &e);
    for (uint i = s; i < e; ++i) {
        k += !dropped(i, n, nn);
        g += merges(i, n, nn);
    }
    bsum[b] = k;
    bsum[nb + b] = g;
}

// One work-item: exclusive scans of the block counts (kept clusters from 0, merged nodes from the
// node counter); the new cluster count goes to cnt[1 - p], the node counter after this iteration to
// next_node, and after iterations 0 and 1 (`it`) to marks[3 + it].
__kernel void scan_blocks(__global uint* bsum, uint nb, __global uint* cnt, uint p, __global uint* next_node,
                          uint it, __global uint* marks) {
    if (get_global_id(0) != 0) return;
    uint acc = 0, v = *next_node;
    for (uint b = 0; b < nb; ++b) {
        uint k = bsum[b], g = bsum[nb + b];
        bsum[b] = acc;
        bsum[nb + b] = v;
        acc += k;
        v += g;
    }
    cnt[1 - p] = acc;
    *next_node = v;
    if (it < 2) marks[3 + it] = acc;  // clusters written by iterations 0 and 1 (bvh_device.py, _out_offsets)
}

// A merging child's triangle count, kept-node count and height, and its SAH cost as the result:
// from its inner node record, or for a triangle (id below n_tri) 1, 1, 0 and its box's area.
inline float child_info(__global const float4* node, uint id, uint n_tri, float4 lo, float4 hi, int* count,
                        int* kept, int* height) {
    if (id < n_tri) {
        *count = 1; *kept = 1; *height = 0;
        return half_area(lo, hi);
    }
    __global const float4* r = node + NODE_F4 * (size_t)(id - n_tri);
    int4 info = as_int4(r[0]);
    *count = info.x; *kept = info.y; *height = info.z >> 1;
    return as_float(info.w);
}

// Mutual nearest pairs (i < j) merge into a new inner node (ids in cluster order from the block's
// offset) that takes cluster slot i; slot j is dropped; the kept clusters are compacted into the
// other cluster arrays, order kept. Inner node v (>= n) is stored at v - n; a child below n is a
// triangle (count 1, kept 1, height 0, cost its box's area, the box being its cluster's). The node's
// SAH cost is the cheaper of a leaf and the split (traversal 1, intersection 1 per triangle, in area
// units), as a bottom-up dynamic programme.
inline void merge_body(int from_tri, __global const float* tri, __global const uint* perm, uint n,
                       __global const uint* nn, uint nb, __global const uint* bsum, __global const float4* cmin,
                       __global const float4* cmax, __global float4* dmin, __global float4* dmax, uint n_tri,
                       __global float4* node) {
    uint bk = get_global_id(0);
    if (bk >= nb) return;
    uint s, e, o = bsum[bk], v = bsum[nb + bk];
    block_range(bk, nb, n, &s, &e);
    bool pairs = n > 1;
    for (uint i = s; i < e; ++i) {
#ifdef PREFETCH
        uint ip = i + PREFETCH;
        if (from_tri && i + 2 * PREFETCH < e) {  // the triangles gathered 2 PREFETCH clusters on
            __global const float* t = tri + 9 * (size_t)perm[i + 2 * PREFETCH];
            __builtin_prefetch(t);
            __builtin_prefetch(t + 8);
        }
        if (!from_tri && pairs && ip < e) {  // the child records a merge reads PREFETCH clusters on
            uint jp = nn[ip];
            if (jp > ip) {
                uint pa = as_uint(cmin[ip].w), pb = as_uint(cmin[jp].w);
                if (pa >= n_tri) __builtin_prefetch(node + NODE_F4 * (size_t)(pa - n_tri));
                if (pb >= n_tri) __builtin_prefetch(node + NODE_F4 * (size_t)(pb - n_tri));
            }
        }
#endif
        // dropped / merges, reading the neighbours once
        uint j = pairs ? nn[i] : i;
        bool mutual = j != i && nn[j] == i;
        if (mutual && j < i) continue;  // dropped: merged into cluster j
        float4 alo, ahi;
        load_cluster(from_tri, tri, perm, cmin, cmax, i, &alo, &ahi);
        uint a = as_uint(alo.w);
        if (!mutual) {
            dmin[o] = alo;
            dmax[o] = ahi;
            ++o;
            continue;
        }
        float4 blo, bhi;
        load_cluster(from_tri, tri, perm, cmin, cmax, j, &blo, &bhi);
        uint b = as_uint(blo.w);
        float4 lo = fmin(alo, blo), hi = fmax(ahi, bhi);
        int ca, cb, ka, kb, ha, hb;
        float sa = child_info(node, a, n_tri, alo, ahi, &ca, &ka, &ha);
        float sb = child_info(node, b, n_tri, blo, bhi, &cb, &kb, &hb);
        int c = ca + cb;
        float area = half_area(lo, hi);
        float split = area + sa + sb;
        float leaf = (float)c * area;
        int ok = c <= MIN_LEAF || (c <= MAX_LEAF && leaf <= split);
        int h = ok ? 0 : 1 + max(ha, hb);
        __global float4* r = node + NODE_F4 * (size_t)(v - n_tri);
        r[0] = as_float4((int4)(c, ok ? 1 : 1 + ka + kb, (h << 1) | ok, as_int(ok ? leaf : split)));
        r[1] = (float4)(lo.xyz, as_float(a));
        r[2] = (float4)(hi.xyz, as_float(b));
        dmin[o] = (float4)(lo.xyz, as_float(v));
        dmax[o] = hi;
        ++o;
        ++v;
    }
}

__kernel void merge_scatter(__global const uint* cnt, uint p, __global const uint* nn, uint nb,
                            __global const uint* bsum, __global const float4* cmin, __global const float4* cmax,
                            __global float4* dmin, __global float4* dmax, uint n_tri, __global float4* node) {
    merge_body(0, 0, 0, cnt[p], nn, nb, bsum, cmin, cmax, dmin, dmax, n_tri, node);
}

// merge_scatter of the first iteration fused with init_leaves: the clusters are the triangles in
// Morton order (boxes gathered again, never written for all n), only the merged ones are written.
__kernel void merge_leaves(__global const float* tri, __global const uint* perm, uint n, __global const uint* nn,
                           uint nb, __global const uint* bsum, __global float4* dmin, __global float4* dmax,
                           __global float4* node) {
    merge_body(1, tri, perm, n, nn, nb, bsum, 0, 0, dmin, dmax, n, node);
}

// ---- layout -----------------------------------------------------------------------------------
// The finished tree is written breadth first, one level at a time, straight into `out` (min and
// max: 3 floats per node, then left, right, first, count, parent, depth, height: m ints each, then
// tri_order: n ints). lev[d] is the first index of level d (lev[0] = 0, lev[1] = 1; level_scan
// writes lev[d + 2]). The children of level d's inner nodes are level d + 1, in their parents'
// order, left then right: the same order as a stable sort of the preorder by depth. A node's
// parent writes all of it from its record (one record read a node) but left and depth, and keeps
// in right and depth, until the node's level is placed, its own links (a triangle: its Morton
// index in right).

// marks[0] = root node id, marks[1] = kept nodes, marks[2] = the root's height (levels - 1).
__kernel void root_count(__global const float4* cmin, uint n_tri, __global const float4* node,
                         __global uint* marks) {
    if (get_global_id(0) != 0) return;
    uint root = as_uint(cmin[0].w);
    marks[0] = root;
    marks[1] = 1u;
    marks[2] = 0u;
    if (root >= n_tri) {
        __global const float4* r = node + NODE_F4 * (size_t)(root - n_tri);
        int4 info = as_int4(r[0]);
        marks[1] = (uint)info.y;
        marks[2] = (uint)(info.z >> 1);
    }
}

// The finished tree's arrays lie at word offsets offs[0..9] of `out` (min, max, left, right, first,
// count, parent, depth, height, tri_order): the host puts them where the cluster boxes already
// touched the pages, so fewer of them are fresh (bvh_device.py, _out_offsets). 64-bit offsets: the
// regions span 16n words, past 2^32 from about 268 M triangles.
#define OUT_FIELDS(out, offs)                                         \
    __global float* omin = (__global float*)((out) + (offs)[0]);      \
    __global float* omax = (__global float*)((out) + (offs)[1]);      \
    __global int* oleft = (out) + (offs)[2];                          \
    __global int* oright = (out) + (offs)[3];                         \
    __global int* ofirst = (out) + (offs)[4];                         \
    __global int* ocount = (out) + (offs)[5];                         \
    __global int* oparent = (out) + (offs)[6];                        \
    __global int* odepth = (out) + (offs)[7];                         \
    __global int* oheight = (out) + (offs)[8];                        \
    __global int* tri_order = (out) + (offs)[9]

// Node v (PLOC id) at index k, child of `parent`, first slot `first`: its box, triangle count and
// height, its links kept in right/depth; returns its triangle count.
inline int put_node(uint v, uint k, int parent, int first, uint n_tri, __global const float4* node,
                    __global const float* tri, __global const uint* perm, __global int* out,
                    __global const ulong* offs) {
    OUT_FIELDS(out, offs);
    float4 lo, hi;
    int c = 1, h = 0;
    if (v < n_tri) {
        tri_box(tri, perm[v], &lo, &hi);
        oright[k] = (int)v;
    } else {
        __global const float4* r = node + NODE_F4 * (size_t)(v - n_tri);
        int4 info = as_int4(r[0]);
        lo = r[1];
        hi = r[2];
        c = info.x;
        h = info.z >> 1;
        oright[k] = as_int(lo.w);
        odepth[k] = as_int(hi.w);
    }
    vstore3(lo.xyz, k, omin);
    vstore3(hi.xyz, k, omax);
    ocount[k] = c;
    oheight[k] = h;
    oparent[k] = parent;
    ofirst[k] = first;
    return c;
}

__kernel void layout_root(__global const uint* marks, uint m, uint n_tri, __global const float4* node,
                          __global const float* tri, __global const uint* perm, __global uint* lev,
                          __global int* out, __global const ulong* offs) {
    if (get_global_id(0) != 0) return;
    put_node(marks[0], 0, -1, 0, n_tri, node, tri, perm, out, offs);
    lev[0] = 0;
    lev[1] = 1;
}

// Level d, per block: its inner nodes (height > 0: they have children in the tree) in bsum[b].
__kernel void level_count(uint d, __global const uint* lev, uint nb, __global const int* out, __global const ulong* offs,
                          __global uint* bsum) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    __global const int* oheight = out + offs[8];
    uint l0 = lev[d], s, e, g = 0;
    block_range(b, nb, lev[d + 1] - l0, &s, &e);
    for (uint k = l0 + s; k < l0 + e; ++k) g += oheight[k] > 0;
    bsum[b] = g;
}

// One work-item: exclusive scan of level d's per-block inner-node counts; lev[d + 2] = the end of
// level d + 1 (two children per inner node).
__kernel void level_scan(uint d, uint nb, __global uint* bsum, __global uint* lev) {
    if (get_global_id(0) != 0) return;
    uint acc = 0;
    for (uint b = 0; b < nb; ++b) {
        uint g = bsum[b];
        bsum[b] = acc;
        acc += g;
    }
    lev[d + 2] = lev[d + 1] + 2 * acc;
}

#ifdef PREFETCH
// Ask for what put_node will read of node v: a record's first and last byte (48 bytes: half of them
// span two cache lines), or the triangle's 36 bytes (likewise).
inline void prefetch_node(uint v, uint n_tri, __global const float4* node, __global const float* tri,
                          __global const uint* perm) {
    __global const char* p = v < n_tri ? (__global const char*)(tri + 9 * (size_t)perm[v])
                                       : (__global const char*)(node + NODE_F4 * (size_t)(v - n_tri));
    __builtin_prefetch(p);
    __builtin_prefetch(p + (v < n_tri ? 35 : 47));
}
#endif

// Level d, per block: an inner node writes its two children at the next level's end, in order,
// and links them; a leaf writes its triangles' Morton indices (left subtree first) to tri_order from
// its first slot (tri_ids makes them triangle ids: perm read in slot order, not leaf by leaf in
// level order, where those reads missed the cache: a third of level_place's time). Then the node's
// depth.
__kernel void level_place(uint d, __global const uint* lev, uint nb, uint n_tri,
                          __global const float4* node, __global const float* tri, __global const uint* perm,
                          __global const uint* bsum, __global int* out, __global const ulong* offs) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    OUT_FIELDS(out, offs);
    uint l0 = lev[d], s, e;
    block_range(b, nb, lev[d + 1] - l0, &s, &e);
    uint c = lev[d + 1] + 2 * bsum[b];
    for (uint k = l0 + s; k < l0 + e; ++k) {
#ifdef PREFETCH
        if (k + PREFETCH < l0 + e && oheight[k + PREFETCH] > 0) {  // the records read PREFETCH nodes on
            uint pl = (uint)oright[k + PREFETCH], pr = (uint)odepth[k + PREFETCH];
            prefetch_node(pl, n_tri, node, tri, perm);
            prefetch_node(pr, n_tri, node, tri, perm);
        }
#endif
        uint l = (uint)oright[k], r = (uint)odepth[k];
        int first = ofirst[k];
        if (oheight[k] > 0) {
            int cl = put_node(l, c, (int)k, first, n_tri, node, tri, perm, out, offs);
            put_node(r, c + 1, (int)k, first + cl, n_tri, node, tri, perm, out, offs);
            oleft[k] = (int)c;
            oright[k] = (int)c + 1;
            c += 2;
        } else {
            int slot = first;
            if (ocount[k] == 1) {  // a triangle (inner nodes hold at least two)
                tri_order[slot] = (int)l;
            } else {
                uint stack[MAX_LEAF + 1];
                int sp = 1;
                stack[0] = r;
                uint w = l;
                for (;;) {
                    if (w < n_tri) {
                        tri_order[slot++] = (int)w;
                        if (sp == 0) break;
                        w = stack[--sp];
                    } else {
                        __global const float4* wr = node + NODE_F4 * (size_t)(w - n_tri);
                        stack[sp++] = as_uint(wr[2].w);
                        w = as_uint(wr[1].w);
                    }
                }
            }
            oleft[k] = -1;
            oright[k] = -1;
        }
        odepth[k] = (int)d;
    }
}

// Per block of leaf-order slots: tri_order[s] = perm[tri_order[s]] (Morton index -> triangle id).
// The leaves' slots follow the Morton order closely, so perm is read nearly in order.
__kernel void tri_ids(uint n, uint nb, __global const uint* perm, __global int* out, __global const ulong* offs) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    __global int* tri_order = out + offs[9];
    uint s, e;
    block_range(b, nb, n, &s, &e);
    for (uint i = s; i < e; ++i) tri_order[i] = (int)perm[tri_order[i]];
}

#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
// BuildStats of the finished tree (the sums of viewer.accel.bvh.tree_stats, in float64 as there),
// per block of nodes; the host adds the blocks (one read): part[STATS_W * b + ...] = inner nodes'
// area sum, leaves' area x triangles sum, inner node count, deepest leaf, leaves of 0 .. MAX_LEAF
// triangles.
#define STATS_W (MAX_LEAF + 5)
__kernel void stats_blocks(uint m, uint nb, __global const int* out, __global const ulong* offs,
                           __global double* part) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint s, e;
    block_range(b, nb, m, &s, &e);
    __global const float* omin = (__global const float*)(out + offs[0]);
    __global const float* omax = (__global const float*)(out + offs[1]);
    __global const int* oleft = out + offs[2];
    __global const int* ocount = out + offs[5];
    __global const int* odepth = out + offs[7];
    double inner = 0.0, leaf = 0.0, n_inner = 0.0, deepest = 0.0;
    double hist[MAX_LEAF + 1];
    for (int c = 0; c <= MAX_LEAF; ++c) hist[c] = 0.0;
    for (uint k = s; k < e; ++k) {
        double ex = (double)omax[3 * k] - (double)omin[3 * k];
        double ey = (double)omax[3 * k + 1] - (double)omin[3 * k + 1];
        double ez = (double)omax[3 * k + 2] - (double)omin[3 * k + 2];
        double area = ex * ey + ey * ez + ez * ex;
        if (oleft[k] >= 0) {
            inner += area;
            n_inner += 1.0;
        } else {
            int c = ocount[k];
            leaf += area * (double)c;
            hist[min(c, MAX_LEAF)] += 1.0;
            deepest = fmax(deepest, (double)odepth[k]);
        }
    }
    __global double* p = part + STATS_W * (size_t)b;
    p[0] = inner;
    p[1] = leaf;
    p[2] = n_inner;
    p[3] = deepest;
    for (int c = 0; c <= MAX_LEAF; ++c) p[4 + c] = hist[c];
}
#endif

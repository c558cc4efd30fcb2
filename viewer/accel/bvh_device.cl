// Device BVH build: Morton order + PLOC clustering + SAH leaf collapse (viewer/accel/bvh_device.py).
// Defines: WG (work-items per group of the per-element kernels), RADIUS (PLOC search radius),
// MAX_LEAF, MIN_LEAF (leaf sizes as in viewer/accel/bvh.py).
//
// Nodes 0..n-1 are the triangles in Morton order (node i = triangle perm[i]); merged nodes get ids
// n, n+1, ... from an atomic counter, so a child's id is always below its parent's. Clusters are
// (node id, box) triples in Morton order; an iteration is nearest -> merge -> count -> scan ->
// scatter, all reading the cluster count from the device (cnt[p]) so the host need not read it.

#define RING (RADIUS < 8 ? 8 : RADIUS < 16 ? 16 : RADIUS < 32 ? 32 : 64)

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

// Triangle boxes (exact float32 min/max of the vertices) and box centres per axis.
__kernel void tri_boxes(__global const float* tri, uint n, __global float4* bmin, __global float4* bmax,
                        __global float* cx, __global float* cy, __global float* cz) {
    uint i = get_global_id(0);
    if (i >= n) return;
    __global const float* t = tri + 9 * (size_t)i;
    float4 a = (float4)(t[0], t[1], t[2], 0.0f), b = (float4)(t[3], t[4], t[5], 0.0f),
           c = (float4)(t[6], t[7], t[8], 0.0f);
    float4 lo = fmin(fmin(a, b), c), hi = fmax(fmax(a, b), c);
    bmin[i] = lo;
    bmax[i] = hi;
    float4 m = (lo + hi) * 0.5f;
    cx[i] = m.x;
    cy[i] = m.y;
    cz[i] = m.z;
}

// 30-bit Morton code of the box centre in the centroid box [lo, lo + 1024 / scale).
__kernel void morton(__global const float* cx, __global const float* cy, __global const float* cz, uint n,
                     float4 lo, float4 scale, __global uint* keys, __global uint* vals) {
    uint i = get_global_id(0);
    if (i >= n) return;
    float4 q = ((float4)(cx[i], cy[i], cz[i], 0.0f) - lo) * scale;
    q = clamp(q, 0.0f, 1023.0f);
    keys[i] = (expand10((uint)q.x) << 2) | (expand10((uint)q.y) << 1) | expand10((uint)q.z);
    vals[i] = i;
}

// Leaf nodes (one per triangle, Morton order) and the first clusters.
__kernel void init_leaves(__global const uint* perm, __global const float4* bmin, __global const float4* bmax,
                          uint n, __global float4* nmin, __global float4* nmax, __global int* left,
                          __global int* right, __global int* parent, __global int* count, __global int* kept_nodes,
                          __global int* height, __global uint* uheight, __global float* cost,
                          __global uchar* leaf_ok, __global uint* cnode, __global float4* cmin,
                          __global float4* cmax) {
    uint i = get_global_id(0);
    if (i >= n) return;
    uint t = perm[i];
    float4 lo = bmin[t], hi = bmax[t];
    nmin[i] = lo;
    nmax[i] = hi;
    left[i] = -1;
    right[i] = -1;
    parent[i] = -1;
    count[i] = 1;
    kept_nodes[i] = 1;
    height[i] = 0;
    uheight[i] = 0;
    cost[i] = half_area(lo, hi);
    leaf_ok[i] = 1;
    cnode[i] = i;
    cmin[i] = lo;
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

// Mutual nearest pairs (i < j) merge into a new node that takes cluster slot i; slot j is dropped
// by the compaction. The node's SAH cost is the cheaper of a leaf and the split (traversal 1,
// intersection 1 per triangle, in area units), as a bottom-up dynamic programme.
__kernel void merge(__global const uint* cnt, uint p, __global const uint* nn, __global uint* cnode,
                    __global float4* cmin, __global float4* cmax, volatile __global uint* next_node,
                    __global float4* nmin, __global float4* nmax, __global int* left, __global int* right,
                    __global int* parent, __global int* count, __global int* kept_nodes, __global int* height,
                    __global uint* uheight, __global float* cost, __global uchar* leaf_ok) {
    uint n = cnt[p];
    uint i = get_global_id(0);
    if (i >= n || n <= 1) return;
    uint j = nn[i];
    if (j <= i || nn[j] != i) return;
    uint a = cnode[i], b = cnode[j];
    float4 lo = fmin(cmin[i], cmin[j]), hi = fmax(cmax[i], cmax[j]);
    uint v = atomic_inc(next_node);
    nmin[v] = lo;
    nmax[v] = hi;
    left[v] = (int)a;
    right[v] = (int)b;
    parent[v] = -1;
    parent[a] = (int)v;
    parent[b] = (int)v;
    int c = count[a] + count[b];
    count[v] = c;
    float area = half_area(lo, hi);
    float split = area + cost[a] + cost[b];
    float leaf = (float)c * area;
    uchar ok = c <= MIN_LEAF || (c <= MAX_LEAF && leaf <= split);
    leaf_ok[v] = ok;
    cost[v] = ok ? leaf : split;
    kept_nodes[v] = ok ? 1 : 1 + kept_nodes[a] + kept_nodes[b];
    height[v] = ok ? 0 : 1 + max(height[a], height[b]);
    uheight[v] = 1 + max(uheight[a], uheight[b]);
    cnode[i] = v;
    cmin[i] = lo;
    cmax[i] = hi;
}

inline bool dropped(uint i, uint n, __global const uint* nn) {
    if (n <= 1) return false;
    uint j = nn[i];
    return j < i && nn[j] == i;
}

__kernel void count_kept(__global const uint* cnt, uint p, __global const uint* nn, uint nb, __global uint* bsum) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint n = cnt[p], s, e, k = 0;
    block_range(b, nb, n, &s, &e);
    for (uint i = s; i < e; ++i) k += !dropped(i, n, nn);
    bsum[b] = k;
}

// One work-item: exclusive scan of the block counts; the new cluster count goes to cnt[1 - p].
__kernel void scan_blocks(__global uint* bsum, uint nb, __global uint* cnt, uint p) {
    if (get_global_id(0) != 0) return;
    uint acc = 0;
    for (uint b = 0; b < nb; ++b) {
        uint k = bsum[b];
        bsum[b] = acc;
        acc += k;
    }
    cnt[1 - p] = acc;
}

__kernel void scatter(__global const uint* cnt, uint p, __global const uint* nn, uint nb,
                      __global const uint* bsum, __global const uint* cnode, __global const float4* cmin,
                      __global const float4* cmax, __global uint* dnode, __global float4* dmin,
                      __global float4* dmax) {
    uint b = get_global_id(0);
    if (b >= nb) return;
    uint n = cnt[p], s, e, o = bsum[b];
    block_range(b, nb, n, &s, &e);
    for (uint i = s; i < e; ++i) {
        if (dropped(i, n, nn)) continue;
        dnode[o] = cnode[i];
        dmin[o] = cmin[i];
        dmax[o] = cmax[i];
        ++o;
    }
}

// Pointer-jumping state per node: (slot offset, preorder offset, depth, ancestor). A node's own
// term: as a right child it is preceded by its left sibling's triangles and kept nodes; every
// non-root node is one below its parent. Summed over the path to the root they give the node's
// first triangle slot, its preorder index among the kept nodes and its depth.
// Nodes inside a leaf (an ancestor was chosen as a leaf) get ancestor -2: they take no part (no
// kept node points at them) and `emit` skips them.
__kernel void jump_init(uint m, __global const int* left, __global const int* right, __global const int* parent,
                        __global const int* count, __global const int* kept_nodes, __global const uchar* leaf_ok,
                        __global int4* st) {
    uint v = get_global_id(0);
    if (v >= m) return;
    int u = parent[v];
    for (int w = u; w >= 0 && count[w] <= MAX_LEAF; w = parent[w]) {
        if (leaf_ok[w]) {
            st[v] = (int4)(0, 0, 0, -2);
            return;
        }
    }
    int4 s = (int4)(0, 0, 0, -1);
    if (u >= 0) {
        bool r = right[u] == (int)v;
        int l = left[u];
        s = (int4)(r ? count[l] : 0, 1 + (r ? kept_nodes[l] : 0), 1, u);
    }
    st[v] = s;
}

__kernel void jump(uint m, __global const int4* src, __global int4* dst) {
    uint v = get_global_id(0);
    if (v >= m) return;
    int4 s = src[v];
    if (s.w >= 0) {
        int4 a = src[s.w];
        s = (int4)(s.x + a.x, s.y + a.y, s.z + a.z, a.w);
    }
    dst[v] = s;
}

// Kept nodes (no ancestor chosen as a leaf) by preorder index: pnode[pre] = node; the depth is the
// sort key that turns preorder into breadth-first order (`order`: BFS position -> preorder index).
__kernel void preorder(uint m, __global const int4* st, __global uint* pnode, __global uint* keys,
                       __global uint* order) {
    uint v = get_global_id(0);
    if (v >= m) return;
    int4 s = st[v];
    if (s.w == -2) return;  // inside a leaf
    pnode[s.y] = v;
    keys[s.y] = (uint)s.z;
    order[s.y] = (uint)s.y;
}

__kernel void invert(uint m, __global const uint* order, __global int* rank) {
    uint k = get_global_id(0);
    if (k >= m) return;
    rank[order[k]] = (int)k;
}

// The canonical tree in breadth-first order (rank: preorder index -> BFS position); a leaf also
// writes its triangles (left subtree first) to tri_order at its first slot.
__kernel void emit(uint m, __global const uint* order, __global const int* rank, __global const uint* pnode,
                   __global const int4* st, __global const float4* nmin, __global const float4* nmax,
                   __global const int* left, __global const int* right, __global const int* parent,
                   __global const int* count, __global const int* height, __global const uchar* leaf_ok,
                   __global const uint* perm, __global float4* omin, __global float4* omax, __global int* oleft,
                   __global int* oright, __global int* ofirst, __global int* ocount, __global int* oparent,
                   __global int* odepth, __global int* oheight, __global int* tri_order) {
    uint k = get_global_id(0);
    if (k >= m) return;
    int v = (int)pnode[order[k]];
    int4 s = st[v];
    omin[k] = nmin[v];
    omax[k] = nmax[v];
    ofirst[k] = s.x;
    ocount[k] = count[v];
    odepth[k] = s.z;
    oheight[k] = height[v];
    int u = parent[v];
    oparent[k] = u >= 0 ? rank[st[u].y] : -1;
    if (!leaf_ok[v]) {
        oleft[k] = rank[st[left[v]].y];
        oright[k] = rank[st[right[v]].y];
        return;
    }
    oleft[k] = -1;
    oright[k] = -1;
    int stack[MAX_LEAF + 1];
    int sp = 0, w = v, slot = s.x;
    for (;;) {
        if (left[w] < 0) {
            tri_order[slot++] = (int)perm[w];
            if (sp == 0) break;
            w = stack[--sp];
        } else {
            stack[sp++] = right[w];
            w = left[w];
        }
    }
}

// CHC+RT leaf cache (paper section 5.2): leaves a ray enters are not intersected at once but
// collected, up to LEAF_CACHE of them, and their triangles are then tested in ONE loop over all of
// them. Fragments of a SIMD vector reach leaves at different traversal steps; delaying the tests
// lets more of them run the triangle loop together (coherent), at the price of pruning with an
// older hit distance (more box tests). Exact: every collected leaf is intersected before the ray
// is finished (flushLeaves after the traversal), and a stale hit.t only prunes less.
// LEAF_CACHE = 0 intersects each leaf immediately (no cache).
#ifndef LEAF_CACHE
#define LEAF_CACHE 0
#endif

#if LEAF_CACHE > 0
int leafFirst[LEAF_CACHE];
int leafCount[LEAF_CACHE];
int leafTotal = 0;  // triangles held
int nLeaves = 0;

// Intersect every cached leaf's triangles in one flat loop; returns true if any was hit.
bool flushLeaves(RayPre r, float tmin, inout Hit hit) {
    bool found = false;
    int c = 0, k = 0;
    for (int i = 0; i < leafTotal; ++i) {
        if (k == leafCount[c]) { k = 0; ++c; }  // leaf counts are >= 1: one step suffices
        int slot = leafFirst[c] + k;
        ++k;
        if (intersectSlot(r, slot, tmin, hit)) found = true;
    }
    nLeaves = 0;
    leafTotal = 0;
    return found;
}
#else
bool flushLeaves(RayPre r, float tmin, inout Hit hit) { return false; }
#endif

// A leaf the ray enters: intersect now (no cache) or cache it, flushing a full cache. Returns true
// if triangles were tested and one was hit.
bool visitLeaf(RayPre r, int first, int count, float tmin, inout Hit hit) {
#if LEAF_CACHE > 0
    if (count <= 0) return false;
    leafFirst[nLeaves] = first;
    leafCount[nLeaves] = count;
    ++nLeaves;
    leafTotal += count;
    return nLeaves == LEAF_CACHE ? flushLeaves(r, tmin, hit) : false;
#else
    return intersectLeaf(r, first, count, tmin, hit);
#endif
}

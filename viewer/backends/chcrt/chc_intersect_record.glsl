// CHC+RT intersection: the pixels of a tile traverse up to CHC_MAX_ITEMS scheduled subtrees (BVH
// inner nodes, or leaves) with a stack bounded by the subtree height (STACK_SIZE = the maximum
// subtree height, or the tree's, + 2). The hit is output through the depth test (LESS on key(t)), so
// only a hit nearer than the pixel's current one is written; an any-hit ray writes depth 0 and is
// finished.
//
// The item loop only tests the items' boxes and marks the entered ones in bit masks. Scheduled BVH
// leaves the ray enters are intersected after it, before the traversal (a triangle loop inside the
// item loop made every lane of a SIMD group wait for the lanes that entered a leaf: the visible
// records' draw of city-near primary+ao:4 at 1280x720 took 6 % longer on llvmpipe, median of five
// alternated pairs of runs). The inner subtree roots it entered are then taken one by one from their
// mask, in the record's order (closest-hit passes: by gap, near to far; own items before merged kept
// pairs), by ONE traverseBVH-style loop (intersect.glsl: same node order, nearer child first) that
// starts the next root whenever its stack runs empty. Nothing of the items goes on the stack: an
// insertion sort by entry distance there (per-lane indices: scatters and gathers on llvmpipe) cost
// 8-9 % of the visible records' draw against this order (city-near 1280x720, primary and ao:4, two
// alternated pairs of runs); a root whose box now lies beyond the hit costs one node visit.
//
// Loop limit: Mesa llvmpipe silently ends shader loops after 65,535 loop back-edges per invocation,
// one counter shared by every loop of the shader (per SIMD vector of fragments); once it is spent,
// every further loop runs one iteration. (That is what an earlier version, which called
// traverseBVH once per subtree, ran into; it was not a miscompilation.) A batch of up to
// CHC_MAX_ITEMS subtrees of <= 4096 triangles can need more than 24 x 4,000 node visits, so the
// bound is reachable (a closed fan of 62,832 needles reaches it). The traversal therefore stops
// after CHC_MAX_VISITS node visits (chcrt.py derives it like gl_traversal.py max_visits) and hands the
// ray to the glsl backend's resumable full traversal: the pixel is marked -2 in resumeSlot and
// counted once; after the CHC+RT pass those rays are traced again from the root, in as many draws
// as they need, and their hits replace what this pass found.
//
// Merged kept pairs (GPU-driven pass on a device front, chc_querycull.comp mergeKept): a visible
// record may also carry the invisible pairs the cull kept for its tile (vKeptBase, vKeptCount: items
// in the same buffer, sorted by gap). The item loop tests them after the record's own items, and
// the entered ones join the same stack and traversal: what the survivors' draw would do, without a
// second fragment per ray. Their counts (the query) take the ray's final nearest hit: a kept pair
// counts a ray that enters its box before that hit.
//
// This file: what the intersection's two stages share (chc_intersect.frag: a fragment per record and
// pixel; chc_visible.comp: an invocation per pixel over its tile's visible records).
#include "chc_common.glsl"
#include "chc_leafcache.glsl"
uniform int anyHit;
uniform int countOverlays;
#ifdef CHC_COUNT_ITEMS
uniform int gapOrder;  // ChcrtParams.gap_order: every record's items sorted by gap
#endif
uniform int useHint;  // 1: hintId holds last pass's hit triangle per pixel (leaf-order slot, -1 = none)
uniform isampler2D hintId;
#if CHC_MAX_ITEMS > 32
#error "chc_intersect_record.glsl: at most 32 items per record (enteredMask)"
#endif
#ifndef CHC_MAX_VISITS
#define CHC_MAX_VISITS 2048
#endif
#ifndef RESUMABLE
#define RESUMABLE 1
#endif
#if RESUMABLE  // (0 without a loop limit: CHC_MAX_VISITS exceeds the tree's nodes, nothing is handed over)
layout(r32i, binding = BIND_IMG_RESUME) uniform coherent iimage2D resumeSlot;  // gl_traversal.py ResumableTraversal
layout(std430, binding = BIND_RESUME_COUNTERS) buffer ResumeCounters { int unfinished; int allocated; };
#endif
#if defined(CHC_MERGE_KEPT) && !defined(CHC_COUNT_ITEMS)
#error "chc_intersect_record.glsl: CHC_MERGE_KEPT needs CHC_COUNT_ITEMS"
#endif
#ifdef CHC_COUNT_ITEMS
// GPU-driven pass: the intersection is the query. A ray that enters an item's box before its
// nearest hit so far (the query's pass condition) counts into the item's pair slot (p2 >= 0).
layout(std430, binding = BIND_CHC_QUERY_COUNTS) buffer ChcQueryCounts { uint chcPassed[]; };
#endif
#ifdef WORK_PROBE
// work probe (chcrt_pass_device.py, ChcrtParams.work_probe): on the sampled pixels (chc_probe.glsl), what this
// fragment did is summed into the front's META row, which chc_probe.comp fills with what the full
// traversal does for the same rays
#include "chc_probe.glsl"
uniform int probeStride;
uniform int probeBase;  // META index of the front's META_PROBE_FRONT
layout(std430, binding = BIND_FR_META) buffer ChcMeta { int chcMeta[]; };
#endif

// The next entered inner subtree root of a record (own items first, then its merged kept pairs),
// taken off its mask; -1 when there is none left.
int nextRoot(inout uint own, inout uint kept, int ownBase, int keptBase) {
    if ((own | kept) == 0u) return -1;
    bool o = own != 0u;
    int i = findLSB(o ? own : kept);
    if (o) own &= own - 1u; else kept &= kept - 1u;
    return loadItem(o ? ownBase + i : keptBase + i).ref;
}

// One record's items for a ray (own items at itemBase, then its merged kept pairs at keptBase): the
// item loop, the entered leaves, the entered subtrees' traversal, the pairs' query counts, the hand
// over at the loop limit, the leaf cache's flush. `hit` holds the nearest hit so far (also as tmax);
// `done`: an any-hit ray finished, or a ray handed over (nothing more to trace here); `visits`: node
// visits so far, of every record this invocation traced (the loop limit's budget).
void intersectRecord(ivec2 px, int itemBase, int itemCount, int keptBase, int keptCount, RayPre r, float tmin,
                     float dlen, bool any, inout Hit hit, inout bool done, inout int visits) {
    if (done) return;
    int stackNode[STACK_SIZE];
    float stackT[STACK_SIZE];
    int sp = 0;
    uint entered = 0u;
    uint enteredMask = 0u;  // items whose box the ray entered (the counted ones count after the traversal)
    uint keptMask = 0u;  // the same for the merged kept pairs
    uint leafMask = 0u, leafKept = 0u;  // entered BVH leaves among the items (own, kept)
    uint rootOwn = 0u, rootKept = 0u;  // entered inner subtree roots (own, kept), traversed in item order
#ifdef CHC_COUNT_ITEMS
    // gap_order: a record holds its items sorted by gap, a lower bound of the distance from every ray
    // origin of the tile to the box (invisible pairs: chc_querycull.comp; visible: chc_visorder.comp):
    // the first item whose gap lies beyond the ray's nearest hit so far (t * |d|, with the gap's
    // relative margin) ends the box tests of its list, as neither it nor any later item can be
    // entered before that hit
    bool byGap = gapOrder != 0;
#else
    const bool byGap = false;
#endif
    // the record's items, then its merged kept pairs (GPU-driven builds only): one loop, one set of masks
    int total = itemCount + keptCount;
    for (int k = 0; k < total; ++k) {
        bool own = keptCount == 0 || k < itemCount;  // (a constant without merge_kept: the loop folds to the own items')
        // (an any-hit ray finished by its hint tests no item; one finished later, in a leaf or the
        // traversal, counts the kept pairs it entered before that hit)
        int i = own ? k : k - itemCount;
        ChcItem it = loadItem(own ? itemBase + i : keptBase + i);
        if (byGap && it.gap > hit.t * dlen) {
            if (!own || keptCount == 0) break;
            k = itemCount - 1;  // on with the kept pairs
            continue;
        }
        float te;
        if (intersectBox(r, it.bmin, it.bmax, tmin, hit.t, te)) {
            ++entered;
            // (whether the pair is counted, p2 >= 0, is read after the traversal for the entered
            // items only: the loop reads two texels an item, chc_records.glsl)
            if (own) enteredMask |= 1u << uint(i);
            else keptMask |= 1u << uint(i);
            if (it.count > 0) {  // a scheduled BVH leaf: intersected after the loop
                if (own) leafMask |= 1u << uint(i);
                else leafKept |= 1u << uint(i);
            } else {
                if (own) rootOwn |= 1u << uint(i);
                else rootKept |= 1u << uint(i);
            }
        }
    }
    // the entered leaves (a hit of an any-hit ray ends the ray; the counts above took the boxes
    // entered before the hit so far, a kept pair's below takes the final one)
    while ((leafMask | leafKept) != 0u && !done) {
        bool o = leafMask != 0u;
        int i = findLSB(o ? leafMask : leafKept);
        if (o) leafMask &= leafMask - 1u; else leafKept &= leafKept - 1u;
        ChcItem it = loadItem(o ? itemBase + i : keptBase + i);
        if (visitLeaf(r, it.ref, it.count, tmin, hit) && any) done = true;
    }
    if (done) { rootOwn = 0u; rootKept = 0u; }
    int ni = nextRoot(rootOwn, rootKept, itemBase, keptBase);
    bool handOver = false;
    while (ni >= 0) {
        // the loop limit is near: finish this ray elsewhere (the atomics after the loop: llvmpipe
        // runs a branch's code under a lane mask even when no lane takes it, so nothing heavy is
        // written inside this loop)
        if (visits >= CHC_MAX_VISITS) { handOver = true; break; }
        ++visits;
        Node nd = loadNode(ni);
        WORK(workNode);
        float tl, tr;
        bool hl = intersectBox(r, nd.lmin, nd.lmax, tmin, hit.t, tl);
        bool hr = intersectBox(r, nd.rmin, nd.rmax, tmin, hit.t, tr);
#if LEAF_CACHE == 0
        // both entered leaf children in one triangle loop (intersect.glsl)
        if (intersectLeafChildren(r, nd, hl, hr, tmin, any, hit) && any) { done = true; break; }
#else
        if (hl && nd.left < 0) {
            hl = false;
            if (visitLeaf(r, ~nd.left, nd.lcount, tmin, hit) && any) { done = true; break; }
        }
        if (hr && nd.right < 0) {
            hr = false;
            if (visitLeaf(r, ~nd.right, nd.rcount, tmin, hit) && any) { done = true; break; }
        }
#endif
        hl = hl && tl <= hit.t;
        hr = hr && tr <= hit.t;
        if (hl && hr) {
            bool leftFirst = tl <= tr;
            stackNode[sp] = leftFirst ? nd.right : nd.left;
            stackT[sp] = leftFirst ? tr : tl;
            sp = min(sp + 1, STACK_SIZE - 1);
            ni = leftFirst ? nd.left : nd.right;
        } else if (hl) {
            ni = nd.left;
        } else if (hr) {
            ni = nd.right;
        } else {
            bool found = false;
            while (sp > 0) {
                --sp;
                if (stackT[sp] <= hit.t) { ni = stackNode[sp]; found = true; break; }
            }
            if (!found) {  // this subtree is done: the next entered root
                ni = nextRoot(rootOwn, rootKept, itemBase, keptBase);
                if (ni < 0) break;
            }
        }
    }
#ifdef CHC_COUNT_ITEMS
    // the query counts of the entered items' pairs, out of the loops above (see handOver)
    while (enteredMask != 0u) {
        int i = findLSB(enteredMask);
        enteredMask &= enteredMask - 1u;
        int slot = loadItem(itemBase + i).p2;  // (chcrt_pass_gpu.py _due_slots; -1: not counted)
        if (slot >= 0) atomicAdd(chcPassed[slot], 1u);
    }
    while (keptMask != 0u) {  // a kept pair entered before the ray's final nearest hit
        int i = findLSB(keptMask);
        keptMask &= keptMask - 1u;
        ChcItem it = loadItem(keptBase + i);
        float te;
        if (it.p2 >= 0 && (handOver || intersectBox(r, it.bmin, it.bmax, tmin, hit.t, te))) atomicAdd(chcPassed[it.p2], 1u);
    }
#endif
#if RESUMABLE
    if (handOver) {
        if (imageAtomicExchange(resumeSlot, px, -2) != -2) atomicAdd(unfinished, 1);
        done = true;  // traced again from the root: the leaf cache needs no flush
    }
#endif
    if (!done && flushLeaves(r, tmin, hit) && any) done = true;  // the leaf cache's last leaves
#ifdef COUNT_WORK
    atomicAdd(workTotals[8], entered);
#endif
}

// The scheduled subtree (canonical node id) of a record's items that holds triangle `id`, -1 if none
// (the subtree_id overlay).
int subtreeOfHit(int id, int itemBase, int itemCount, int keptBase, int keptCount) {
    int sub = -1;
    for (int i = 0; i < itemCount + keptCount; ++i) {
        ChcItem it = loadItem(i < itemCount ? itemBase + i : keptBase + i - itemCount);
        if (id >= it.p0 && id < it.p0 + it.p1) sub = it.id;
    }
    return sub;
}

// What a record's fragment adds to the overlays for its pixel: its subtrees (subtree batches) and, for a
// query record (`query` != 0) or merged kept pairs, one query test per pair (query overdraw).
void countRecordOverlays(ivec2 px, int itemCount, int keptCount, int query) {
    if (countOverlays == 0) return;
    imageAtomicAdd(batchSubtrees, px, itemCount + keptCount);
#ifdef CHC_COUNT_ITEMS
    if (query != 0 || keptCount > 0) imageAtomicAdd(overdraw, px, query != 0 ? itemCount : keptCount);
#endif
}

#ifdef CHC_COUNT_ITEMS
// gap_order: the record's nearest item (with merged kept pairs: the nearer of the two lists' first
// items) lies beyond `reach` (the ray's nearest hit so far, t * |d| with the gap's margin): nothing
// in it can be entered before that hit (nor hit: a hint triangle lies in some subtree of the tile's
// cut)
bool recordBeyond(int itemBase, int itemCount, int keptBase, int keptCount, float reach) {
    const float inf = uintBitsToFloat(0x7f800000u);
    float firstGap = min(itemCount > 0 ? loadItem(itemBase).gap : inf, keptCount > 0 ? loadItem(keptBase).gap : inf);
    return gapOrder != 0 && (itemCount + keptCount == 0 || firstGap > reach);
}
#endif

// hit hint (ChcrtParams.hit_hint; Haines & Greenberg's shadow cache, for every ray type): the
// triangle this pixel's ray hit in the front's previous pass is tested first, while the pixel has
// no hit yet (`fresh`). A hit there is a real hit: an any-hit ray is done (true), a closest-hit ray
// traverses with that distance as tmax (exact: the traversal still finds anything nearer)
bool testHint(ivec2 px, bool fresh, RayPre r, float tmin, bool any, inout Hit hit) {
    if (useHint == 0 || !fresh) return false;
    int h = texelFetch(hintId, px, 0).r;
    return h >= 0 && intersectSlot(r, h, tmin, hit) && any;
}

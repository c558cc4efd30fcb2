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
#include "chc_common.glsl"
#include "chc_leafcache.glsl"
uniform int anyHit;
uniform int countOverlays;
#ifdef CHC_COUNT_ITEMS
uniform int gapOrder;  // ChcrtParams.gap_order: every record's items sorted by gap
#endif
uniform int useHint;  // 1: hintId holds last pass's hit triangle per pixel (leaf-order slot, -1 = none)
uniform isampler2D hintId;
layout(location = 0) out float outT;
layout(location = 1) out int outId;
layout(location = 2) out int outSub;
#if CHC_MAX_ITEMS > 32
#error "chc_intersect.frag: at most 32 items per record (enteredMask)"
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
#ifdef CHC_MERGE_KEPT  // (chcrt.py sets it for the counting intersection only)
#ifndef CHC_COUNT_ITEMS
#error "chc_intersect.frag: CHC_MERGE_KEPT needs CHC_COUNT_ITEMS"
#endif
flat in int vKeptBase;
flat in int vKeptCount;
#define KEPT_BASE vKeptBase
#define KEPT_COUNT vKeptCount
#else
#define KEPT_BASE 0
#define KEPT_COUNT 0  // without merge_kept the loops below are the record's own items only
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

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    if (countOverlays != 0) imageAtomicAdd(batchSubtrees, px, ITEM_COUNT + KEPT_COUNT);
#ifdef CHC_COUNT_ITEMS
    // a query record (invisible pairs tested by intersecting them), or merged kept pairs: one query
    // test per pair
    if (countOverlays != 0 && (vQuery != 0 || KEPT_COUNT > 0)) imageAtomicAdd(overdraw, px, vQuery != 0 ? ITEM_COUNT : KEPT_COUNT);
#endif
    int best = imageLoad(bestBits, px).r;
    if (best < 0) discard;
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
#ifdef CHC_COUNT_ITEMS
    // gap_order: the record's nearest item lies beyond the ray's nearest hit: nothing here can be
    // entered before it (nor hit: a hint triangle lies in some subtree of the tile's cut), so the
    // ray set-up is skipped too (most invisible pairs' fragments of primary rays)
    // (with merged kept pairs: the nearer of the two lists' first items)
    float dlen = length(dt.xyz) * (1.0 + 1e-4);
    const float inf = uintBitsToFloat(0x7f800000u);
    float firstGap = min(ITEM_COUNT > 0 ? loadItem(ITEM_BASE).gap : inf, KEPT_COUNT > 0 ? loadItem(KEPT_BASE).gap : inf);
    if (gapOrder != 0 && (ITEM_COUNT + KEPT_COUNT == 0 || firstGap > min(intBitsToFloat(best), dt.w) * dlen)) discard;
#endif
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float tmin = ot.w;
    bool any = anyHit != 0;
    Hit hit = Hit(min(intBitsToFloat(best), dt.w), -1);
    // hit hint (ChcrtParams.hit_hint; Haines & Greenberg's shadow cache, for every ray type): the
    // triangle this pixel's ray hit in the front's previous pass is tested first, while the pixel has
    // no hit yet. A hit there is a real hit: an any-hit ray is done, a closest-hit ray traverses with
    // that distance as tmax (exact: the traversal still finds anything nearer)
    bool done = false;
    if (useHint != 0 && best == floatBitsToInt(dt.w)) {
        int h = texelFetch(hintId, px, 0).r;
        if (h >= 0 && intersectSlot(r, h, tmin, hit)) done = any;
    }
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
    const float dlen = 0.0;
#endif
    // the record's items, then its merged kept pairs (GPU-driven builds only): one loop, one set of masks
    int total = ITEM_COUNT + KEPT_COUNT;
    for (int k = done ? total : 0; k < total; ++k) {
        bool own = KEPT_COUNT == 0 || k < ITEM_COUNT;  // (a constant without merge_kept: the loop folds to the own items')
        // (an any-hit ray finished by its hint tests no item; one finished later, in a leaf or the
        // traversal, counts the kept pairs it entered before that hit)
        int i = own ? k : k - ITEM_COUNT;
        ChcItem it = loadItem(own ? ITEM_BASE + i : KEPT_BASE + i);
        if (byGap && it.gap > hit.t * dlen) {
            if (!own || KEPT_COUNT == 0) break;
            k = ITEM_COUNT - 1;  // on with the kept pairs
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
        ChcItem it = loadItem(o ? ITEM_BASE + i : KEPT_BASE + i);
        if (visitLeaf(r, it.ref, it.count, tmin, hit) && any) done = true;
    }
    if (done) { rootOwn = 0u; rootKept = 0u; }
    int ni = nextRoot(rootOwn, rootKept, ITEM_BASE, KEPT_BASE);
    int visits = 0;
    bool handOver = false;
    while (ni >= 0) {
        // the loop limit is near: finish this ray elsewhere (the atomics after the loop: llvmpipe
        // runs a branch's code under a lane mask even when no lane takes it, so nothing heavy is
        // written inside this loop)
        if (visits == CHC_MAX_VISITS) { handOver = true; break; }
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
                ni = nextRoot(rootOwn, rootKept, ITEM_BASE, KEPT_BASE);
                if (ni < 0) break;
            }
        }
    }
#ifdef CHC_COUNT_ITEMS
    // the query counts of the entered items' pairs, out of the loops above (see handOver)
    while (enteredMask != 0u) {
        int i = findLSB(enteredMask);
        enteredMask &= enteredMask - 1u;
        int slot = loadItem(ITEM_BASE + i).p2;  // (chcrt_pass_gpu.py _due_slots; -1: not counted)
        if (slot >= 0) atomicAdd(chcPassed[slot], 1u);
    }
    while (keptMask != 0u) {  // a kept pair entered before the ray's final nearest hit
        int i = findLSB(keptMask);
        keptMask &= keptMask - 1u;
        ChcItem it = loadItem(KEPT_BASE + i);
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
    workFlushPixel(0, px);
#ifdef COUNT_WORK
    atomicAdd(workTotals[8], entered);
#endif
#ifdef WORK_PROBE
    // one unit per box and triangle test, and one for the fragment (its ray set-up)
    if (probePixel(px, probeStride)) atomicAdd(chcMeta[probeBase], int(workBox + workTri) + 1);
#endif
    if (hit.id < 0) discard;
#ifdef CHC_OOC
    hit.id = tris[hit.id].id;  // out-of-core: cache slot -> the triangle's leaf-order slot
#endif
    // the scheduled subtree that holds the hit triangle (for the subtree_id overlay)
    int sub = -1;
    for (int i = 0; i < (countOverlays != 0 ? ITEM_COUNT + KEPT_COUNT : 0); ++i) {
        ChcItem it = loadItem(i < ITEM_COUNT ? ITEM_BASE + i : KEPT_BASE + i - ITEM_COUNT);
        if (hit.id >= it.p0 && hit.id < it.p0 + it.p1) sub = it.id;
    }
    outT = hit.t;
    outId = hit.id;
    outSub = sub;
    if (any) {
        imageAtomicMin(bestBits, px, -1);
        gl_FragDepth = 0.0;
    } else {
        imageAtomicMin(bestBits, px, floatBitsToInt(hit.t));
        gl_FragDepth = chcKey(hit.t);
    }
}

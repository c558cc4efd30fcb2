// CHC+RT intersection, the compute stage (ChcrtParams.visible_stage = compute): the visible records
// of a device front's GPU-driven pass, one invocation per pixel (work groups of 8x8 pixels) instead of
// one fragment per (record, pixel). The invocation finds its finest tile's plan (chc_front_plan.comp
// wrote its records, in tile order), sets its ray up once, and runs the tile's records in their
// order (chc_intersect_record.glsl, as the fragment stage does), the nearest hit so far carried from
// record to record. Why: a GPU may run compute shaders on many more of its processors than
// fragment shaders (an NVIDIA H100/H200 has its graphics pipeline on a few), and a pixel's ray is
// fetched, set up and tested against its hint once, not once per record.
// Output: 3 words per pixel (row-major) in VisHits: t's bits, the triangle id (-1: no hit found
// here), the scheduled subtree that holds it (overlay); chc_visible_resolve.frag writes them through
// the depth test, as the fragment stage's draw would. bestBits takes the hit as in that stage.
// Loop limit (RESUMABLE): the records of one invocation share llvmpipe's back-edge budget, so each
// record first charges CHC_RECORD_VISITS node visits' worth of its item loops to `visits`
// (chcrt.py), and the ray is handed over once CHC_MAX_VISITS is reached, as in one record.
// keptAfter (chc_querycull.comp mergeAll): the kept invisible pairs the cull did not merge into a tile's
// last record come after its records, in chunks of keptChunk (the survivors' records), so that no pair is
// left to a fragment draw: a device cold start's young front has only such pairs.
#undef CHC_BATCHED  // (the records are read here: no instanced draw hands them over as vertex outputs)
#include "chc_intersect_record.glsl"
#include "chc_front.glsl"
#ifndef CHC_COUNT_ITEMS
#error "chc_visible.comp: the counting intersection's build (CHC_COUNT_ITEMS)"
#endif
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = BIND_FR_TILES) readonly buffer TilePlans { ChcTilePlan plans[]; };
layout(std430, binding = BIND_CHC_DRAWS) readonly buffer ChcDraws { ChcDraw draws[]; };
layout(std430, binding = BIND_CHC_VIS_HITS) writeonly buffer VisHits { uint visHits[]; };
uniform ivec2 raySize;
uniform int maxLevel;   // the finest tiles' quadtree level (tile = ty * 2^level + tx)
uniform int mergeKept;  // 1: a tile's last record carries its merged kept pairs (chc_querycull.comp)
uniform int keptAfter;  // 1 (with mergeKept): a tile's kept range that its last record does not carry is traced
                        // after its records, in chunks of keptChunk items, as the survivors' records would be
uniform int keptChunk;  // (chc_querycull.comp mergeAll; = its maxItems)
#ifndef CHC_RECORD_VISITS
#define CHC_RECORD_VISITS 0
#endif

// the finest tile holding pixel coordinate x of an image `size` wide (tileRect's inverse: tile t
// covers [(t * size) >> level, ((t + 1) * size) >> level))
int tileOf(int x, int size, int level) { return (((x + 1) << level) - 1) / size; }

void main() {
    ivec2 px = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(px, raySize))) return;
    int w = 3 * (px.y * raySize.x + px.x);
    int side = 1 << maxLevel;
    ChcTilePlan tp = plans[tileOf(px.y, raySize.y, maxLevel) * side + tileOf(px.x, raySize.x, maxLevel)];
    int r0 = tp.recBase, r1 = tp.recBase + tp.nrec;
    // the overlays count every record's subtrees at every pixel of it, as its fragments do
    // kept pairs ride in the tile's last record where the cull merged them into it (a tile with records
    // and at most keptChunk kept pairs, chc_querycull.comp), else they come after the records (keptAfter),
    // in the order in which the fragment stage's survivors' draw would trace them: the same hits, also
    // the same occluder for any-hit rays
    bool carried = mergeKept != 0 && (keptAfter == 0 || (tp.nrec >= 1 && tp.keptCount <= keptChunk));
    int nk = mergeKept != 0 && !carried ? tp.keptCount : 0;
    int chunk = max(keptChunk, 1);  // (a loop step of 0 would never end)
    for (int k = r0; k < (countOverlays != 0 ? r1 : r0); ++k) {
        bool kept = carried && keptCarrier(tp, k);
        countRecordOverlays(px, draws[k].info.y, kept ? tp.keptCount : 0, 0);
    }
    for (int b = 0; b < (countOverlays != 0 ? nk : 0); b += chunk) countRecordOverlays(px, min(chunk, nk - b), 0, 1);
    int best = imageLoad(bestBits, px).r;
    visHits[w + 1] = uint(-1);
    if (best < 0 || (r0 == r1 && nk == 0)) return;
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    float dlen = length(dt.xyz) * (1.0 + 1e-4);
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float tmin = ot.w;
    bool any = anyHit != 0;
    Hit hit = Hit(min(intBitsToFloat(best), dt.w), -1);
    bool done = testHint(px, best == floatBitsToInt(dt.w), r, tmin, any, hit);
    int visits = 0;
    for (int k = r0; k < r1 && !done; ++k) {
        ChcDraw d = draws[k];
        int kb = 0, kc = 0;
        if (carried && keptCarrier(tp, k)) { kb = tp.keptBase; kc = tp.keptCount; }
        if (recordBeyond(d.info.x, d.info.y, kb, kc, hit.t * dlen)) continue;
#if RESUMABLE
        if (visits + CHC_RECORD_VISITS > CHC_MAX_VISITS) {  // the budget cannot take this record's loops:
            // the ray is traced again from the root after the pass (the pairs of the records left
            // out count nothing for it: the front may refine less, the hits stay exact)
            if (imageAtomicExchange(resumeSlot, px, -2) != -2) atomicAdd(unfinished, 1);
            break;
        }
#endif
        visits += CHC_RECORD_VISITS;
        intersectRecord(px, d.info.x, d.info.y, kb, kc, r, tmin, dlen, any, hit, done, visits);
    }
    for (int b = 0; b < nk && !done; b += chunk) {  // (sorted by gap across the tile: a chunk beyond
        int m = min(chunk, nk - b);                   // the nearest hit leaves the rest beyond it too)
        if (recordBeyond(tp.keptBase + b, m, 0, 0, hit.t * dlen)) break;
#if RESUMABLE
        if (visits + CHC_RECORD_VISITS > CHC_MAX_VISITS) {
            if (imageAtomicExchange(resumeSlot, px, -2) != -2) atomicAdd(unfinished, 1);
            break;
        }
#endif
        visits += CHC_RECORD_VISITS;
        intersectRecord(px, tp.keptBase + b, m, 0, 0, r, tmin, dlen, any, hit, done, visits);
    }
    workFlushPixel(0, px);
#ifdef WORK_PROBE
    // one unit per box and triangle test, and one for the invocation (its ray set-up)
    if (probePixel(px, probeStride)) atomicAdd(chcMeta[probeBase], int(workBox + workTri) + 1);
#endif
    if (hit.id < 0) return;
#ifdef CHC_OOC
    hit.id = tris[hit.id].id;  // out-of-core: cache slot -> the triangle's leaf-order slot
#endif
    int sub = -1;
    for (int k = r0; k < (countOverlays != 0 ? r1 : r0); ++k) {
        bool kept = carried && keptCarrier(tp, k);
        int s = subtreeOfHit(hit.id, draws[k].info.x, draws[k].info.y, kept ? tp.keptBase : 0, kept ? tp.keptCount : 0);
        if (s >= 0) sub = s;
    }
    if (countOverlays != 0 && nk > 0) {
        int s = subtreeOfHit(hit.id, tp.keptBase, nk, 0, 0);
        if (s >= 0) sub = s;
    }
    imageAtomicMin(bestBits, px, any ? -1 : floatBitsToInt(hit.t));
    visHits[w] = floatBitsToUint(hit.t);
    visHits[w + 1] = uint(hit.id);
    visHits[w + 2] = uint(sub);
}

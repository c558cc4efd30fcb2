// CHC+RT intersection, the fragment stage: one fragment per (record, pixel) of an instanced draw of
// rectangles (chc_tile.vert; a scissored full-screen draw in the synchronous passes). The method and
// its loops: chc_intersect_record.glsl. The hit is output through the depth test (LESS on key(t)),
// so only a hit nearer than the pixel's current one is written; an any-hit ray writes depth 0 and is
// finished.
#include "chc_intersect_record.glsl"
layout(location = 0) out float outT;
layout(location = 1) out int outId;
layout(location = 2) out int outSub;
#ifdef CHC_MERGE_KEPT  // (chcrt.py sets it for the counting intersection only)
flat in int vKeptBase;
flat in int vKeptCount;
#define KEPT_BASE vKeptBase
#define KEPT_COUNT vKeptCount
#else
#define KEPT_BASE 0
#define KEPT_COUNT 0  // without merge_kept the loops are the record's own items only
#endif
#ifdef CHC_BATCHED
#define QUERY vQuery
#else
#define QUERY 0
#endif

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    countRecordOverlays(px, ITEM_COUNT, KEPT_COUNT, QUERY);
    int best = imageLoad(bestBits, px).r;
    if (best < 0) discard;
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
#ifdef CHC_COUNT_ITEMS
    // gap_order: nothing of this record can be entered before the ray's nearest hit so far, so the
    // ray set-up is skipped too (most invisible pairs' fragments of primary rays)
    float dlen = length(dt.xyz) * (1.0 + 1e-4);
    if (recordBeyond(ITEM_BASE, ITEM_COUNT, KEPT_BASE, KEPT_COUNT, min(intBitsToFloat(best), dt.w) * dlen)) discard;
#else
    const float dlen = 0.0;
#endif
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float tmin = ot.w;
    bool any = anyHit != 0;
    Hit hit = Hit(min(intBitsToFloat(best), dt.w), -1);
    bool done = testHint(px, best == floatBitsToInt(dt.w), r, tmin, any, hit);
    int visits = 0;
    intersectRecord(px, ITEM_BASE, ITEM_COUNT, KEPT_BASE, KEPT_COUNT, r, tmin, dlen, any, hit, done, visits);
    workFlushPixel(0, px);
#ifdef WORK_PROBE
    // one unit per box and triangle test, and one for the fragment (its ray set-up)
    if (probePixel(px, probeStride)) atomicAdd(chcMeta[probeBase], int(workBox + workTri) + 1);
#endif
    if (hit.id < 0) discard;
#ifdef CHC_OOC
    hit.id = tris[hit.id].id;  // out-of-core: cache slot -> the triangle's leaf-order slot
#endif
    outT = hit.t;
    outId = hit.id;
    outSub = countOverlays != 0 ? subtreeOfHit(hit.id, ITEM_BASE, ITEM_COUNT, KEPT_BASE, KEPT_COUNT) : -1;
    if (any) {
        imageAtomicMin(bestBits, px, -1);
        gl_FragDepth = 0.0;
    } else {
        imageAtomicMin(bestBits, px, floatBitsToInt(hit.t));
        gl_FragDepth = chcKey(hit.t);
    }
}

// CHC+RT generalized occlusion query: the pixels of a tile intersect their rays with a list of
// boxes (a pair's two child boxes, or all boxes of a multi-query); the fragment survives with depth
// = depth(nearest entry) if some box is entered before tmax, and the depth test (LESS against
// key(best t)) keeps it only if that entry is not beyond the nearest hit found so far. A
// samples-passed query counts the rays that may still hit the pair.
//
// Batched mode (CHC_BATCHED, chc_tile.vert): many queries in one instanced draw; each fragment does
// the depth test's comparison itself against bestBits (the same key: depth(entry) <= depth(best t))
// and counts into its query's slot of chcPassed. bestBits may be stale by the writes of draws still
// in flight; it only ever decreases within a pass, so a stale value can only make a query pass more
// (conservative: more work, never a missed hit). A passing fragment also widens its query's
// bounds per box (min x, min y, max x, max y of the pixels whose ray enters the box before its
// nearest hit; 8 slots per query from boundsBase: the first box, then all others): a descendant
// pair queries boxes inside one of this query's boxes, so only pixels that passed that box here can
// pass there (chcrt_pass_sync.py draws the children's queries over these bounds only).
#include "chc_common.glsl"
uniform int countOverdraw;
#ifdef CHC_BATCHED
layout(std430, binding = BIND_CHC_QUERY_COUNTS) buffer ChcQueryCounts { uint chcPassed[]; };
uniform int boundsBase;
#endif
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    if (countOverdraw != 0) imageAtomicAdd(overdraw, px, 1);
    int best = imageLoad(bestBits, px).r;
    if (best < 0) discard;  // no ray, or an any-hit ray that is done
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float entry = uintBitsToFloat(0x7f800000u);
    bool any = false;
#ifdef CHC_BATCHED
    float bestDepth = chcDepth(intBitsToFloat(best));
    uint passedBoxes = 0u;  // bit 0: the first box, bit 1: any other
#endif
    for (int i = 0; i < ITEM_COUNT; ++i) {
        ChcItem it = loadItem(ITEM_BASE + i);
        float te;
        if (intersectBox(r, it.bmin, it.bmax, ot.w, dt.w, te)) {
            entry = min(entry, te);
            any = true;
#ifdef CHC_BATCHED
            if (chcDepth(te) <= bestDepth) passedBoxes |= (i == 0) ? 1u : 2u;
#endif
        }
    }
    workFlush(4);
    if (!any) discard;
#ifdef CHC_BATCHED
    // the depth test's pass condition (depth of the nearest entry <= depth of the best hit) holds
    // exactly when some box passes (chcDepth is monotone)
    if (passedBoxes != 0u) {
        atomicAdd(chcPassed[vQuery], 1u);
        for (int k = 0; k < 2; ++k) {
            if ((passedBoxes & (1u << k)) == 0u) continue;
            int b = boundsBase + 8 * vQuery + 4 * k;
            atomicMin(chcPassed[b], uint(px.x));
            atomicMin(chcPassed[b + 1], uint(px.y));
            atomicMax(chcPassed[b + 2], uint(px.x));
            atomicMax(chcPassed[b + 3], uint(px.y));
        }
    }
#else
    gl_FragDepth = chcDepth(entry);
#endif
}

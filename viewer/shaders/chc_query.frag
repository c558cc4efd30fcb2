// CHC+RT generalized occlusion query: the pixels of a tile intersect their rays with a list of
// boxes (a pair's two child boxes, or all boxes of a multi-query); the fragment survives with depth
// = depth(nearest entry) if some box is entered before tmax, and the depth test (LESS against
// key(best t)) keeps it only if that entry is not beyond the nearest hit found so far. A
// samples-passed query counts the rays that may still hit the pair.
#include "chc_common.glsl"
uniform int countOverdraw;
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    if (countOverdraw != 0) imageAtomicAdd(overdraw, px, 1);
    if (imageLoad(bestBits, px).r < 0) discard;  // no ray, or an any-hit ray that is done
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float entry = uintBitsToFloat(0x7f800000u);
    bool any = false;
    for (int i = 0; i < itemCount; ++i) {
        ChcItem it = items[itemBase + i];
        float te;
        if (intersectBox(r, it.bmin, it.bmax, ot.w, dt.w, te)) {
            entry = min(entry, te);
            any = true;
        }
    }
    if (!any) discard;
    gl_FragDepth = chcDepth(entry);
}

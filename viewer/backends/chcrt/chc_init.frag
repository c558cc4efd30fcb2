// CHC+RT: start of a pass. Clears the hit buffer and the subtree overlay (colour outputs), the
// overdraw and batch overlays (while overlays are on) and bestBits (images), sets the depth
// (1 = active ray, 0 = no ray) and counts active rays.
#include "chc_common.glsl"
layout(std430, binding = BIND_CHC_COUNT) buffer ChcCount { uint chcActive[]; };
uniform int countOverlays;  // the overlay images are only written (and so cleared) while overlays are on
layout(location = 0) out float outT;
layout(location = 1) out int outId;
layout(location = 2) out int outSub;
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    bool live = dt.w > ot.w;
    outT = uintBitsToFloat(0x7f800000u);
    outId = -1;
    outSub = -1;
    if (countOverlays != 0) {
        imageStore(overdraw, px, ivec4(0));
        imageStore(batchSubtrees, px, ivec4(0));
    }
    imageStore(bestBits, px, ivec4(live ? floatBitsToInt(dt.w) : -1));
    gl_FragDepth = live ? 1.0 : 0.0;
    if (live) atomicAdd(chcActive[(px.x & 7) + 8 * (px.y & 7)], 1u);
}

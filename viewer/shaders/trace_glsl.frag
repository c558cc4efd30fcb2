// The "GLSL" baseline (CHC+RT Table 2): every ray traverses the whole BVH from the root.
#include "scene.glsl"
#include "intersect.glsl"
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform int anyHit;
layout(location = 0) out float outT;
layout(location = 1) out int outId;
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    outT = uintBitsToFloat(0x7f800000u);
    outId = -1;
    if (dt.w > ot.w) {
        Hit h = Hit(dt.w, -1);
        traverseBVH(prepareRay(ot.xyz, dt.xyz), 0, ot.w, anyHit != 0, h);
        if (h.id >= 0) { outT = h.t; outId = h.id; }
        workFlush(0);
    }
}

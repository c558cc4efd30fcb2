// The compute stage's visible hits (chc_visible.comp's VisHits) into the hit framebuffer, through the
// depth test (LESS on key(t); an any-hit ray's depth 0), as the fragment stage's records would have
// written them; a pixel without a hit there keeps what it has.
#include "chc_common.glsl"
layout(std430, binding = BIND_CHC_VIS_HITS) readonly buffer VisHits { uint visHits[]; };
uniform int anyHit;
uniform int width;
layout(location = 0) out float outT;
layout(location = 1) out int outId;
layout(location = 2) out int outSub;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int w = 3 * (px.y * width + px.x);
    int id = int(visHits[w + 1]);
    if (id < 0) discard;
    float t = uintBitsToFloat(visHits[w]);
    outT = t;
    outId = id;
    outSub = int(visHits[w + 2]);
    gl_FragDepth = anyHit != 0 ? 0.0 : chcKey(t);
}

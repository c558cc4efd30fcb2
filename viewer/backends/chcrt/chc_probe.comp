// CHC+RT work probe, the baseline's side (chcrt_pass_device.py, ChcrtParams.work_probe): the rays of the sampled
// pixels (chc_probe.glsl) traverse the whole BVH as the full-BVH pass would (traverseBVH: the glsl
// backend's order), and their box and triangle tests (plus one per ray, its set-up) and their
// number are added to the front's META row. Nothing else is written; one invocation per sampled
// pixel.
layout(local_size_x = 64) in;
#ifndef WORK_PROBE
#define WORK_PROBE 1  // intersect.glsl's per-invocation work counts
#endif
#include "scene.glsl"
#include "intersect.glsl"
#include "chc_probe.glsl"
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform ivec2 raySize;
uniform int probeStride;
uniform int probeBase;  // META index of the front's META_PROBE_FRONT: FULL and RAYS follow it
uniform int anyHit;
layout(std430, binding = BIND_FR_META) buffer ChcMeta { int chcMeta[]; };

void main() {
    ivec2 px = probePixelAt(int(gl_GlobalInvocationID.x), raySize.x, probeStride);
    if (px.x >= raySize.x || px.y >= raySize.y) return;
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    if (!(dt.w > ot.w)) return;  // no ray here (tmax <= tmin)
    Hit hit = Hit(dt.w, -1);
    traverseBVH(prepareRay(ot.xyz, dt.xyz), 0, ot.w, anyHit != 0, hit);
    atomicAdd(chcMeta[probeBase + 1], int(workBox + workTri) + 1);
    atomicAdd(chcMeta[probeBase + 2], 1);
}

// Turns one pass of traced rays into a contribution, added (blend ONE, ONE) to the effect's
// accumulator. Uses the same shading formula for every backend, so images differ only where hits do.
#include "scene.glsl"
#include "sampling.glsl"
#include "lighting.glsl"

#define ACC_SHADOW 1
#define ACC_SOFT 2
#define ACC_AO 3
#define ACC_DIFFUSE 4
#define ACC_REFLECT 5

// One program per effect (ACC_EFFECT = the ray type, passes/accumulate.py): with a uniform, a SIMD
// driver that runs both sides of a branch on a uniform (llvmpipe) shaded every effect for every
// pixel (an AO pass paid for the diffuse bounce's shading: 5.5x the time on llvmpipe).
#ifndef ACC_EFFECT
#error "accumulate.frag: ACC_EFFECT (the ray type, viewer.effects.RayType) must be defined"
#endif
const int effect = ACC_EFFECT;
uniform int lightIndex;
uniform float weight;
uniform sampler2D gPos;
uniform sampler2D gNormal;
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform sampler2D hitT;
uniform isampler2D hitId;
out vec4 outAcc;

const float LIGHT_EPS = 1e-4;

vec3 radianceAlong(vec3 o, vec3 d, float t, int id) {
    if (id < 0) return skyColor * ambient;
    vec3 p = o + d * t;
    vec3 n = triNormal(id);
    if (dot(n, d) > 0.0) n = -n;
    return shadeSecondaryHit(p, n, materials[loadTri(id).mat].rgb);
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    if (!(dt.w > ot.w)) { outAcc = vec4(0.0); return; }
    float t = texelFetch(hitT, px, 0).r;
    int id = texelFetch(hitId, px, 0).r;
    float vis = id < 0 ? 1.0 : 0.0;
    vec3 p = texelFetch(gPos, px, 0).xyz;
    vec3 n = texelFetch(gNormal, px, 0).xyz;
    if (effect == ACC_SHADOW) {
        outAcc = vec4(pointIrradiance(lightIndex, p, n) * vis, vis) * weight;
    } else if (effect == ACC_SOFT) {
        vec3 q = ot.xyz + dt.xyz * (dt.w / (1.0 - LIGHT_EPS));
        outAcc = vec4(rectSampleIrradiance(lightIndex, q, p, n) * vis, vis) * weight;
    } else if (effect == ACC_AO) {
        outAcc = vec4(vis) * weight;
    } else {
        outAcc = vec4(radianceAlong(ot.xyz, dt.xyz, t, id), 1.0) * weight;
    }
}

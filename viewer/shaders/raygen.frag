// One ray per pixel per pass, written as (origin, tmin) and (direction, tmax); tmax < 0 = no ray.
// Secondary rays start at the exact ray/triangle hit of the pixel's primary ray (recomputed from
// the G-buffer triangle id) moved off the surface by a few ulps (scale-independent).
#include "scene.glsl"
#include "camera.glsl"
#include "intersect.glsl"
#include "sampling.glsl"
#include "lighting.glsl"

#define RAY_PRIMARY 0
#define RAY_SHADOW 1
#define RAY_SOFT 2
#define RAY_AO 3
#define RAY_DIFFUSE 4
#define RAY_REFLECT 5

// One program per ray type (RAY_TYPE = viewer.effects.RayType, passes/raygen.py): with a uniform,
// a SIMD driver that runs both sides of a branch on a uniform (llvmpipe) ran every type's code for
// every pixel, the secondary rays' triangle test in the camera rays' pass too.
#ifndef RAY_TYPE
#error "raygen.frag: RAY_TYPE (the ray type, viewer.effects.RayType) must be defined"
#endif
const int rayType = RAY_TYPE;
uniform int lightIndex;
uniform vec2 sampleUV;      // this pass's Halton point, shared by every pixel
uniform float perturbAngle; // radians, per-pixel random rotation of at most this angle
uniform float rayLength;    // AO / diffuse ray length
uniform uint stream;        // decorrelates the per-pixel random numbers of different ray types
uniform isampler2D gId;

uniform int countSlot;      // this pass's active-ray counter (passes/raygen.py RayGenPass)
layout(std430, binding = BIND_COUNTERS) buffer Counters { uint counters[]; };
layout(location = 0) out vec4 outOrigin;
layout(location = 1) out vec4 outDir;

const float LIGHT_EPS = 1e-4;  // shadow rays stop this fraction short of the light

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec3 dPrim = primaryDir(gl_FragCoord.xy);
    vec3 o = camPos, d = dPrim;
    float tmin = 0.0, tmax = -1.0;
    if (rayType == RAY_PRIMARY) {
        tmax = 1e30;
    } else {
        int id = texelFetch(gId, px, 0).r;
        if (id >= 0) {
            Tri tri = loadTri(id);
            // (a sliver whose float cross product vanishes has no normal here: any plane through the
            // hit point serves, and one facing the viewer keeps the offset and the rays defined)
            vec3 c = cross(tri.v1 - tri.v0, tri.v2 - tri.v0);
            float cl = length(c);
            vec3 n = cl > 0.0 && !isinf(cl) ? normalize(c) : -dPrim;  // (normalize: the bits as before)
            float tHit; vec2 b;
            precise vec3 p;  // no fused multiply-adds (docs/numerics.md)
            if (intersectTriangle(prepareRay(camPos, dPrim), tri.v0, tri.v1, tri.v2, 0.0, 1e30, tHit, b)) {
                p = tri.v0 * (1.0 - b.x - b.y) + tri.v1 * b.x + tri.v2 * b.y;
            } else {  // pixel centre covered by rasterization but on the far side of an edge
                p = camPos + dPrim * divRounded(dotPrecise(tri.v0 - camPos, n), dotPrecise(dPrim, n));
            }
            if (dot(n, dPrim) > 0.0) n = -n;  // face the viewer
            precise vec3 po = offsetRayOrigin(p, n);
            vec2 rnd = pixelRandom2(px, stream);
            if (rayType == RAY_SHADOW) {
                vec3 l = pointPos[lightIndex] - po;
                float dist = length(l);
                if (dot(l, n) > 0.0 && dist > 0.0) { o = po; d = l / dist; tmax = dist * (1.0 - LIGHT_EPS); }
            } else if (rayType == RAY_SOFT) {
                float shift = perturbAngle / PI;  // toroidal shift of the shared sample, per pixel
                vec2 uv = fract(sampleUV + (rnd - 0.5) * shift);
                vec3 q = rectCorner[lightIndex] + uv.x * rectU[lightIndex] + uv.y * rectV[lightIndex];
                vec3 nl = cross(rectU[lightIndex], rectV[lightIndex]);
                vec3 l = q - po;
                float dist = length(l);
                if (dot(l, n) > 0.0 && dot(nl, -l) > 0.0 && dist > 0.0) {
                    o = po; d = l / dist; tmax = dist * (1.0 - LIGHT_EPS);
                }
            } else if (rayType == RAY_AO || rayType == RAY_DIFFUSE) {
                vec3 t, bb;
                makeBasis(n, t, bb);
                vec3 local = cosineHemisphere(sampleUV);
                vec3 dir = perturbInCone(normalize(t * local.x + bb * local.y + n * local.z), perturbAngle, rnd);
                float c = dot(dir, n);
                if (c <= 0.0) dir = normalize(dir - 2.0 * c * n);
                o = po; d = dir; tmax = rayLength;
            } else if (rayType == RAY_REFLECT) {
                if (materials[tri.mat].a > 0.5) { o = po; d = normalize(reflect(dPrim, n)); tmax = 1e30; }
            }
        }
    }
    if (tmax > 0.0) atomicAdd(counters[countSlot], 1u);  // (tmin is 0: active = tmax > tmin)
    outOrigin = vec4(o, tmin);
    outDir = vec4(d, tmax);
}

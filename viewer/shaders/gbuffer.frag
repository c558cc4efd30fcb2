// The exact raster writes a visibility buffer: the triangle id and depth = f(distance), nothing
// else (4 colour bytes per fragment instead of 52; gbuffer_fill.frag with RESOLVE then writes
// position, normal and albedo once per pixel from the id). Coverage and depth come from the same
// watertight ray/triangle test the tracers use, applied to the pixel's primary ray (the geometry
// shader rasterizes conservatively), so the G-buffer agrees with a traced primary ray.
// PREVIEW (moving frames only): a plain raster without the geometry shader that writes every
// target itself: world position (w = distance along the primary ray), facing geometric normal,
// albedo (a = mirror flag), triangle id. The vertex shader passes the triangle id; the depth test
// uses the rasterizer's depth before the shader runs (early fragment tests: hidden fragments cost
// nothing), and the distance is the ray's to the triangle's plane, without the exact test (edge
// pixels may differ from a traced primary ray).
#include "scene.glsl"
#include "camera.glsl"
#include "intersect.glsl"
uniform float depthScale;
#ifdef PREVIEW
layout(location = 0) out vec4 outPos;
layout(location = 1) out vec4 outNormal;
layout(location = 2) out vec4 outAlbedo;
layout(location = 3) out int outId;
layout(early_fragment_tests) in;
flat in int vTri;
#else
layout(location = 0) out int outId;
flat in vec3 gV0, gV1, gV2;  // the triangle's vertices (gbuffer.geom: no SSBO load per fragment)
// the rasterized depth is the triangle's lower bound (gbuffer.geom depthLowerBound) and the depth
// written is never less, so the GL may test the bound before this shader runs
layout(depth_greater) out float gl_FragDepth;
#endif
void main() {
#ifdef PREVIEW
    int id = vTri;
#else
    int id = gl_PrimitiveID;
#endif
    vec3 d = primaryDir(gl_FragCoord.xy);
#ifdef PREVIEW
    Tri tri = loadTri(id);
    vec3 n = normalize(cross(tri.v1 - tri.v0, tri.v2 - tri.v0));
    float dn = dot(d, n);
    float t = dn != 0.0 ? max(dot(tri.v0 - camPos, n) / dn, 0.0) : 0.0;
    if (dot(d, n) > 0.0) n = -n;
    outPos = vec4(camPos + d * t, t);
    outNormal = vec4(n, 0.0);
    outAlbedo = materials[tri.mat];
    outId = id;
#else
    float t; vec2 b;
    if (!intersectTriangle(prepareRay(camPos, d), gV0, gV1, gV2, 0.0, 1e30, t, b)) discard;
    outId = id;
    gl_FragDepth = divRounded(t, t + depthScale);  // (correctly rounded: the same depths, so the same order, on every device)
#endif
}

// Writes world position (w = distance along the primary ray), facing geometric normal, albedo
// (a = mirror flag), triangle id, and depth = f(distance). Coverage and depth come from the same
// watertight ray/triangle test the tracers use, applied to the pixel's primary ray (the geometry
// shader rasterizes conservatively), so the G-buffer agrees with a traced primary ray.
#include "scene.glsl"
#include "camera.glsl"
#include "intersect.glsl"
uniform float depthScale;
layout(location = 0) out vec4 outPos;
layout(location = 1) out vec4 outNormal;
layout(location = 2) out vec4 outAlbedo;
layout(location = 3) out int outId;
void main() {
    int id = gl_PrimitiveID;
    Tri tri = tris[id];
    vec3 d = primaryDir(gl_FragCoord.xy);
    float t; vec2 b;
    if (!intersectTriangle(prepareRay(camPos, d), tri.v0, tri.v1, tri.v2, 0.0, 1e30, t, b)) discard;
    vec3 n = normalize(cross(tri.v1 - tri.v0, tri.v2 - tri.v0));
    if (dot(d, n) > 0.0) n = -n;
    outPos = vec4(camPos + d * t, t);
    outNormal = vec4(n, 0.0);
    outAlbedo = materials[tri.mat];
    outId = id;
    gl_FragDepth = t / (t + depthScale);
}

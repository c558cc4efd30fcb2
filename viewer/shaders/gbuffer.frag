// Writes world position (w = distance along the primary ray), facing geometric normal, albedo
// (a = mirror flag), triangle id, and depth = f(distance). Depth comes from the exact ray/plane
// distance of the pixel's primary ray, not the interpolated z, so near-coincident surfaces resolve
// as the ray tracers resolve them.
#include "scene.glsl"
#include "camera.glsl"
uniform float depthScale;
layout(location = 0) out vec4 outPos;
layout(location = 1) out vec4 outNormal;
layout(location = 2) out vec4 outAlbedo;
layout(location = 3) out int outId;
void main() {
    int id = gl_PrimitiveID;
    Tri tri = tris[id];
    vec3 d = primaryDir(gl_FragCoord.xy);
    vec3 n = normalize(cross(tri.v1 - tri.v0, tri.v2 - tri.v0));
    float denom = dot(d, n);
    float t = dot(tri.v0 - camPos, n) / denom;
    if (!(t > 0.0) || isinf(t)) t = 0.0;
    if (denom > 0.0) n = -n;
    outPos = vec4(camPos + d * t, t);
    outNormal = vec4(n, 0.0);
    outAlbedo = materials[tri.mat];
    outId = id;
    gl_FragDepth = t / (t + depthScale);
}

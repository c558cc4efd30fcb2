// The G-buffer from traced primary rays (the renderer's "trace" G-buffer source): per pixel, the
// triangle the backend's nearest hit names, with exactly the outputs the raster's gbuffer.frag
// writes for it (the same watertight test on the same pixel ray), so either source gives the same
// G-buffer for the same visible triangle. Misses keep the clear values.
#include "scene.glsl"
#include "camera.glsl"
#include "intersect.glsl"
uniform float depthScale;
uniform sampler2D hitT;
uniform isampler2D hitId;
layout(location = 0) out vec4 outPos;
layout(location = 1) out vec4 outNormal;
layout(location = 2) out vec4 outAlbedo;
layout(location = 3) out int outId;
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int id = texelFetch(hitId, px, 0).r;
    if (id < 0) discard;
    Tri tri = tris[id];
    vec3 d = primaryDir(gl_FragCoord.xy);
    float t; vec2 b;
    if (!intersectTriangle(prepareRay(camPos, d), tri.v0, tri.v1, tri.v2, 0.0, 1e30, t, b)) {
        t = texelFetch(hitT, px, 0).r;  // the backend's own distance (a hit on an edge it accepted)
    }
    vec3 n = normalize(cross(tri.v1 - tri.v0, tri.v2 - tri.v0));
    if (dot(d, n) > 0.0) n = -n;
    outPos = vec4(camPos + d * t, t);
    outNormal = vec4(n, 0.0);
    outAlbedo = materials[tri.mat];
    outId = id;
    gl_FragDepth = t / (t + depthScale);
}

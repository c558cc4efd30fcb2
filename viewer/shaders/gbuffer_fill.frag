// The G-buffer's position, normal and albedo from a triangle id per pixel, with exactly the outputs
// the raster's gbuffer.frag computed for that triangle before it wrote a visibility buffer (the
// same watertight test on the same pixel ray), so every source gives the same G-buffer for the
// same visible triangle.
// * default (the renderer's "trace" G-buffer source): the id is the backend's nearest hit of the
//   traced primary ray; this pass also writes the id and the depth. Misses keep the clear values.
// * RESOLVE (the exact raster's second half, Burns and Hunt's visibility buffer): the id is the one
//   the exact raster wrote (its coverage and depth are already final); every pixel is written once,
//   misses with the clear values (-1, 0, 0, 0), so the targets need no clear of their own.
#include "scene.glsl"
#include "camera.glsl"
#include "intersect.glsl"
layout(location = 0) out vec4 outPos;
layout(location = 1) out vec4 outNormal;
layout(location = 2) out vec4 outAlbedo;
#ifdef RESOLVE
uniform isampler2D visId;
#else
uniform float depthScale;
uniform sampler2D hitT;
uniform isampler2D hitId;
layout(location = 3) out int outId;
#endif
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
#ifdef RESOLVE
    int id = texelFetch(visId, px, 0).r;
    if (id < 0) {
        outPos = outNormal = outAlbedo = vec4(-1.0, 0.0, 0.0, 0.0);
        return;
    }
#else
    int id = texelFetch(hitId, px, 0).r;
    if (id < 0) discard;
#endif
    Tri tri = loadTri(id);
    vec3 d = primaryDir(gl_FragCoord.xy);
    float t; vec2 b;
    if (!intersectTriangle(prepareRay(camPos, d), tri.v0, tri.v1, tri.v2, 0.0, 1e30, t, b)) {
#ifdef RESOLVE
        t = 0.0;  // unreachable: the raster kept this pixel because the same test hit
#else
        t = texelFetch(hitT, px, 0).r;  // the backend's own distance (a hit on an edge it accepted)
#endif
    }
    vec3 n = normalize(cross(tri.v1 - tri.v0, tri.v2 - tri.v0));
    if (dot(d, n) > 0.0) n = -n;
    outPos = vec4(camPos + d * t, t);
    outNormal = vec4(n, 0.0);
    outAlbedo = materials[tri.mat];
#ifndef RESOLVE
    outId = id;
    gl_FragDepth = divRounded(t, t + depthScale);  // (correctly rounded: the same depths, so the same order, on every device)
#endif
}

// Slightly conservative rasterization by triangle expansion (after Hasselgren, Akenine-Möller and
// Ohlsson, GPU Gems 2 ch. 42): every edge is pushed out a little so each pixel whose centre the
// exact ray/triangle test accepts gets a fragment; the fragment shader then keeps exactly those. This
// makes the G-buffer's coverage that of the primary ray through the pixel centre, not of the
// rasterizer's snapped vertices. The push-out is EXPAND_PX pixels: enough to cover the rasterizer's
// sub-pixel vertex snapping (1/256 pixel on llvmpipe, similar on GPUs) and float rounding, small
// enough to add little area.
//
// Nothing is ever near- or far-clipped: every emitted vertex's depth is the triangle's lower bound
// in [0, 1) (depthLowerBound; the depth written comes from the exact ray distance in the fragment
// shader). A triangle with a vertex at or behind the camera plane is
// clipped, in double, at a small positive depth that loses nothing on screen (clippedPolygon
// below), and the clipped polygon (one or two triangles) is expanded the same way: such triangles
// (a floor under the camera) used to become screen rectangles whose every pixel ran the exact test,
// half of a city frame's G-buffer time on llvmpipe. Whatever the expansion still cannot handle (an
// edge-on projection) gets a screen rectangle that holds every pixel the triangle can cover
// (coverageRect), so primary visibility agrees with traced primary rays for any camera position,
// however close to the geometry. Corners are emitted homogeneous (x, y, 0, w), scaled to unit
// size, so a corner far off screen keeps its precision through the GL's clipper.
#include "scene.glsl"
#include "camera.glsl"
#ifndef EXPAND_PX
#define EXPAND_PX (1.0 / 32.0)
#endif
uniform float depthScale;
layout(triangles) in;
// at most 7 vertices: a clipped quad's first triangle (3) and then, when its second cannot be
// expanded, the screen rectangle (4) (emitClipped). A vertex past max_vertices is undefined
// behaviour (Mesa drops it, which lost half of that rectangle; other drivers may do worse)
layout(triangle_strip, max_vertices = 7) out;
flat in int vTri[];  // the triangle id (leaf slot), from gl_VertexID: valid in every draw of a multi-draw
// The triangle's vertices, passed flat to every fragment: gbuffer.frag reads them here instead of
// from the triangle SSBO. On llvmpipe that load is a per-lane gather in every fragment
// invocation, and the exact raster runs ~10 per covered pixel (llvmpipe has no early depth test
// for a shader that writes depth): the flat inputs made the raster 1.6x faster (city-near 640x360).
flat out vec3 gV0, gV1, gV2;

void emitVertex(vec4 position, Tri tri) {
    gl_Position = position;
    gl_PrimitiveID = vTri[0];
    gV0 = tri.v0;
    gV1 = tri.v1;
    gV2 = tri.v2;
    EmitVertex();
}

// The part of the triangle a pixel's primary ray can hit, in clip space (x, y, w), computed in
// float64 from the float32 vertices and camera (exact differences): points with camera depth w
// project on screen only if w >= c * |p| (c = cos of the half-diagonal field of view, with a
// margin), and |p| >= the distance from the camera to the triangle's plane, so clipping the triangle
// at w = wmin = c * planeDistance / 2 (Sutherland-Hodgman) loses nothing that is on screen. Returns
// the polygon's corner count (0: nothing on screen, or only t = 0 hits; at most 4), all with w >= wmin.
int clippedPolygon(out dvec3 poly[4]) {
    Tri tri = loadTri(vTri[0]);
    dvec3 cp = dvec3(camPos);
    dvec3 a = dvec3(tri.v0) - cp, b = dvec3(tri.v1) - cp, c = dvec3(tri.v2) - cp;
    dvec3 n = cross(b - a, c - a);
    double nn = dot(n, n);
    if (nn == 0.0lf) return 0;  // zero area: the ray test never hits it
    double planeDist = abs(dot(n, a)) / sqrt(nn);
    if (planeDist == 0.0lf) return 0;  // the camera lies in its plane: only t = 0 hits, excluded
    double aspect = double(viewport.x) / double(viewport.y);
    double tx = double(tanHalfFov) * aspect * 1.1lf, ty = double(tanHalfFov) * 1.1lf;
    double wmin = 0.5lf * planeDist / sqrt(1.0lf + tx * tx + ty * ty);
    dvec3 R = dvec3(camRight), U = dvec3(camUp), F = dvec3(camForward);
    dvec2 scale = dvec2(1.0lf / (double(tanHalfFov) * aspect), 1.0lf / double(tanHalfFov));
    dvec3 q[3] = dvec3[3](dvec3(dot(a, R), dot(a, U), dot(a, F)), dvec3(dot(b, R), dot(b, U), dot(b, F)),
                          dvec3(dot(c, R), dot(c, U), dot(c, F)));
    int k = 0;
    for (int i = 0; i < 3; ++i) {
        dvec3 p = q[i], s = q[(i + 1) % 3];
        if (p.z >= wmin) poly[k++] = dvec3(p.xy * scale, p.z);
        if ((p.z >= wmin) != (s.z >= wmin)) {
            dvec3 x = mix(p, s, (wmin - p.z) / (s.z - p.z));
            poly[k++] = dvec3(x.xy * scale, wmin);
        }
    }
    return k;
}

// Screen rectangle (NDC) holding the projection of the clipped polygon (every point of the
// triangle a pixel's primary ray can hit), grown by a pixel and the push-out.
bool coverageRect(dvec3 poly[4], int k, out vec4 rect) {
    if (k == 0) return false;  // entirely behind w = wmin: nothing on screen
    dvec2 lo = dvec2(1e300lf), hi = dvec2(-1e300lf);
    for (int i = 0; i < k; ++i) {
        dvec2 v = poly[i].xy / poly[i].z;
        lo = min(lo, v); hi = max(hi, v);
    }
    vec2 pad = 2.0 * (1.0 + EXPAND_PX) / viewport;  // a pixel and the push-out, in NDC units
    vec2 flo = vec2(max(lo, dvec2(-2.0lf))) - pad, fhi = vec2(min(hi, dvec2(2.0lf))) + pad;
    flo = max(flo, vec2(-1.0) - pad);
    fhi = min(fhi, vec2(1.0) + pad);
    if (flo.x > fhi.x || flo.y > fhi.y) return false;
    rect = vec4(flo, fhi);
    return true;
}

// A lower bound of the depth gbuffer.frag writes for any pixel of this triangle (t / (t +
// depthScale), t the primary ray's parameter = the hit's camera depth, since the ray direction's
// forward component is 1): the nearest vertex's camera depth (in double), less the float32 ray
// test's slack (1e-5 of the farthest vertex's distance) and the rounding of the depth map, the NDC
// conversion and the interpolation. Every corner gets it as its depth, so it is the rasterized
// depth, and gbuffer.frag declares that it writes no less (layout(depth_greater)): a fragment
// whose bound already fails the depth test may be dropped before the shader runs (early depth
// test), without changing any outcome. The G-buffer's overdraw stops costing a shader run each
// (llvmpipe: 1.3-1.5x faster at 1280x720 on city-near).
float depthLowerBound() {
    Tri tri = loadTri(vTri[0]);
    dvec3 cp = dvec3(camPos), F = dvec3(camForward);
    dvec3 a = dvec3(tri.v0) - cp, b = dvec3(tri.v1) - cp, c = dvec3(tri.v2) - cp;
    double w = min(min(dot(a, F), dot(b, F)), dot(c, F));
    double r = max(max(length(a), length(b)), length(c));
    double t = max(w - 1e-5lf * r, 0.0lf);
    double z = t / (t + double(depthScale)) * (1.0lf - 1e-6lf) - 1e-6lf;
    return float(max(z, 0.0lf)) * 2.0 - 1.0;  // NDC (window depth = z / 2 + 1 / 2)
}

// Triangle (a, b, c) (clip-space x, y, w) with every edge pushed out by EXPAND_PX pixels, emitted
// (or nothing, when no pixel centre can be covered); false (nothing emitted) when a vertex is not
// in front of the camera, the projection is edge-on, or a pushed-out corner would not be in front.
bool emitExpanded(vec3 a, vec3 b, vec3 c) {
    if (!(a.z > 0.0 && b.z > 0.0 && c.z > 0.0)) return false;
    // No pixel centre near its screen box: no pixel's ray can hit it (every centre the exact test
    // accepts lies within EXPAND_PX pixels of the projected triangle, the expansion's own premise;
    // twice that here also covers this projection's rounding), so nothing is emitted. Most of a
    // far city's triangles are such sub-pixel slivers between pixel centres; dropping them here
    // saves their setup and binning (llvmpipe: 1.5x faster at 160x90 on city-near).
    vec2 pa = (a.xy / a.z * 0.5 + 0.5) * viewport, pb = (b.xy / b.z * 0.5 + 0.5) * viewport;
    vec2 pc = (c.xy / c.z * 0.5 + 0.5) * viewport;
    vec2 lo = min(min(pa, pb), pc) - 2.0 * EXPAND_PX, hi = max(max(pa, pb), pc) + 2.0 * EXPAND_PX;
    if (any(greaterThan(ceil(lo - 0.5), floor(hi - 0.5)))) return true;  // done: nothing to draw
    float det = dot(a, cross(b, c));
    if (det == 0.0) return false;
    float s = det > 0.0 ? 1.0 : -1.0;
    vec2 hp = 2.0 * EXPAND_PX / viewport;  // EXPAND_PX pixels in NDC units (a pixel spans 2/viewport)
    vec3 e0 = s * cross(a, b), e1 = s * cross(b, c), e2 = s * cross(c, a);  // >= 0 inside
    // push each edge out by the EXPAND_PX box
    e0.z += dot(hp, abs(e0.xy));
    e1.z += dot(hp, abs(e1.xy));
    e2.z += dot(hp, abs(e2.xy));
    vec3 corners[3] = vec3[3](cross(e2, e0), cross(e0, e1), cross(e1, e2));
    for (int i = 0; i < 3; ++i) {  // the new corners must lie in front of the camera with the orientation kept
        vec3 h = corners[i] * s;
        if (!(h.z > 0.0) || any(isinf(h)) || any(isnan(h))) return false;
        corners[i] = h / max(max(abs(h.x), abs(h.y)), h.z);  // homogeneous, scaled to unit size
    }
    float z = depthLowerBound();
    Tri tri = loadTri(vTri[0]);
    for (int i = 0; i < 3; ++i) emitVertex(vec4(corners[i].xy, z * corners[i].z, corners[i].z), tri);
    EndPrimitive();
    return true;
}

void emitRect(dvec3 poly[4], int k) {
    vec4 r;
    if (!coverageRect(poly, k, r)) return;
    vec2 c[4] = vec2[4](r.xy, vec2(r.z, r.y), vec2(r.x, r.w), r.zw);
    float z = depthLowerBound();
    Tri tri = loadTri(vTri[0]);
    for (int i = 0; i < 4; ++i) emitVertex(vec4(c[i], z, 1.0), tri);
    EndPrimitive();
}

// A triangle the plain expansion cannot take: its clipped polygon expanded (one or two
// triangles, the second sharing the first's diagonal), else its screen rectangle.
void emitClipped() {
    dvec3 poly[4];
    int k = clippedPolygon(poly);
    if (k < 3) { emitRect(poly, k); return; }
    vec3 p[4] = vec3[4](vec3(poly[0]), vec3(poly[1]), vec3(poly[2]), vec3(poly[min(k - 1, 3)]));
    if (emitExpanded(p[0], p[1], p[2]) && (k == 3 || emitExpanded(p[0], p[2], p[3]))) return;
    emitRect(poly, k);  // may repeat fragments already emitted: the same id and distance, harmless
}

void main() {
    vec4 p0 = gl_in[0].gl_Position, p1 = gl_in[1].gl_Position, p2 = gl_in[2].gl_Position;
    if (!emitExpanded(p0.xyw, p1.xyw, p2.xyw)) emitClipped();
}

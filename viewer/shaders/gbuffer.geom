// Slightly conservative rasterization by triangle expansion (after Hasselgren, Akenine-Möller and
// Ohlsson, GPU Gems 2 ch. 42): every edge is pushed out a little so each pixel whose centre the
// exact ray/triangle test accepts gets a fragment; the fragment shader then keeps exactly those. This
// makes the G-buffer's coverage that of the primary ray through the pixel centre, not of the
// rasterizer's snapped vertices. The push-out is EXPAND_PX pixels: enough to cover the rasterizer's
// sub-pixel vertex snapping (1/256 pixel on llvmpipe, similar on GPUs) and float rounding, small
// enough to add little area.
//
// Nothing is ever near- or far-clipped: every emitted vertex has z = 0, w = 1 (depth comes from the
// exact ray distance in the fragment shader). Triangles the expansion cannot handle (a vertex at or
// behind the camera plane, an edge-on projection) get a screen rectangle instead that holds every
// pixel the triangle can cover (coverageRect below), so primary visibility agrees with traced
// primary rays for any camera position, however close to the geometry.
#include "scene.glsl"
#include "camera.glsl"
#ifndef EXPAND_PX
#define EXPAND_PX (1.0 / 32.0)
#endif
layout(triangles) in;
layout(triangle_strip, max_vertices = 4) out;

// Screen rectangle (NDC) holding the projection of every point of the triangle that a pixel's
// primary ray can hit, computed in float64 from the float32 vertices and camera (exact differences).
// Points with camera depth w project on screen only if w >= c * |p| (c = cos of the half-diagonal
// field of view, with a margin), and |p| >= the distance from the camera to the triangle's plane,
// so clipping the triangle at w = wmin = c * planeDistance / 2 loses nothing that is on screen; the
// clipped polygon (<= 4 corners, all in front) then projects to a bounded rectangle.
bool coverageRect(out vec4 rect) {
    Tri tri = tris[gl_PrimitiveIDIn];
    dvec3 cp = dvec3(camPos);
    dvec3 a = dvec3(tri.v0) - cp, b = dvec3(tri.v1) - cp, c = dvec3(tri.v2) - cp;
    dvec3 n = cross(b - a, c - a);
    double nn = dot(n, n);
    if (nn == 0.0lf) return false;  // zero area: the ray test never hits it
    double planeDist = abs(dot(n, a)) / sqrt(nn);
    if (planeDist == 0.0lf) return false;  // the camera lies in its plane: only t = 0 hits, excluded
    double aspect = double(viewport.x) / double(viewport.y);
    double tx = double(tanHalfFov) * aspect * 1.1lf, ty = double(tanHalfFov) * 1.1lf;
    double wmin = 0.5lf * planeDist / sqrt(1.0lf + tx * tx + ty * ty);
    dvec3 R = dvec3(camRight), U = dvec3(camUp), F = dvec3(camForward);
    dvec3 q[3] = dvec3[3](dvec3(dot(a, R), dot(a, U), dot(a, F)), dvec3(dot(b, R), dot(b, U), dot(b, F)),
                          dvec3(dot(c, R), dot(c, U), dot(c, F)));
    dvec2 lo = dvec2(1e300lf), hi = dvec2(-1e300lf);
    dvec2 scale = dvec2(1.0lf / (double(tanHalfFov) * aspect), 1.0lf / double(tanHalfFov));
    for (int i = 0; i < 3; ++i) {  // Sutherland-Hodgman against w >= wmin, folded into the bounds
        dvec3 p = q[i], s = q[(i + 1) % 3];
        if (p.z >= wmin) {
            dvec2 v = p.xy / p.z * scale;
            lo = min(lo, v); hi = max(hi, v);
        }
        if ((p.z >= wmin) != (s.z >= wmin)) {
            dvec3 x = mix(p, s, (wmin - p.z) / (s.z - p.z));
            dvec2 v = x.xy / wmin * scale;
            lo = min(lo, v); hi = max(hi, v);
        }
    }
    if (lo.x > hi.x) return false;  // entirely behind w = wmin: nothing on screen
    vec2 pad = 2.0 * (1.0 + EXPAND_PX) / viewport;  // a pixel and the push-out, in NDC units
    vec2 flo = vec2(max(lo, dvec2(-2.0lf))) - pad, fhi = vec2(min(hi, dvec2(2.0lf))) + pad;
    flo = max(flo, vec2(-1.0) - pad);
    fhi = min(fhi, vec2(1.0) + pad);
    if (flo.x > fhi.x || flo.y > fhi.y) return false;
    rect = vec4(flo, fhi);
    return true;
}

void emitRect() {
    vec4 r;
    if (!coverageRect(r)) return;
    vec2 c[4] = vec2[4](r.xy, vec2(r.z, r.y), vec2(r.x, r.w), r.zw);
    for (int i = 0; i < 4; ++i) {
        gl_Position = vec4(c[i], 0.0, 1.0);
        gl_PrimitiveID = gl_PrimitiveIDIn;
        EmitVertex();
    }
    EndPrimitive();
}

void main() {
    vec4 p0 = gl_in[0].gl_Position, p1 = gl_in[1].gl_Position, p2 = gl_in[2].gl_Position;
    if (!(p0.w > 0.0 && p1.w > 0.0 && p2.w > 0.0)) { emitRect(); return; }
    vec3 a = p0.xyw, b = p1.xyw, c = p2.xyw;
    float det = dot(a, cross(b, c));
    if (det == 0.0) { emitRect(); return; }
    float s = det > 0.0 ? 1.0 : -1.0;
    vec2 hp = 2.0 * EXPAND_PX / viewport;  // EXPAND_PX pixels in NDC units (a pixel spans 2/viewport)
    vec3 e0 = s * cross(a, b), e1 = s * cross(b, c), e2 = s * cross(c, a);  // >= 0 inside
    // push each edge out by the EXPAND_PX box
    e0.z += dot(hp, abs(e0.xy));
    e1.z += dot(hp, abs(e1.xy));
    e2.z += dot(hp, abs(e2.xy));
    vec3 na = cross(e2, e0), nb = cross(e0, e1), nc = cross(e1, e2);
    // the new corners must lie in front of the camera with the orientation kept
    if (!(na.z * s > 0.0 && nb.z * s > 0.0 && nc.z * s > 0.0)) { emitRect(); return; }
    vec3 corners[3] = vec3[3](na / na.z, nb / nb.z, nc / nc.z);
    for (int i = 0; i < 3; ++i) {
        // any positive w works: depth comes from the exact ray distance in the fragment shader
        gl_Position = vec4(corners[i].xy, 0.0, 1.0);
        gl_PrimitiveID = gl_PrimitiveIDIn;
        EmitVertex();
    }
    EndPrimitive();
}

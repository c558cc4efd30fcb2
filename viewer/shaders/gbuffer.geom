// Slightly conservative rasterization by triangle expansion (after Hasselgren, Akenine-Möller and
// Ohlsson, GPU Gems 2 ch. 42): every edge is pushed out a little so each pixel whose centre the
// exact ray/triangle test accepts gets a fragment; the fragment shader then keeps exactly those. This
// makes the G-buffer's coverage that of the primary ray through the pixel centre, not of the
// rasterizer's snapped vertices. Triangles crossing the camera plane are passed through unchanged.
// The push-out is EXPAND_PX pixels: enough to cover the rasterizer's sub-pixel vertex snapping
// (1/256 pixel on llvmpipe, similar on GPUs) and float rounding, small enough to add little area.
#ifndef EXPAND_PX
#define EXPAND_PX (1.0 / 32.0)
#endif
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
uniform vec2 viewport;

void emitOriginal() {
    for (int i = 0; i < 3; ++i) {
        gl_Position = gl_in[i].gl_Position;
        gl_PrimitiveID = gl_PrimitiveIDIn;
        EmitVertex();
    }
    EndPrimitive();
}

void main() {
    vec4 p0 = gl_in[0].gl_Position, p1 = gl_in[1].gl_Position, p2 = gl_in[2].gl_Position;
    if (!(p0.w > 0.0 && p1.w > 0.0 && p2.w > 0.0)) { emitOriginal(); return; }
    vec3 a = p0.xyw, b = p1.xyw, c = p2.xyw;
    float det = dot(a, cross(b, c));
    if (det == 0.0) { emitOriginal(); return; }
    float s = det > 0.0 ? 1.0 : -1.0;
    vec2 hp = 2.0 * EXPAND_PX / viewport;  // EXPAND_PX pixels in NDC units (a pixel spans 2/viewport)
    vec3 e0 = s * cross(a, b), e1 = s * cross(b, c), e2 = s * cross(c, a);  // >= 0 inside
    // push each edge out by the EXPAND_PX box
    e0.z += dot(hp, abs(e0.xy));
    e1.z += dot(hp, abs(e1.xy));
    e2.z += dot(hp, abs(e2.xy));
    vec3 na = cross(e2, e0), nb = cross(e0, e1), nc = cross(e1, e2);
    // the new corners must lie in front of the camera with the orientation kept
    if (!(na.z * s > 0.0 && nb.z * s > 0.0 && nc.z * s > 0.0)) { emitOriginal(); return; }
    vec3 corners[3] = vec3[3](na / na.z, nb / nb.z, nc / nc.z);
    float ws[3] = float[3](p0.w, p1.w, p2.w);
    for (int i = 0; i < 3; ++i) {
        // any positive w works: depth comes from the exact ray distance in the fragment shader
        gl_Position = vec4(corners[i].xy, 0.0, 1.0);
        gl_PrimitiveID = gl_PrimitiveIDIn;
        EmitVertex();
    }
    EndPrimitive();
}

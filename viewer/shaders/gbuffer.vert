// G-buffer rasterization with vertex pulling: the draw has no vertex attributes; vertex
// gl_VertexID is corner gl_VertexID % 3 of leaf-ordered triangle gl_VertexID / 3, read from the
// scene's triangle buffer (scene.glsl), so the raster needs no vertex buffer of its own (36 bytes a
// triangle, 360 MB uploaded for a 10 M-triangle scene). gl_VertexID counts from the draw's `first`,
// unlike gl_PrimitiveID, which restarts in each draw of a culled multi-draw. Positions are made
// camera-relative before projection.
#include "scene.glsl"
uniform mat4 viewProjRel;  // projection * view rotation (camera at origin)
uniform vec3 camPosV;
flat out int vTri;
void main() {
    vTri = gl_VertexID / 3;
    int corner = gl_VertexID - 3 * vTri;
    Tri t = tris[vTri];
    vec3 p = corner == 0 ? t.v0 : (corner == 1 ? t.v1 : t.v2);
    gl_Position = viewProjRel * vec4(p - camPosV, 1.0);
}

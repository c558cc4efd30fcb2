// G-buffer rasterization: vertices are the leaf-ordered triangles, three per triangle, so
// gl_VertexID / 3 is the triangle id used by every tracer (gl_VertexID counts from the draw's
// `first`, unlike gl_PrimitiveID, which restarts in each draw of a culled multi-draw). Positions
// are made camera-relative before projection.
uniform mat4 viewProjRel;  // projection * view rotation (camera at origin)
uniform vec3 camPosV;
in vec3 in_pos;
flat out int vTri;
void main() {
    vTri = gl_VertexID / 3;
    gl_Position = viewProjRel * vec4(in_pos - camPosV, 1.0);
}

// G-buffer rasterization: vertices are the leaf-ordered triangles, so gl_PrimitiveID is the
// triangle id used by every tracer. Positions are made camera-relative before projection.
uniform mat4 viewProjRel;  // projection * view rotation (camera at origin)
uniform vec3 camPosV;
in vec3 in_pos;
void main() {
    gl_Position = viewProjRel * vec4(in_pos - camPosV, 1.0);
}

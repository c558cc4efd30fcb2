// G-buffer rasterization: vertices are the leaf-ordered triangles, so gl_PrimitiveID is the
// triangle id used by every tracer. Positions are made camera-relative before projection.
uniform mat4 viewProjRel;  // projection * view rotation (camera at origin)
uniform vec3 camPosV;
in vec3 in_pos;
out vec3 vWorld;  // for the geometry shader's exact fallback (triangles at or behind the camera plane)
void main() {
    vWorld = in_pos;
    gl_Position = viewProjRel * vec4(in_pos - camPosV, 1.0);
}

// G-buffer rasterization with vertex pulling: the draw has no vertex attributes; vertex
// gl_VertexID is corner gl_VertexID % 3 of leaf-ordered triangle gl_VertexID / 3, read from the
// scene's triangle buffer, so the raster needs no vertex buffer of its own (36 bytes a triangle,
// 360 MB uploaded for a 10 M-triangle scene). The buffer is read as plain floats, the three of the
// corner only (scene.glsl's Tri record, 12 words: v0 at word 0, v1 at 4, v2 at 8): a whole-record
// load is 12 per-lane gathers on llvmpipe. gl_VertexID counts from the draw's `first`, unlike
// gl_PrimitiveID, which restarts in each draw of a culled multi-draw. Positions are made
// camera-relative before projection.
// With SCENE_TEXELS (viewer/gl/scene.py) the corner is one texel of the triangles' buffer texture.
#ifdef SCENE_TEXELS
layout(binding = BIND_TEX_TRIS) uniform usamplerBuffer triTexels;  // 3 texels a Tri
#else
layout(std430, binding = BIND_TRIS) readonly buffer TriWords { float triWords[]; };
#endif
uniform mat4 viewProjRel;  // projection * view rotation (camera at origin)
uniform vec3 camPosV;
flat out int vTri;
void main() {
    vTri = gl_VertexID / 3;
#ifdef SCENE_TEXELS
    vec3 p = uintBitsToFloat(texelFetch(triTexels, gl_VertexID).xyz);  // texel 3 * vTri + corner
#else
    int w = 12 * vTri + 4 * (gl_VertexID - 3 * vTri);
    vec3 p = vec3(triWords[w], triWords[w + 1], triWords[w + 2]);
#endif
    gl_Position = viewProjRel * vec4(p - camPosV, 1.0);
}

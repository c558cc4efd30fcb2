// Scene buffers shared by every pass. Layouts match viewer/accel/bvh.py (GPU_NODE_DTYPE, GPU_TRI_DTYPE).
// Node: both child boxes stored in the parent (Aila-Laine). A child reference >= 0 is an inner
// node index; a negative reference is a leaf ~firstTriangle with its count in lcount/rcount.
struct Node { vec3 lmin; int left; vec3 lmax; int right; vec3 rmin; int lcount; vec3 rmax; int rcount; };
struct Tri { vec3 v0; int id; vec3 v1; int mat; vec3 v2; int pad; };

layout(std430, binding = BIND_NODES) readonly buffer Nodes { Node nodes[]; };
layout(std430, binding = BIND_TRIS) readonly buffer Tris { Tri tris[]; };
layout(std430, binding = BIND_MATERIALS) readonly buffer Materials { vec4 materials[]; };  // rgb albedo, a = mirror

// The traversals' node and triangle reads (intersect.glsl and the backends' loops). SCENE_TEXELS
// (viewer/gl/scene.py GpuScene.trace_defines: set when the buffers fit the device's buffer-texture
// limit): through RGBA32UI buffer textures over the same two buffers (GpuScene binds them), the
// same bits: on llvmpipe an SSBO load is a loop over the SIMD lanes, a texel fetch one gather
// (viewer/gl/textures.py TexelView). Else straight from the SSBOs.
#ifdef SCENE_TEXELS
layout(binding = BIND_TEX_NODES) uniform usamplerBuffer sceneNodeTexels;  // 4 texels a Node
layout(binding = BIND_TEX_TRIS) uniform usamplerBuffer sceneTriTexels;  // 3 texels a Tri
Node loadNode(int i) {
    uvec4 a = texelFetch(sceneNodeTexels, 4 * i), b = texelFetch(sceneNodeTexels, 4 * i + 1);
    uvec4 c = texelFetch(sceneNodeTexels, 4 * i + 2), d = texelFetch(sceneNodeTexels, 4 * i + 3);
    return Node(uintBitsToFloat(a.xyz), int(a.w), uintBitsToFloat(b.xyz), int(b.w),
                uintBitsToFloat(c.xyz), int(c.w), uintBitsToFloat(d.xyz), int(d.w));
}
Tri loadTri(int i) {
    uvec4 a = texelFetch(sceneTriTexels, 3 * i), b = texelFetch(sceneTriTexels, 3 * i + 1);
    uvec4 c = texelFetch(sceneTriTexels, 3 * i + 2);
    return Tri(uintBitsToFloat(a.xyz), int(a.w), uintBitsToFloat(b.xyz), int(b.w), uintBitsToFloat(c.xyz), int(c.w));
}
#else
Node loadNode(int i) { return nodes[i]; }
Tri loadTri(int i) { return tris[i]; }
#endif

vec3 triNormal(int id) {
    Tri t = tris[id];
    return normalize(cross(t.v1 - t.v0, t.v2 - t.v0));
}

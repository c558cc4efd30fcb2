// Scene buffers shared by every pass. Layouts match viewer/accel/bvh.py (GPU_NODE_DTYPE, GPU_TRI_DTYPE).
// Node: both child boxes stored in the parent (Aila-Laine). A child reference >= 0 is an inner
// node index; a negative reference is a leaf ~firstTriangle with its count in lcount/rcount.
struct Node { vec3 lmin; int left; vec3 lmax; int right; vec3 rmin; int lcount; vec3 rmax; int rcount; };
struct Tri { vec3 v0; int id; vec3 v1; int mat; vec3 v2; int pad; };

layout(std430, binding = BIND_NODES) readonly buffer Nodes { Node nodes[]; };
layout(std430, binding = BIND_TRIS) readonly buffer Tris { Tri tris[]; };
layout(std430, binding = BIND_MATERIALS) readonly buffer Materials { vec4 materials[]; };  // rgb albedo, a = mirror

vec3 triNormal(int id) {
    Tri t = tris[id];
    return normalize(cross(t.v1 - t.v0, t.v2 - t.v0));
}

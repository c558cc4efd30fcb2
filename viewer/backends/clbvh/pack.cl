// Leaf blocks of clbvh (layout: trace.cl, LEAF_BLOCK_DTYPE in __init__.py): block k holds the
// triangles in slots first[k] .. first[k] + count[k] - 1 (count <= 4), one float4 lane each in SoA
// form (v[3 * vertex + axis]), NaN in empty lanes, then int4 (first slot, count, 0, 0). One
// work-item per block; the triangles are in leaf order (slot = triangle id).
__kernel void pack_blocks(__global const float* tris, uint n_blocks, __global const int* first,
                          __global const int* count, __global float4* blocks) {
    uint k = get_global_id(0);
    if (k >= n_blocks) return;
    int f = first[k], c = count[k];
    __global float4* out = blocks + 10 * (size_t)k;
    float v[4][9];
    for (int lane = 0; lane < 4; ++lane) {
        __global const float* t = tris + 9 * (size_t)(f + lane);
        for (int q = 0; q < 9; ++q) v[lane][q] = lane < c ? t[q] : as_float(0x7fc00000u);  // NumPy's NaN
    }
    for (int q = 0; q < 9; ++q) out[q] = (float4)(v[0][q], v[1][q], v[2][q], v[3][q]);
    out[9] = as_float4((int4)(f, c, 0, 0));
}

// From a BVH4 already on the device (leaves of at most 4 triangles: one block each): leaf slots per
// node, for the scan that numbers the blocks in row-major order (as leaf_block_index does).
__kernel void leaf_slots(uint n4, __global const int4* nodes, __global uint* slots) {
    uint i = get_global_id(0);
    if (i >= n4) return;
    int4 child = nodes[8 * (size_t)i + 6], count = nodes[8 * (size_t)i + 7];
    int4 leaf = (child < 0) & (count > 0);
    slots[i] = (uint)(-(leaf.x + leaf.y + leaf.z + leaf.w));
}

// The kernel's copy of node i (leaf refs ~block instead of ~first slot) and its blocks' first slot
// and triangle count.
__kernel void kernel_nodes(uint n4, __global const int4* nodes, __global const uint* offset, __global int4* knodes,
                           __global int* first, __global int* count) {
    uint i = get_global_id(0);
    if (i >= n4) return;
    __global const int4* src = nodes + 8 * (size_t)i;
    __global int4* dst = knodes + 8 * (size_t)i;
    for (int f = 0; f < 6; ++f) dst[f] = src[f];
    int4 c4 = src[6], n4c = src[7];
    int ch[4] = {c4.x, c4.y, c4.z, c4.w}, cn[4] = {n4c.x, n4c.y, n4c.z, n4c.w};
    uint o = offset[i];
    for (int s = 0; s < 4; ++s) {
        if (ch[s] < 0 && cn[s] > 0) {
            first[o] = ~ch[s];
            count[o] = cn[s];
            ch[s] = ~(int)o;
            ++o;
        }
    }
    dst[6] = (int4)(ch[0], ch[1], ch[2], ch[3]);
    dst[7] = n4c;
}

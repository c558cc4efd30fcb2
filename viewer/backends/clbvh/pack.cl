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

// Staging triangles in local memory for the four-wide test: triangle k of a batch goes to lane
// k % 4 of SoA block k / 4 (nine float4 rows: v0x, v0y, v0z, v1x, ..., v2z), the layout
// rt_intersect_triangle4_local reads (geometry.cl).
inline void stage_triangle(__local float4 *blocks, uint k, __global const float4 *tris, uint slot) {
    __local float *f = (__local float *)(blocks + 9 * (k / 4));
    uint lane = k % 4;
    float4 a = tris[3 * slot], b = tris[3 * slot + 1], c = tris[3 * slot + 2];
    f[0 * 4 + lane] = a.x; f[1 * 4 + lane] = a.y; f[2 * 4 + lane] = a.z;
    f[3 * 4 + lane] = b.x; f[4 * 4 + lane] = b.y; f[5 * 4 + lane] = b.z;
    f[6 * 4 + lane] = c.x; f[7 * 4 + lane] = c.y; f[8 * 4 + lane] = c.z;
}

// Lanes of the block starting at batch index k that hold one of the batch's cnt triangles (-1).
inline int4 stage_lanes(uint k, uint cnt) {
    return (int4)(k < cnt ? -1 : 0, k + 1 < cnt ? -1 : 0, k + 2 < cnt ? -1 : 0, k + 3 < cnt ? -1 : 0);
}

// A triangle's 2D box (x min, x max, y min, y max: the camera grid's pixel rectangle, the point
// grid's angular box) into lane k % 4 of SoA block k / 4 (four float4 rows: x min, x max, y min,
// y max). A ray whose own (x, y) lies outside a triangle's box cannot meet it: the test that bins
// triangles into tiles, at the ray's resolution instead of the tile's.
inline void stage_box(__local float4 *boxes, uint k, float4 b) {
    __local float *f = (__local float *)(boxes + 4 * (k / 4));
    uint lane = k % 4;
    f[lane] = b.x; f[4 + lane] = b.y; f[8 + lane] = b.z; f[12 + lane] = b.w;
}

// Lanes (-1) of the staged block at `boxes` whose box holds (x, y).
inline int4 box_lanes(__local const float4 *boxes, float x, float y) {
    return (x >= boxes[0]) & (x <= boxes[1]) & (y >= boxes[2]) & (y <= boxes[3]);
}

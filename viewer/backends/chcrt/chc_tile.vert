// CHC+RT batched mode: one instanced draw covers many (tile, item range) records; instance i draws
// the pixel rectangle of record i as two triangles (edges on pixel boundaries, so every pixel
// centre of the tile is covered exactly once) and hands its item range and query slot to the
// fragment shader. Replaces one scissored draw (and one occlusion query object) per record.
// GPU-driven pass with mergeKept (device fronts): a visible record (query slot 0) that carries its
// tile's merged kept invisible pairs (chc_querycull.comp; info.w = finest tile; keptCarrier) also
// hands them over.
#include "chc_records.glsl"
#ifdef CHC_MERGE_KEPT  // (chcrt.py sets it for the counting intersection only)
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_TILES) readonly buffer TilePlans { ChcTilePlan plans[]; };
uniform int mergeKept;
flat out int vKeptBase;
flat out int vKeptCount;
#endif
layout(std430, binding = BIND_CHC_DRAWS) readonly buffer ChcDraws { ChcDraw draws[]; };
uniform ivec2 raySize;
flat out int vItemBase;
flat out int vItemCount;
flat out int vQuery;
void main() {
    ChcDraw d = draws[gl_InstanceID];
    const ivec2 corner[6] = ivec2[6](ivec2(0, 0), ivec2(1, 0), ivec2(0, 1), ivec2(0, 1), ivec2(1, 0), ivec2(1, 1));
    vec2 p = vec2(d.rect.xy + corner[gl_VertexID] * d.rect.zw) / vec2(raySize);
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
    vItemBase = d.info.x;
    vItemCount = d.info.y;
    vQuery = d.info.z;
#ifdef CHC_MERGE_KEPT  // (chcrt.py sets it for the counting intersection only)
    vKeptBase = 0;
    vKeptCount = 0;
    if (mergeKept != 0 && d.info.z == 0) {  // a branch, not a select: no plan buffer is read otherwise
        ChcTilePlan tp = plans[d.info.w];
        if (keptCarrier(tp, gl_InstanceID)) {
            vKeptBase = tp.keptBase;
            vKeptCount = tp.keptCount;
        }
    }
#endif
}

// Shared by the CHC+RT shaders (viewer/backends/chcrt/chcrt.py).
//  * Rays come from the ray batch textures (origin+tmin, direction+tmax; tmax <= tmin = no ray).
//  * Depth = distance along the ray, t * depthScale with depthScale a power of two (exact, so the
//    depth test compares distances exactly), clamped to 0.5. The depth buffer holds, per pixel,
//    1.0 (no hit yet: everything passes), key(best t) = nextUp(depth(best t)) (a query passes iff
//    its entry distance <= best t, like traverseBVH's `tl <= hit.t`), or 0.0 (inactive ray, or an
//    any-hit ray that is finished: nothing passes).
//  * bestBits (r32i image) mirrors the best t as float bits (-1 = inactive / finished). It only
//    prunes traversal: the hit buffer is written through the depth test, so a stale read costs
//    work, never correctness. Within a pass it only falls (imageAtomicMin), so its draws need no
//    barrier between them ("hazards: monotone", tests/gl_hazards.py); a pass's first values are
//    stores (the init draw, chc_tilebounds.comp's CHC_INIT_RAYS build, a copy), with barriers on
//    both sides: the last pass's atomics must not land on the new pass's values.
#include "scene.glsl"
#include "intersect.glsl"

#ifndef CHC_MAX_ITEMS
#define CHC_MAX_ITEMS 48
#endif

uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform float depthScale;
#ifdef CHC_BATCHED
// batched mode (chc_tile.vert): the draw record of this fragment's instance
flat in int vItemBase;
flat in int vItemCount;
flat in int vQuery;
#define ITEM_BASE vItemBase
#define ITEM_COUNT vItemCount
#else
uniform int itemBase;
uniform int itemCount;
#define ITEM_BASE itemBase
#define ITEM_COUNT itemCount
#endif

layout(r32i, binding = BIND_IMG_CHC_BEST) uniform coherent iimage2D bestBits;  // hazards: monotone
layout(r32i, binding = BIND_IMG_CHC_OVERDRAW) uniform coherent iimage2D overdraw;
layout(r32i, binding = BIND_IMG_CHC_BATCH) uniform coherent iimage2D batchSubtrees;  // overlay: subtrees in the pixel's batches

#include "chc_records.glsl"
layout(std430, binding = BIND_CHC_ITEMS) readonly buffer ChcItems { ChcItem items[]; };
// The fragment shaders' item reads: through a buffer texture over the same buffer (chcrt.py
// bind_items; 4 texels an item), the same bits: on llvmpipe an SSBO load is a loop over the SIMD
// lanes, a texel fetch one gather (viewer/gl/textures.py TexelView), and every fragment of a record
// reads its items. (Fields a caller does not use are not fetched: the compiler drops them.)
layout(binding = BIND_TEX_CHC_ITEMS) uniform usamplerBuffer chcItemTexels;
ChcItem loadItem(int k) {
    uvec4 a = texelFetch(chcItemTexels, 4 * k), b = texelFetch(chcItemTexels, 4 * k + 1);
    uvec4 c = texelFetch(chcItemTexels, 4 * k + 2), e = texelFetch(chcItemTexels, 4 * k + 3);
    return ChcItem(uintBitsToFloat(a.xyz), uintBitsToFloat(a.w), uintBitsToFloat(b.xyz), int(b.w), int(c.x), int(c.y),
                   int(c.z), int(c.w), int(e.x), int(e.y), int(e.z), int(e.w));
}

float chcDepth(float t) { return min(t * depthScale, 0.5); }
float chcKey(float t) { return max(uintBitsToFloat(floatBitsToUint(chcDepth(t)) + 1u), 1e-30); }

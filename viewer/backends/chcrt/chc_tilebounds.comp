// CHC+RT, GPU-driven queries, step 1: per finest tile, what its rays can still reach after the
// visible pairs were intersected: the box around the active rays' origins and the largest
// distance to their nearest hit so far (bestBits, or tmax without a hit), in world units
// (t * |d|), a cone around the active rays' directions (axis: the tile's centre pixel's direction,
// half angle: the largest angle of an active ray's direction from it; any axis gives a valid cone)
// and four side planes (spanned by the tile's corner rays, each with the least n . d/|d| of the
// tile's rays, so any rays give valid planes), which let the cull and the gap order drop boxes that
// no ray of the tile can enter (chc_tilecone.glsl). One work group of TILE_BOUNDS_GROUP invocations
// per tile (chcrt_layout.tile_bounds_group: 64 on a GPU; 8 on a CPU rasterizer, one of llvmpipe's
// 256-bit SIMD vectors, where fewer reduction rounds made a dispatch at 640x360 0.99 ms instead of
// 1.51, medians of 120 alternated dispatches); a tile without an active ray gets maxDist = -1.
// CHC_INIT_RAYS (a device front's pass that merges its kept pairs, without overlays): this dispatch
// is also the pass's init draw (chc_init.frag), whose other work the host does with texture clears:
// every pixel's bestBits is set from its ray (tmax bits, -1 = no ray), and the tile's active rays
// are counted with one atomic per invocation instead of one per pixel. A build of its
// own, not a uniform: llvmpipe runs both sides of a branch on a uniform, and the image load of the
// other side cost 7 % of the dispatch (1.525 -> 1.417 ms at 640x360, docs/results/chcrt.md).
#ifndef TILE_BOUNDS_GROUP
#define TILE_BOUNDS_GROUP 64
#endif
#if TILE_BOUNDS_GROUP != 8 && TILE_BOUNDS_GROUP != 16 && TILE_BOUNDS_GROUP != 32 && TILE_BOUNDS_GROUP != 64
#error "chc_tilebounds.comp: TILE_BOUNDS_GROUP must be 8, 16, 32 or 64 (rows of 8; 64 ray-count slots)"
#endif
#define TB_ROWS (TILE_BOUNDS_GROUP / 8)
// (literal sizes, as tests/test_portability.py checks them against NVIDIA's limits)
#if TILE_BOUNDS_GROUP == 8
layout(local_size_x = 8) in;
#elif TILE_BOUNDS_GROUP == 16
layout(local_size_x = 16) in;
#elif TILE_BOUNDS_GROUP == 32
layout(local_size_x = 32) in;
#else
layout(local_size_x = 64) in;
#endif
layout(r32i, binding = BIND_IMG_CHC_BEST) uniform coherent iimage2D bestBits;  // hazards: monotone (chc_common.glsl)
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform ivec2 raySize;
uniform int level;  // the finest tile level: 2^level x 2^level tiles
#include "chc_tilecone.glsl"
layout(std430, binding = BIND_CHC_TILES) writeonly buffer ChcTiles { TileBound tiles[]; };
layout(std430, binding = BIND_CHC_COUNT) buffer ChcCount { uint chcActive[]; };  // chc_init.frag's ray counts
shared vec3 sMin[64];  // (64: the largest group; a smaller one uses the first entries)
shared vec3 sMax[64];
shared float sDist[64];
shared float sCount[64];
shared float sAngle[64];
shared vec4 sSide[64];
void main() {
    int n = 1 << level;
    int tx = int(gl_WorkGroupID.x) % n, ty = int(gl_WorkGroupID.x) / n;
    ivec2 lo = (ivec2(tx, ty) * raySize) >> level;
    ivec2 hi = (ivec2(tx + 1, ty + 1) * raySize) >> level;
    uint li = gl_LocalInvocationIndex;
    vec3 omin = vec3(3.0e38), omax = vec3(-3.0e38);
    float dmax = -1.0, nActive = 0.0;
    // (the axis's and the corners' pixels clamped into the tile and the texture: an empty tile,
    // hi == lo, reads a defined texel, though its bounds are unused: nActive 0)
    ivec2 last = max(min(hi, textureSize(rayDir, 0)) - 1, ivec2(0));
    ivec2 lo0 = min(lo, last), hi1 = clamp(hi - 1, lo0, last);
    vec3 ac = texelFetch(rayDir, min((lo + hi) >> 1, hi1), 0).xyz;
    float al = length(ac);
    bool coneOk = al > 0.0 && !isinf(al) && !isnan(al);
    vec3 axis = coneOk ? ac / al : vec3(0.0, 0.0, 1.0);
    float s2max = coneOk ? 0.0 : 2.0;
    // the side planes: spanned by the tile's corner rays, normals towards the axis (chc_tilecone.glsl)
    vec3 e00 = texelFetch(rayDir, lo0, 0).xyz, e11 = texelFetch(rayDir, hi1, 0).xyz;
    vec3 e10 = texelFetch(rayDir, ivec2(hi1.x, lo0.y), 0).xyz;
    vec3 e01 = texelFetch(rayDir, ivec2(lo0.x, hi1.y), 0).xyz;
    vec3 sn[4] = vec3[4](cross(e00, e01), cross(e11, e10), cross(e10, e00), cross(e01, e11));
    for (int i = 0; i < 4; ++i) {
        float l = length(sn[i]);
        sn[i] = (coneOk && l > 0.0 && !isinf(l) && !isnan(l)) ? sn[i] / l : vec3(0.0);
        if (dot(sn[i], axis) < 0.0) sn[i] = -sn[i];
    }
    vec4 smin = vec4(0.0);
    // invocation li walks the pixels lo + (li % 8, li / 8) + (8 i, TB_ROWS j): no integer division per
    // pixel (llvmpipe does vector integer division lane by lane)
    ivec2 first = lo + ivec2(int(li) & 7, int(li) >> 3);
    for (int y = first.y; y < hi.y; y += TB_ROWS) for (int x = first.x; x < hi.x; x += 8) {
        ivec2 px = ivec2(x, y);
        // (the ray is read outside the branch: llvmpipe runs both sides of a branch on a uniform)
        vec4 o = texelFetch(rayOrigin, px, 0);
        vec4 d = texelFetch(rayDir, px, 0);
#ifdef CHC_INIT_RAYS
        int best = d.w > o.w ? floatBitsToInt(d.w) : -1;  // as chc_init.frag
        imageStore(bestBits, px, ivec4(best));
#else
        int best = imageLoad(bestBits, px).r;
#endif
        if (best < 0) continue;  // no ray, or an any-hit ray that is done
        omin = min(omin, o.xyz);
        omax = max(omax, o.xyz);
        // (min and max of a NaN are undefined in GLSL, NVIDIA returns the other operand: a NaN reach
        // or side bound, a zero or non-finite direction, is replaced before them: no reach bound, no plane)
        float reach = intBitsToFloat(best) * length(d.xyz);
        dmax = isnan(reach) ? uintBitsToFloat(0x7f800000u) : max(dmax, reach);
        nActive += 1.0;
        // the largest sin^2 of the angle from the axis (a direction at or beyond 90 degrees: no cone);
        // the sine from the cross product stays accurate at small angles (1 - cos does not)
        vec3 cr = cross(d.xyz, axis);
        float s2 = dot(cr, cr) / dot(d.xyz, d.xyz);
        s2max = (dot(d.xyz, axis) > 0.0 && !isnan(s2)) ? max(s2max, s2) : 2.0;
        vec4 sd = vec4(dot(sn[0], d.xyz), dot(sn[1], d.xyz), dot(sn[2], d.xyz), dot(sn[3], d.xyz)) / length(d.xyz);
        smin = mix(min(smin, sd), vec4(-2.0), isnan(sd));  // -2: below every cosine, "no plane"
    }
#ifdef CHC_INIT_RAYS
    if (nActive > 0.0) atomicAdd(chcActive[li], uint(nActive));  // (slots: chcrt_layout.COUNT_SLOTS = 64 >= the group)
#endif
    sMin[li] = omin; sMax[li] = omax; sDist[li] = dmax; sCount[li] = nActive; sAngle[li] = s2max;
    sSide[li] = smin;
    barrier();
    for (uint s = uint(TILE_BOUNDS_GROUP / 2); s > 0u; s >>= 1) {
        if (li < s) {
            sMin[li] = min(sMin[li], sMin[li + s]);
            sMax[li] = max(sMax[li], sMax[li + s]);
            sDist[li] = max(sDist[li], sDist[li + s]);
            sCount[li] += sCount[li + s];
            sAngle[li] = max(sAngle[li], sAngle[li + s]);
            sSide[li] = min(sSide[li], sSide[li + s]);
        }
        barrier();
    }
    if (li == 0u) {
        float s2 = sAngle[0];
        float a = s2 < 1.0 ? asin(sqrt(s2)) : 4.0;  // the half angle (radians), 4 = no cone
        vec4 sm = sSide[0];
        // a side some ray has no bound for (a zero or non-finite direction): no plane
        for (int i = 0; i < 4; ++i) if (!(sm[i] >= -1.5)) { sn[i] = vec3(0.0); sm[i] = 0.0; }
        tiles[gl_WorkGroupID.x] = TileBound(vec4(sMin[0], sDist[0]), vec4(sMax[0], sCount[0]), vec4(axis, a),
                                            vec4[4](vec4(sn[0], sm.x), vec4(sn[1], sm.y), vec4(sn[2], sm.z),
                                                    vec4(sn[3], sm.w)));
    }
}

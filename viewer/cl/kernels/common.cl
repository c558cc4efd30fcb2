/* Shared definitions for rtwalk kernels (include with #include "common.cl").
 * Ray layout (viewer/cl/transfer.py): origin float4 (x, y, z, tmin), dir float4 (dx, dy, dz, tmax);
 * hits: float t (+INFINITY on a miss), int tri (-1 on a miss). */

#define RT_MISS_ID (-1)

/* A ray is active when tmin < tmax and every component is finite (tracing.py conventions). */
inline bool rt_ray_active(float4 o, float4 d) {
    return isfinite(o.x) && isfinite(o.y) && isfinite(o.z) && isfinite(o.w) &&
           isfinite(d.x) && isfinite(d.y) && isfinite(d.z) && !isnan(d.w) && o.w < d.w;
}

/* [begin, end) of contiguous block `b` of `nblocks` over n items (one work-item per block).
 * Blocks start at multiples of 16 items (vector loads stay aligned); trailing blocks may be empty. */
inline uint2 rt_block_range(uint n, uint b, uint nblocks) {
    uint per = ((n + nblocks - 1u) / nblocks + 15u) & ~15u;
    uint begin = min(n, b * per);
    return (uint2)(begin, min(n, begin + per));
}

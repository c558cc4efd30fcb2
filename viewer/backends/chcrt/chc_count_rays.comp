// CHC+RT: the active rays of a device pass that traces the whole BVH (chcrt.py _count_rays), in
// place of the init draw: the glsl traversal writes every pixel's hit itself, and nothing reads
// the depth or the best-hit bits, so only the ray count (the pass's `rays`) is left of it.
// Invocation i counts the 8x8 pixel block i and adds its count with one atomic (the init draw
// added one per pixel) into ray-count slot gl_LocalInvocationIndex (chcrt.COUNT_SLOTS = 64).
layout(local_size_x = 64) in;
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform ivec2 raySize;
layout(std430, binding = BIND_CHC_COUNT) buffer ChcCount { uint chcActive[]; };
void main() {
    int blocksX = (raySize.x + 7) >> 3;
    int b = int(gl_GlobalInvocationID.x);
    ivec2 lo = ivec2(b % blocksX, b / blocksX) * 8;
    ivec2 hi = min(lo + 8, raySize);
    uint n = 0u;
    for (int y = lo.y; y < hi.y; ++y) for (int x = lo.x; x < hi.x; ++x) {
        vec4 o = texelFetch(rayOrigin, ivec2(x, y), 0);
        vec4 d = texelFetch(rayDir, ivec2(x, y), 0);
        n += d.w > o.w ? 1u : 0u;  // as chc_init.frag
    }
    if (n > 0u) atomicAdd(chcActive[gl_LocalInvocationIndex], n);
}

// CHC+RT: the active rays of a device pass that traces the whole BVH (chcrt_pass.py _count_rays), in
// place of the init draw: the glsl traversal writes every pixel's hit itself, and nothing reads
// the depth or the best-hit bits, so only the ray count (the pass's `rays`) is left of it.
// copySlot >= 0: the ray generation counted the rays (PassInfo.ray_count): one invocation copies its
// count, word copySlot of its counters, into slot 0. (A glCopyBufferSubData did the same; on an
// NVIDIA H200 it made the host wait for the GPU in every pass that traced the whole BVH, 59-67 ms a
// frame for city 10 M at 1920x1080 with ao:20, while the ray generation's counters were read back
// directly after every frame: the driver seems to have kept them in host memory, glio.ReadBack.)
// Work group i counts the 64x64 pixel region i; its invocations are an 8x8 grid that steps over the
// region 8 pixels at a time, so a SIMD vector reads a row of neighbouring pixels, and each adds its
// count with one atomic into ray-count slot gl_LocalInvocationIndex (chcrt_layout.COUNT_SLOTS = 64). (One
// invocation per 8x8 block, its vectors reading eight blocks at once, took 1.06 ms a pass at 640x360
// on llvmpipe; a work group per 8x8 block 2.3 ms: llvmpipe pays per work group.)
layout(local_size_x = 8, local_size_y = 8) in;
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform ivec2 raySize;
uniform int copySlot;
layout(std430, binding = BIND_CHC_COUNT) buffer ChcCount { uint chcActive[]; };
layout(std430, binding = BIND_COUNTERS) readonly buffer RaygenCount { uint raygenCount[]; };
void main() {
    if (copySlot >= 0) {
        if (gl_LocalInvocationIndex == 0u && gl_WorkGroupID.xy == uvec2(0u)) chcActive[0] = raygenCount[copySlot];
        return;
    }
    ivec2 first = ivec2(gl_WorkGroupID.xy) * 64 + ivec2(gl_LocalInvocationID.xy);
    ivec2 last = min(ivec2(gl_WorkGroupID.xy) * 64 + 64, raySize);
    uint n = 0u;
    for (int y = first.y; y < last.y; y += 8) for (int x = first.x; x < last.x; x += 8) {
        vec4 o = texelFetch(rayOrigin, ivec2(x, y), 0);
        vec4 d = texelFetch(rayDir, ivec2(x, y), 0);
        n += d.w > o.w ? 1u : 0u;  // as chc_init.frag
    }
    if (n > 0u) atomicAdd(chcActive[gl_LocalInvocationIndex], n);
}

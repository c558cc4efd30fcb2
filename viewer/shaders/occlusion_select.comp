// G-buffer occlusion culling (viewer/passes/occlusion.py), one invocation per node of the BVH cut.
// phase 1: draw the nodes in the view pyramid that were visible last frame;
// phase 2: draw the others in the pyramid that the distance pyramid of phase 1 cannot prove hidden;
// phase 3: remember as visible the nodes in the pyramid the final distance pyramid does not hide.
// A node is hidden when the nearest point of its box is farther than the farthest distance drawn
// over every pixel its box can cover: each of its fragments would then fail the depth test (along
// one pixel ray, distance and depth order alike). Conservative: the pixel rectangle is padded by a
// pixel and the distances by a relative margin; a box reaching the camera plane is never hidden.
layout(local_size_x = 64) in;
struct CutNode { vec3 lo; int first; vec3 hi; int count; };
layout(std430, binding = BIND_CULL_NODES) readonly buffer CullNodes { CutNode nodes[]; };
layout(std430, binding = BIND_CULL_VISIBLE) buffer CullVisible { uint visible[]; };
layout(std430, binding = BIND_CULL_CMDS) writeonly buffer CullCmds { uint cmds[]; };  // 5 words each
layout(std430, binding = BIND_CULL_STATS) buffer CullStats { uint stats[]; };  // tris, nodes per phase
uniform int nNodes;
uniform int phase;
uniform vec3 camPos;
uniform vec3 camRight;
uniform vec3 camUp;
uniform vec3 camForward;
uniform float tanHalfFov;
uniform vec2 viewport;
uniform vec3 planes[4];  // inward normals of the view pyramid's side planes (viewer.passes.cull)
uniform float apexTol;  // the float32 camera's rounding, in distance units
uniform sampler2D hiz;
uniform int hizLevels;

bool inPyramid(vec3 lo, vec3 hi) {
    float extent = max(max(abs(lo.x), abs(lo.y)), max(max(abs(lo.z), abs(hi.x)), max(abs(hi.y), abs(hi.z))));
    float tol = apexTol + 1e-5 * extent;
    for (int k = 0; k < 4; ++k) {
        vec3 n = planes[k];
        vec3 far = mix(lo, hi, greaterThanEqual(n, vec3(0.0)));
        if (dot(far, n) < -tol) return false;
    }
    return true;
}

bool hidden(vec3 lo, vec3 hi) {
    float aspect = viewport.x / viewport.y;
    vec2 fmin = vec2(1e30), fmax = vec2(-1e30);
    float zmin = 1e30, extent = 0.0;
    for (int c = 0; c < 8; ++c) {
        vec3 q = vec3((c & 1) != 0 ? hi.x : lo.x, (c & 2) != 0 ? hi.y : lo.y, (c & 4) != 0 ? hi.z : lo.z);
        vec3 v = vec3(dot(q, camRight), dot(q, camUp), dot(q, camForward));
        zmin = min(zmin, v.z);
        extent = max(extent, length(q));
        vec2 ndc = v.xy / (max(v.z, 1e-30) * vec2(tanHalfFov * aspect, tanHalfFov));
        vec2 f = (ndc * 0.5 + 0.5) * viewport;  // the pixel-centre coordinate whose ray meets q
        fmin = min(fmin, f);
        fmax = max(fmax, f);
    }
    if (zmin <= 1e-4 * extent) return false;  // reaches the camera plane: its projection is unbounded
    // (clamped before the conversion: a box near the camera plane at a narrow field of view projects
    // beyond the int range, where float -> int is undefined: x86 gives INT_MIN, a wrong rectangle)
    fmin = clamp(fmin, vec2(-1e9), vec2(1e9));
    fmax = clamp(fmax, vec2(-1e9), vec2(1e9));
    ivec2 p0 = ivec2(floor(fmin - 0.5)) - 1, p1 = ivec2(ceil(fmax - 0.5)) + 1;
    ivec2 size0 = ivec2(viewport);
    p0 = clamp(p0, ivec2(0), size0 - 1);
    p1 = clamp(p1, ivec2(0), size0 - 1);
    // the finest level where the rectangle spans at most 2x2 texels: its extent < 2^level (found
    // without a loop, and the level's size computed, not queried: llvmpipe miscompiled a loop
    // feeding textureSize)
    int span = max(p1.x - p0.x, p1.y - p0.y);
    int level = min(span > 0 ? findMSB(span) + 1 : 0, hizLevels - 1);
    ivec2 sz = max(size0 >> level, ivec2(1));
    ivec2 t0 = min(p0 >> level, sz - 1), t1 = min(p1 >> level, sz - 1);
    float farthest = 0.0;
    for (int y = t0.y; y <= t1.y; ++y)
        for (int x = t0.x; x <= t1.x; ++x) farthest = max(farthest, texelFetch(hiz, ivec2(x, y), level).r);
    vec3 gap = max(max(lo, -hi), vec3(0.0));  // the camera is the origin: lo, hi are camera-relative
    float nearest = length(gap) * (1.0 - 1e-5) - apexTol;
    return nearest > farthest * (1.0 + 1e-5);
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= nNodes) return;
    CutNode nd = nodes[i];
    vec3 lo = nd.lo - camPos, hi = nd.hi - camPos;
    bool seen = inPyramid(lo, hi);
    if (phase == 3) {
        visible[i] = (seen && !hidden(lo, hi)) ? 1u : 0u;
        return;
    }
    bool draw = phase == 1 ? (seen && visible[i] != 0u) : (seen && visible[i] == 0u && !hidden(lo, hi));
    cmds[5 * i] = draw ? uint(nd.count) * 3u : 0u;
    cmds[5 * i + 1] = draw ? 1u : 0u;
    cmds[5 * i + 2] = uint(nd.first) * 3u;
    cmds[5 * i + 3] = 0u;
    cmds[5 * i + 4] = 0u;
    if (draw) {
        atomicAdd(stats[2 * (phase - 1)], uint(nd.count));
        atomicAdd(stats[2 * (phase - 1) + 1], 1u);
    }
}

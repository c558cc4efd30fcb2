// The "GLSL" baseline's traversal (CHC+RT Table 2): every ray traverses the whole BVH from the root.
// One main() for both stages that run it (ResumableTraversal, gl_traversal.py): a full-screen
// fragment draw (trace_glsl.frag) or a compute dispatch (trace_glsl.comp). Each stage defines, before
// including this file, TRACE_PIXEL (the ray's pixel), TRACE_OUTSIDE(px) (no pixel of the image: the
// invocation ends), TRACE_KEEP(px) (the pixel keeps the hit it has: ends the
// invocation) and TRACE_WRITE(px, t, id) (its nearest hit so far; inf and -1 for none). Macros, not
// a function: the fragment stage's code stays what it was before the compute stage existed.
//
// Bounded work per invocation: llvmpipe silently ends shader loops after 65,535 loop back-edges per
// invocation (one counter shared by all loops of the shader, per SIMD vector of fragments), which
// would return a miss or a farther hit for rays that need long traversals. So a ray visits at most
// MAX_VISITS nodes per draw; gl_traversal.py (max_visits) derives MAX_VISITS from the largest leaf
// and the stack size so that the worst case over a SIMD vector stays below that limit. A ray
// that is not finished saves its traversal (next node, stack, current hit) in a resume slot, and
// the backend draws again for the unfinished rays (resume = 1) until none is left.
// RESUMABLE 0 (no loop limit, a GPU: MAX_VISITS exceeds the tree's nodes, every ray finishes in
// its first draw) leaves that machinery out: no slot image, counters or saved states are touched.
#include "scene.glsl"
#include "intersect.glsl"
#ifndef MAX_VISITS
#define MAX_VISITS 2048
#endif
#ifndef RESUMABLE
#define RESUMABLE 1
#endif
#define STATE_STRIDE (4 + 2 * STACK_SIZE)
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform int anyHit;
uniform int resume;    // 0: every ray from the root; 1: only the unfinished rays, from their state
uniform int capacity;  // resume slots in ResumeState
#if RESUMABLE
// per pixel: -1 finished (the state between traces), >= 0 its resume slot, -2 unfinished without
// a slot (the buffer was full: it restarts from the root once the buffer has grown)
layout(r32i, binding = BIND_IMG_RESUME) uniform coherent iimage2D resumeSlot;
layout(std430, binding = BIND_RESUME_COUNTERS) buffer ResumeCounters { int unfinished; int allocated; };
// slot s: next node, stack size, hit t (bits), hit id, then (node, entry t bits) per stack entry
layout(std430, binding = BIND_RESUME_STATE) buffer ResumeState { int state[]; };
#endif

void main() {
    ivec2 px = TRACE_PIXEL;
    if (TRACE_OUTSIDE(px)) return;
    int slot = -1;
#if RESUMABLE
    if (resume != 0) {
        slot = imageLoad(resumeSlot, px).r;
        if (slot == -1) TRACE_KEEP(px);  // finished in an earlier draw: keep its hit
    }
#endif
    vec4 ot = texelFetch(rayOrigin, px, 0);
    vec4 dt = texelFetch(rayDir, px, 0);
    TRACE_WRITE(px, uintBitsToFloat(0x7f800000u), -1);
    if (!(dt.w > ot.w)) return;
    RayPre r = prepareRay(ot.xyz, dt.xyz);
    float tmin = ot.w;
    bool any = anyHit != 0;
    Hit hit = Hit(dt.w, -1);
    int stackNode[STACK_SIZE];
    float stackT[STACK_SIZE];
    int sp = 0;
    int ni = 0;
#if RESUMABLE
    if (slot >= 0) {
        int base = slot * STATE_STRIDE;
        ni = state[base];
        sp = state[base + 1];
        hit = Hit(intBitsToFloat(state[base + 2]), state[base + 3]);
        for (int i = 0; i < sp; ++i) {
            stackNode[i] = state[base + 4 + 2 * i];
            stackT[i] = intBitsToFloat(state[base + 5 + 2 * i]);
        }
    }
#endif
    // traverseBVH (intersect.glsl) with a visit budget: nearer child first, any-hit stops at a hit
    bool done = false;
    for (int visits = 0; visits < MAX_VISITS; ++visits) {
        Node nd = loadNode(ni);
        WORK(workNode);
        float tl, tr;
        bool hl = intersectBox(r, nd.lmin, nd.lmax, tmin, hit.t, tl);
        bool hr = intersectBox(r, nd.rmin, nd.rmax, tmin, hit.t, tr);
        // both entered leaf children in one triangle loop (intersect.glsl)
        if (intersectLeafChildren(r, nd, hl, hr, tmin, any, hit) && any) { done = true; break; }
        hl = hl && tl <= hit.t;
        hr = hr && tr <= hit.t;
        if (hl && hr) {
            bool leftFirst = tl <= tr;
            stackNode[sp] = leftFirst ? nd.right : nd.left;
            stackT[sp] = leftFirst ? tr : tl;
            sp = min(sp + 1, STACK_SIZE - 1);
            ni = leftFirst ? nd.left : nd.right;
        } else if (hl) {
            ni = nd.left;
        } else if (hr) {
            ni = nd.right;
        } else {
            bool found = false;
            while (sp > 0) {
                --sp;
                if (stackT[sp] <= hit.t) { ni = stackNode[sp]; found = true; break; }
            }
            if (!found) { done = true; break; }
        }
    }
#if RESUMABLE
    if (!done) {
        atomicAdd(unfinished, 1);
        if (slot < 0) {
            slot = atomicAdd(allocated, 1);
            if (slot >= capacity) slot = -2;
        }
        if (slot >= 0) {
            int base = slot * STATE_STRIDE;
            state[base] = ni;
            state[base + 1] = sp;
            state[base + 2] = floatBitsToInt(hit.t);
            state[base + 3] = hit.id;
            for (int i = 0; i < sp; ++i) {
                state[base + 4 + 2 * i] = stackNode[i];
                state[base + 5 + 2 * i] = floatBitsToInt(stackT[i]);
            }
        }
        imageStore(resumeSlot, px, ivec4(slot));
    } else if (resume != 0) {
        imageStore(resumeSlot, px, ivec4(-1));
    }
#endif
    if (hit.id >= 0) TRACE_WRITE(px, hit.t, hit.id);
    workFlushPixel(0, px);
}

// CHC+RT device front, refinement step 1 (after the pass's draws; over the pair capacity): this
// pass's counts applied to the front for the next pass, as chcrt_pass_gpu.py _refine does on the host. An
// invisible pair that was tested and that more than `threshold` rays entered becomes visible when the
// split rule terminates it, else inner (its children are made by chc_front_write.comp and tested next
// pass); one that no ray entered ages. A visible leaf whose re-query is due and that no ray entered
// (its own count: not one covered by a heavy tile's ancestor) becomes invisible. The split rule
// (chcrt_front.PairFront.classify): object space if A_node / A_root > t_q * 4^-level, unless the node
// is a leaf; a tile at the finest level cannot split, and a subtree over the height or triangle
// limits then splits in object space anyway.
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_NODES) readonly buffer Nodes { ChcNode nodes[]; };
layout(std430, binding = BIND_FR_PAIRS) buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_COUNTS) readonly buffer Counts { uint counts[]; };
layout(std430, binding = BIND_FR_FLAGS) buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int capacity;
uniform int raySlots;
uniform int frontSlot;
uniform int maxLevel;
uniform int threshold;
uniform int frame;
uniform int requeryInterval;
uniform float tQ;
uniform int maxHeight;
uniform int maxTris;
uniform int statBase;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= capacity || i >= meta[16 * frontSlot + META_N]) return;
    ChcPair p = pairs[i];
    int st = pairState(p);
    int bits = flags[i].x;
    int action = 0;
    if (st == CHC_INVISIBLE && (bits & CHC_F_TESTED) != 0) {
        int c = int(counts[raySlots + i]);
        if (c > threshold) {
            p.pixels = c;
            atomicAdd(meta[statBase + STAT_NEWLY_VISIBLE], 1);
            ChcNode nd = nodes[p.node];
            int level = pairLevel(p);
            bool leaf = nd.left < 0;
            bool preferObj = nd.area > ldexp(tQ, -2 * level);  // exact: a power of two (host: the same in float32)
            bool canRay = level < maxLevel;
            bool small = nd.height <= maxHeight && nd.count <= maxTris;
            bool obj = !leaf && (preferObj || (!canRay && !small));
            bool ray = !obj && canRay;
            action = obj ? 2 : (ray ? 4 : 0);
            st = action == 0 ? CHC_VISIBLE : CHC_INNER;
        } else {
            p.age = min(p.age + 1, 0x7fff);
        }
    } else if (st == CHC_VISIBLE && requeryDue(p, frame, requeryInterval)) {
        atomicAdd(meta[statBase + STAT_REQUERIES], 1);
        int c = int(counts[raySlots + i]);
        if (c <= threshold && (bits & CHC_F_LCA_COVERED) == 0) st = CHC_INVISIBLE;
        p.age = 0;
        p.pixels = c;
    }
    if (action != 0) {
        atomicAdd(meta[16 * frontSlot + META_SPLITS], 1);
        atomicAdd(meta[statBase + STAT_SPLITS], 1);
    }
    p.kids = st | (pairKids(p) << 8);
    pairs[i] = p;
    flags[i].y = action;
}

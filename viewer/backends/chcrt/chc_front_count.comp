// CHC+RT device front, plan step 1 (over the front's pairs, ARG_PAIRS): zero each pair's count slot
// and scratch flags; every leaf pair to test this pass (visible, or invisible; in aggressive mode
// an invisible pair only while fresh or due for its re-query, as chcrt_pass_gpu.py _due_slots filters it) is counted
// on each finest tile it covers (a pair of level L covers 4^(maxLevel - L) of them), and widens the
// triangle range of those tiles (their lowest common ancestor, chc_front_plan.comp).
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_NODES) readonly buffer Nodes { ChcNode nodes[]; };
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_TILES) buffer Tiles { ChcTilePlan tiles[]; };
layout(std430, binding = BIND_FR_COUNTS) buffer Counts { uint counts[]; };
layout(std430, binding = BIND_FR_FLAGS) writeonly buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int capacity;
uniform int raySlots;
uniform int frontSlot;
uniform int maxLevel;
uniform int threshold;  // ChcrtParams.visible_threshold
uniform int frame;
uniform int requeryInterval;
uniform int statBase;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= capacity) return;
    counts[raySlots + i] = 0u;
    flags[i] = ivec4(0);
    if (i >= meta[16 * frontSlot + META_N]) return;
    ChcPair p = pairs[i];
    int st = pairState(p);
    if (st != CHC_VISIBLE && st != CHC_INVISIBLE) return;
    if (st == CHC_INVISIBLE && threshold > 0 && !(p.age == 0 || requeryDue(p, frame, requeryInterval))) return;
    atomicAdd(meta[statBase + (st == CHC_VISIBLE ? STAT_PHASE1 : STAT_QUERIES)], 1);
    ChcNode nd = nodes[p.node];
    int s = maxLevel - pairLevel(p);
    int side = 1 << maxLevel;
    int x0 = pairTx(p) << s, y0 = pairTy(p) << s;
    for (int y = y0; y < y0 + (1 << s); ++y) {
        for (int x = x0; x < x0 + (1 << s); ++x) {
            int t = y * side + x;
            if (st == CHC_VISIBLE) atomicAdd(tiles[t].cv, 1); else atomicAdd(tiles[t].ci, 1);
            atomicMin(tiles[t].lo, nd.first);
            atomicMax(tiles[t].hi, nd.first + nd.count);
        }
    }
}

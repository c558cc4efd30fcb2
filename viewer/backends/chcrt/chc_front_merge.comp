// CHC+RT device front, refinement step 2 (over the pair capacity): pull invisibility up one level
// (chcrt_front.PairFront.pull_up with min_age = 1): an inner pair whose children are all invisible
// leaves, each culled by at least one query since it was made (age >= 1), is merged back into one
// invisible leaf (its children are dropped by chc_front_scan/write.comp). Pairs split this pass are
// inner already (chc_front_refine.comp), so their parents do not merge.
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_FLAGS) buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int capacity;
uniform int frontSlot;
uniform int statBase;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= capacity || i >= meta[16 * frontSlot + META_N]) return;
    ChcPair p = pairs[i];
    int k = pairKids(p);
    if (pairState(p) != CHC_INNER || k == 0) return;
    for (int c = p.child; c < p.child + k; ++c) {
        ChcPair q = pairs[c];
        if (pairState(q) != CHC_INVISIBLE || q.age < 1) return;
    }
    flags[i].y |= CHC_F_MERGE;
    atomicAdd(meta[statBase + STAT_PULL_UPS], 1);
}

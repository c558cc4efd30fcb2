// CHC+RT device front, refinement step 4 (over the pair capacity): write the next front into the
// other buffer of the pair (ping-pong) at the indices chc_front_scan.comp gave: parent and child
// links renumbered; a merged pair becomes an invisible leaf (age: its youngest child's, a new
// re-query phase); a split pair becomes inner with its new children (object space: the node's two
// children over the same tile; ray space: the node over the tile's four quadrants), or visible when
// the capacity refused the split. Counts the next front's leaves and inner pairs for the statistics.
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_NODES) readonly buffer Nodes { ChcNode nodes[]; };
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_PAIRS_OUT) writeonly buffer PairsOut { ChcPair pairsOut[]; };
layout(std430, binding = BIND_FR_FLAGS) readonly buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int capacity;
uniform int frontSlot;
uniform int frame;
uniform int requeryInterval;
uniform int seed;
uniform int statBase;

void countState(int st) {
    atomicAdd(meta[statBase + (st == CHC_VISIBLE ? STAT_VISIBLE : (st == CHC_INVISIBLE ? STAT_INVISIBLE : STAT_INNER))], 1);
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    int s = 16 * frontSlot;
    if (i >= capacity || i >= meta[s + META_N_OLD]) return;
    ivec4 f = flags[i];
    if (f.z < 0) return;  // a child of a merged pair
    bool over = (meta[s + META_WANTED] > meta[s + META_N]);
    ChcPair p = pairs[i];
    int j = f.z;
    int st = pairState(p), k = pairKids(p);
    ChcPair o = p;
    o.parent = p.parent >= 0 ? flags[p.parent].z : -1;
    int action = f.y & 7;
    if ((f.y & CHC_F_MERGE) != 0) {
        int age = 0x7fff;
        for (int c = p.child; c < p.child + k; ++c) age = min(age, pairs[c].age);
        o.age = age;
        o.child = -1;
        o.kids = CHC_INVISIBLE;
        o.offset = randomPhase(seed, frame, j, requeryInterval);
    } else if (action != 0 && over) {
        o.kids = CHC_VISIBLE;  // no room for the children: terminated here (exact, a larger subtree)
    } else if (action != 0) {
        o.child = f.w;
        o.kids = CHC_INNER | (action << 8);
        int level = pairLevel(p), tx = pairTx(p), ty = pairTy(p);
        ChcNode nd = nodes[p.node];
        for (int c = 0; c < action; ++c) {
            ChcPair q;
            q.node = action == 2 ? (c == 0 ? nd.left : nd.right) : p.node;
            q.tile = action == 2 ? p.tile : packTile(level + 1, 2 * tx + (c & 1), 2 * ty + (c >> 1));
            q.parent = j;
            q.child = -1;
            q.kids = CHC_INVISIBLE;
            q.offset = randomPhase(seed, frame, f.w + c, requeryInterval);
            q.pixels = 0;
            q.age = 0;
            pairsOut[f.w + c] = q;
            countState(CHC_INVISIBLE);
        }
    } else if (st == CHC_INNER) {
        o.child = flags[p.child].z;
    }
    pairsOut[j] = o;
    countState(pairState(o));
}

// CHC+RT device front, plan step 4 (indirect: one invocation per listed (pair, tile)): each listed pair
// takes its rank among its tile's list (by pair index: the order no longer depends on the scatter's
// atomics, so records and traversal order are the same in every run) and writes its intersection
// item there, with its count slot: the pair itself, or -1 for a visible pair whose re-query is not
// due (countDueOnly, chcrt_pass_gpu.py _due_slots). Heavy tiles' ancestor items were written by the plan.
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_NODES) readonly buffer Nodes { ChcNode nodes[]; };
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_TILES) readonly buffer Tiles { ChcTilePlan tiles[]; };
layout(std430, binding = BIND_FR_TMP) readonly buffer Tmp { ivec2 tmp[]; };
layout(std430, binding = BIND_FR_VIS_ITEMS) writeonly buffer VisItems { ChcItem visItems[]; };
layout(std430, binding = BIND_FR_INV_ITEMS) writeonly buffer InvItems { ChcItem invItems[]; };
layout(std430, binding = BIND_FR_ARGS) readonly buffer Args { uint args[]; };
uniform int visCap;
uniform int frame;
uniform int requeryInterval;
uniform int countDueOnly;

void main() {
    int e = int(gl_GlobalInvocationID.x);
    int nv = int(args[256]), ni = int(args[257]);
    if (e >= nv + ni) return;
    bool vis = e < nv;
    int q = vis ? e : visCap + (e - nv);
    ivec2 pt = tmp[q];
    if (pt.x < 0) return;  // a heavy tile's ancestor item
    ChcTilePlan tp = tiles[pt.y];
    int base = vis ? tp.visBase : visCap + tp.invBase;
    int count = vis ? tp.visCount : tp.invCount;
    int rank = 0;
    for (int k = 0; k < count; ++k) rank += tmp[base + k].x < pt.x ? 1 : 0;
    ChcPair p = pairs[pt.x];
    if (vis) {
        int slot = (countDueOnly != 0 && !requeryDue(p, frame, requeryInterval)) ? -1 : pt.x;
        visItems[tp.visBase + rank] = nodeItem(nodes[p.node], p.node, slot);
    } else {
        invItems[tp.invBase + rank] = nodeItem(nodes[p.node], p.node, pt.x);
    }
}

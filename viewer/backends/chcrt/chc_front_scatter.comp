// CHC+RT device front, plan step 3 (over the front's pair capacity): every leaf pair tested this pass
// (the same filter as chc_front_count.comp) is listed, as (pair, tile), on each finest tile it covers
// that is not heavy: the visible pairs in the tile's visible range, the invisible ones in its invisible
// range (after visCap), in any order (chc_front_items.comp orders them). Flags: an invisible pair
// listed somewhere was tested (its count decides it); a visible pair over a heavy tile was covered
// by that tile's ancestor traversal (its own count is then not its own, chcrt_pass_gpu.py lca_covered).
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_TILES) buffer Tiles { ChcTilePlan tiles[]; };
layout(std430, binding = BIND_FR_TMP) writeonly buffer Tmp { ivec2 tmp[]; };
layout(std430, binding = BIND_FR_FLAGS) buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) readonly buffer Meta { int meta[]; };
uniform int capacity;
uniform int frontSlot;
uniform int maxLevel;
uniform int threshold;
uniform int frame;
uniform int requeryInterval;
uniform int visCap;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= capacity || i >= meta[16 * frontSlot + META_N]) return;
    ChcPair p = pairs[i];
    int st = pairState(p);
    if (st != CHC_VISIBLE && st != CHC_INVISIBLE) return;
    if (st == CHC_INVISIBLE && threshold > 0 && !(p.age == 0 || requeryDue(p, frame, requeryInterval))) return;
    int s = maxLevel - pairLevel(p);
    int side = 1 << maxLevel;
    int x0 = pairTx(p) << s, y0 = pairTy(p) << s;
    int bits = 0;
    for (int y = y0; y < y0 + (1 << s); ++y) {
        for (int x = x0; x < x0 + (1 << s); ++x) {
            int t = y * side + x;
            if (tiles[t].heavy != 0) {
                if (st == CHC_VISIBLE) bits |= CHC_F_LCA_COVERED;
            } else if (st == CHC_VISIBLE) {
                tmp[tiles[t].visBase + atomicAdd(tiles[t].visFill, 1)] = ivec2(i, t);
            } else {
                tmp[visCap + tiles[t].invBase + atomicAdd(tiles[t].invFill, 1)] = ivec2(i, t);
                bits |= CHC_F_TESTED;
            }
        }
    }
    flags[i].x = bits;
}

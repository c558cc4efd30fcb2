// CHC+RT device front, first dispatch of a steady pass (chcrt_devfront.py): zero the finest tiles'
// plans (the triangle range starts empty), the ray-count slots the init draw counts into, and the
// pass's extra count slots (query pixels, records drawn, kept pairs) after the pairs' slots, and the
// survivors' indirect draw command (keepCull: a later sample pass that takes its frame's first pass's
// cull keeps the ray counts, the three slots and the command that pass left; keepRays: one whose rays
// an earlier pass of the frame counted keeps the ray counts; chcrt_pass_device.py). The
// pairs' own count slots are zeroed by chc_front_count.comp; the front's overflow bits, work probe and
// refinement's splits are reset (resetMeta: by the frame's first pass of the front only, so that a
// shared front's later sample passes keep what the first one measured and found), and the per-pair
// steps' dispatch is sized (ARG_PAIRS).
// Nothing crosses the host.
layout(local_size_x = 64) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_TILES) writeonly buffer Tiles { ChcTilePlan tiles[]; };
layout(std430, binding = BIND_FR_COUNTS) writeonly buffer Counts { uint counts[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
// the survivors' indirect draw (chc_querycull.comp adds its instances)
layout(std430, binding = BIND_FR_SURVIVOR_CMD) writeonly buffer SurvivorCmd { uint cmd[4]; };
layout(std430, binding = BIND_FR_ARGS) writeonly buffer Args { uint args[]; };
uniform int nTiles;
uniform int frontSlot;  // 0: no front (a full-BVH pass)
uniform int capacity;  // pair slots: the pass's extra slots follow them
uniform int raySlots;  // ray-count slots at the start of the counts buffer (chcrt_layout.COUNT_SLOTS)
uniform int resetMeta;  // 1: zero the front's overflow bits, work probe and splits (0: a later sample pass)
uniform int keepCull;  // 1: keep the ray counts, the pass's three slots and the survivors' command
uniform int keepRays;  // 1: keep the ray counts

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i < nTiles) {
        ChcTilePlan t;
        t.cv = 0; t.ci = 0; t.lo = 0x7fffffff; t.hi = 0; t.heavy = 0; t.lca = -1;
        t.visBase = 0; t.visCount = 0; t.invBase = 0; t.invCount = 0; t.visFill = 0; t.invFill = 0;
        t.recBase = 0; t.nrec = 0; t.keptBase = 0; t.keptCount = 0;
        tiles[i] = t;
    }
    if (i < raySlots && keepCull == 0 && keepRays == 0) counts[i] = 0u;
    if (i < 3 && keepCull == 0) counts[raySlots + capacity + i] = 0u;
    if (i == 0) {
        if (frontSlot > 0) {
            // the per-pair steps' dispatch: the front's pairs now (the scan of the refinement changes
            // META_N last, and the write after it reads the old count)
            args[ARG_PAIRS] = uint(max((meta[16 * frontSlot + META_N] + 63) / 64, 1));
            args[ARG_PAIRS + 1] = 1u;
            args[ARG_PAIRS + 2] = 1u;
            if (resetMeta != 0) {
                meta[16 * frontSlot + META_OVERFLOW] = 0;  // this frame's overflows only
                meta[16 * frontSlot + META_PROBE_FRONT] = 0;  // and its work probe (if it runs one)
                meta[16 * frontSlot + META_PROBE_FULL] = 0;
                meta[16 * frontSlot + META_PROBE_RAYS] = 0;
                meta[16 * frontSlot + META_SPLITS] = 0;  // and its refinement's splits
            }
        }
        if (keepCull == 0) { cmd[0] = 6u; cmd[1] = 0u; cmd[2] = 0u; cmd[3] = 0u; }
    }
}

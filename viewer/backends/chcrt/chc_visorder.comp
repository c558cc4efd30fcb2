// CHC+RT, GPU-driven pass, before the visible pairs' draw (ChcrtParams.gap_order): per record of that
// draw (one finest tile's visible subtrees, info.w = the tile), each item gets its gap, a lower bound
// of the distance from every ray origin of the tile (chc_tilebounds.comp, run just before) to its
// box, and the record's items are sorted by it, nearest first. A ray then stops testing the record's
// boxes at the first one beyond its nearest hit so far (chc_intersect.frag): with the hit hint that
// is its hit already. Only the order changes: the ray still traverses what it enters nearest first.
// With coneCull, items beside the tile's rays (outside its direction cone or behind a side plane,
// chc_tilecone.glsl: no ray of the tile can enter them) are dropped and the record's count lowered (a record left empty draws nothing): a pair visible over a
// coarser tile is copied onto every finest tile under it, also those whose rays pass beside it.
layout(local_size_x = 64) in;
#include "chc_tilecone.glsl"
#include "chc_records.glsl"
layout(std430, binding = BIND_CHC_ITEMS) buffer ChcItems { ChcItem items[]; };
layout(std430, binding = BIND_CHC_DRAWS) buffer ChcDraws { ChcDraw draws[]; };
layout(std430, binding = BIND_CHC_TILES) readonly buffer ChcTiles { TileBound tiles[]; };
#ifdef CHC_RECORDS_IN_BUFFER
// device fronts (chcrt_devfront.py): the record count is the indirect draw's instance count
layout(std430, binding = BIND_CHC_INDIRECT) readonly buffer VisCmd { uint vCount; uint vInstances; uint vFirst;
                                                                     uint vBase; };
#define N_RECORDS int(vInstances)
#else
uniform int nRecords;
#define N_RECORDS nRecords
#endif
#ifdef CHC_MERGE_KEPT  // (chcrt.py sets it for the device fronts' variant only)
// merge_kept: a record that carries its tile's merged kept pairs (chc_querycull.comp, run before;
// chc_front.glsl keptCarrier) still draws when none of its own items is left: its fragments test
// the kept pairs
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_TILES) readonly buffer TilePlans { ChcTilePlan plans[]; };
#define KEPT_PAIRS(tile, record) (keptCarrier(plans[tile], record) ? plans[tile].keptCount : 0)
#else
#define KEPT_PAIRS(tile, record) 0
#endif
uniform int coneCull;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= N_RECORDS) return;
    ChcDraw d = draws[i];
    TileBound t = tiles[d.info.w];
    bool live = t.omax.w > 0.0;  // the tile has active rays (else its origin box is empty)
    int base = d.info.x;
    int kept = 0;
    for (int k = 0; k < d.info.y; ++k) {
        ChcItem it = items[base + k];
        bool beside = live && coneCull != 0 && !(tileCone(it.bmin, it.bmax, t) && tileSides(it.bmin, it.bmax, t));
        if (beside) continue;
        it.gap = live ? tileGap(it.bmin, it.bmax, t) : 0.0;
        int m = base + kept++;
        while (m > base && items[m - 1].gap > it.gap) { items[m] = items[m - 1]; --m; }
        items[m] = it;
    }
    if (kept < d.info.y) {
        draws[i].info.y = kept;
        if (kept == 0 && KEPT_PAIRS(d.info.w, i) == 0) draws[i].rect.zw = ivec2(0);
    }
}

// CHC+RT, GPU-driven pass, step 2: one invocation per cull tile (a finest pair tile, or one of its
// sub-tiles: ChcrtParams.cull_sublevels). Of the invisible pairs whose tile covers it (the host copies
// each pair onto the finest tiles of its tile; a sub-tile reads its finest tile's range), only those whose box
// some ray of the tile may still enter are kept: a box farther from every ray origin of the tile
// than the farthest distance a ray of the tile may still reach (chc_tilebounds.comp) cannot be
// entered. The kept pairs of a tile become records of at most maxItems pairs of ONE indirect
// instanced intersection draw (chc_intersect.frag with CHC_COUNT_ITEMS), each item keeping its
// pair's count slot. Conservative: the gap between the origin box and a pair's box is a lower bound
// of every ray's entry distance; a relative margin covers the rounding. With coneCull, a box that
// lies beside every ray of the tile (outside its direction cone, or behind a side plane:
// chc_tilecone.glsl) is dropped too.
//
// mergeKept (device fronts, cull tiles = finest tiles): the cull runs before the visible pairs' draw,
// and a tile with a visible record and at most maxItems kept pairs gets no survivors' record: its
// kept range goes into its tile plan (keptBase, keptCount), and the fragments of its last visible
// record (its carrier, chc_front.glsl keptCarrier: the one with the fewest own items) test those
// pairs after their own (chc_intersect.frag), one fragment per ray instead of two. The reach is
// then what the rays had before the visible pairs (their tmax): a weaker cull, but each ray still
// stops at the first kept box beyond its nearest hit so far. (In a tile of several records that
// hit need not include the other records' hits, whose fragments may run at the same time: a kept
// pair may count rays that another record's hit occludes, as a visible pair of such a tile
// already may; the counts can only keep more pairs visible, the hits stay exact.)
// mergeAll (mergeKept with the visible records in a compute dispatch, chc_visible.comp): every tile's kept
// range goes into its plan, and that dispatch traces it after the tile's records, in chunks of
// maxItems: no survivors' record, so no pair is intersected in a fragment shader.
layout(local_size_x = 64) in;
#include "chc_tilecone.glsl"
#include "chc_records.glsl"
layout(std430, binding = BIND_CHC_ITEMS) readonly buffer ChcItems { ChcItem items[]; };
layout(std430, binding = BIND_CHC_QUERIES) readonly buffer ChcQueries { ChcDraw queries[]; };
layout(std430, binding = BIND_CHC_TILES) readonly buffer ChcTiles { TileBound tiles[]; };
layout(std430, binding = BIND_CHC_DRAWS) writeonly buffer ChcSurvivors { ChcDraw survivors[]; };
// the kept boxes (the candidates' binding point: candidates are uploaded after the query draw)
layout(std430, binding = BIND_CHC_CANDIDATES) buffer ChcKeptBoxes { ChcItem kept[]; };
#ifdef CHC_MERGE_KEPT
// mergeKept: the finest tiles' plans (chc_front_plan.comp), where a merged tile's kept range goes
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_TILES) buffer TilePlans { ChcTilePlan plans[]; };
uniform int mergeKept;  // 1: merge into tiles' last visible records (cull tile i = finest tile i)
uniform int mergeAll;  // 1 (with mergeKept; visible_stage=compute): every tile's kept range goes into its plan,
                       // whatever its records and its count: chc_visible.comp traces it after the records
#endif
layout(std430, binding = BIND_CHC_INDIRECT) buffer ChcIndirect { uint cmdCount; uint cmdInstances; uint cmdFirst;
                                                                 uint cmdBase; };
// slots pixelSlot .. pixelSlot + 2 of the query counts: pair tests x pixels and records drawn (stats),
// kept pairs
layout(std430, binding = BIND_CHC_QUERY_COUNTS) buffer ChcQueryCounts { uint chcPassed[]; };
uniform int pixelSlot;
uniform int nQueries;
uniform int maxItems;  // items per intersection record (CHC_MAX_ITEMS of the intersection program)
uniform int cull;  // 0: keep every box (ChcrtParams.coarse_cull off)
uniform int sortByGap;  // 0: no gaps (-1: no ray stops early), kept in input order (ChcrtParams.gap_order off)

uniform int coneCull;  // 1: also drop boxes beside the tile's rays: cone and side planes (ChcrtParams.cone_cull)
uniform int keptOffset;  // kept pairs go to kept[keptOffset + ...] (records and plans hold that index)

float gapOf(ChcItem it, TileBound t) { return tileGap(it.bmin, it.bmax, t); }

bool reachable(ChcItem it, TileBound t) {
    if (cull == 0) return true;
    if (gapOf(it, t) > t.omin.w * (1.0 + 1e-4)) return false;  // beyond every ray's reach
    return coneCull == 0 || (tileCone(it.bmin, it.bmax, t) && tileSides(it.bmin, it.bmax, t));
}

void main() {
    int i = int(gl_GlobalInvocationID.x);  // cull tile i = ty * 2^level + tx (chc_tilebounds.comp)
    if (i >= nQueries) return;
    ChcDraw q = queries[i];  // the cull tile's rectangle; info.x, info.y = its finest tile's pair items
#ifdef CHC_MERGE_KEPT
    // (a pass that takes an earlier pass's plan, share_sample_fronts, finds that pass's merged range)
    if (mergeKept != 0) plans[i].keptCount = 0;
#endif
    TileBound t = tiles[i];
    if (q.info.y == 0 || t.omax.w <= 0.0 || t.omin.w < 0.0) return;  // no ray here may still hit
    int nb = 0;
    for (int k = 0; k < q.info.y; ++k) nb += reachable(items[q.info.x + k], t) ? 1 : 0;
    if (nb == 0) return;
    int base = int(atomicAdd(chcPassed[pixelSlot + 2], uint(nb)));
    // the kept pairs sorted by gap, nearest first (insertion sort; a tile keeps at most lca_pairs or so),
    // so that a ray stops testing a record's boxes at the first one beyond its nearest hit
    // (chc_intersect.frag)
    base += keptOffset;
    int j = base;
    for (int k = 0; k < q.info.y; ++k) {
        ChcItem it = items[q.info.x + k];
        if (!reachable(it, t)) continue;
        it.gap = sortByGap != 0 ? gapOf(it, t) : -1.0;
        int m = j++;
        while (m > base && kept[m - 1].gap > it.gap) { kept[m] = kept[m - 1]; --m; }
        kept[m] = it;
    }
#ifdef CHC_MERGE_KEPT
    if (mergeKept != 0 && ((plans[i].nrec >= 1 && nb <= maxItems) || mergeAll != 0)) {
        plans[i].keptBase = base;
        plans[i].keptCount = nb;
        atomicAdd(chcPassed[pixelSlot], uint(q.rect.z * q.rect.w * nb));  // query tests (overlay)
        return;
    }
#endif
    for (int b = 0; b < nb; b += maxItems) {  // records of at most maxItems pairs (the shader's bound)
        int m = min(maxItems, nb - b);
        survivors[atomicAdd(cmdInstances, 1u)] = ChcDraw(q.rect, ivec4(base + b, m, 1, 0));
        atomicAdd(chcPassed[pixelSlot], uint(q.rect.z * q.rect.w * m));  // query tests (overlay)
        atomicAdd(chcPassed[pixelSlot + 1], 1u);
    }
}

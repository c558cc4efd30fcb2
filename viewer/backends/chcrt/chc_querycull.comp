// CHC+RT, GPU-driven pass, step 2: one invocation per group of invisible pairs of one tile (a
// CHC++ multi-query). The group is split onto the finest tiles it covers; on each, only the pairs
// whose box some ray of that tile may still enter are kept: a box farther from every ray origin of
// the tile than the farthest distance a ray of the tile may still reach (chc_tilebounds.comp)
// cannot be entered. A finest tile with pairs left becomes one record of ONE indirect instanced
// intersection draw (chc_intersect.frag with CHC_COUNT_ITEMS) with its own compacted item list;
// each item keeps its pair's count slot. Conservative: the gap between the origin box and a pair's
// box is a lower bound of every ray's entry distance; a relative margin covers the rounding.
layout(local_size_x = 64) in;
struct ChcDraw { ivec4 rect; ivec4 info; };  // info.w = level << 24 | tx << 12 | ty of the query's tile
struct ChcItem { vec3 bmin; int ref; vec3 bmax; int count; int id; int p0; int p1; int p2; };
struct TileBound { vec4 omin; vec4 omax; };
layout(std430, binding = BIND_CHC_ITEMS) readonly buffer ChcItems { ChcItem items[]; };
layout(std430, binding = BIND_CHC_QUERIES) readonly buffer ChcQueries { ChcDraw queries[]; };
layout(std430, binding = BIND_CHC_TILES) readonly buffer ChcTiles { TileBound tiles[]; };
layout(std430, binding = BIND_CHC_DRAWS) writeonly buffer ChcSurvivors { ChcDraw survivors[]; };
// the kept boxes (the candidates' binding point: candidates are uploaded after the query draw)
layout(std430, binding = BIND_CHC_CANDIDATES) writeonly buffer ChcKeptBoxes { ChcItem kept[]; };
layout(std430, binding = BIND_CHC_INDIRECT) buffer ChcIndirect { uint cmdCount; uint cmdInstances; uint cmdFirst;
                                                                 uint cmdBase; };
// slots pixelSlot .. pixelSlot + 2 of the query counts: pixels and records drawn (stats), kept boxes
layout(std430, binding = BIND_CHC_QUERY_COUNTS) buffer ChcQueryCounts { uint chcPassed[]; };
uniform int pixelSlot;
uniform int nQueries;
uniform int level;  // finest tile level
uniform ivec2 raySize;
uniform int cull;  // 0: keep every box (ChcrtParams.coarse_cull off)

bool reachable(ChcItem it, TileBound t) {
    if (cull == 0) return true;
    vec3 gap = max(max(it.bmin - t.omax.xyz, t.omin.xyz - it.bmax), vec3(0.0));
    return length(gap) * (1.0 - 1e-4) <= t.omin.w * (1.0 + 1e-4);
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= nQueries) return;
    ChcDraw q = queries[i];
    int ql = q.info.w >> 24, qx = (q.info.w >> 12) & 4095, qy = q.info.w & 4095;
    int s = level - ql, n = 1 << level;
    for (int y = qy << s; y < (qy + 1) << s; ++y) {
        for (int x = qx << s; x < (qx + 1) << s; ++x) {
            TileBound t = tiles[y * n + x];
            if (t.omax.w <= 0.0 || t.omin.w < 0.0) continue;  // no ray in this tile may still hit
            int nb = 0;
            for (int k = 0; k < q.info.y; ++k) nb += reachable(items[q.info.x + k], t) ? 1 : 0;
            if (nb == 0) continue;
            int base = int(atomicAdd(chcPassed[pixelSlot + 2], uint(nb)));
            int j = base;
            for (int k = 0; k < q.info.y; ++k) {
                ChcItem it = items[q.info.x + k];
                if (reachable(it, t)) kept[j++] = it;
            }
            ivec2 lo = (ivec2(x, y) * raySize) >> level;
            ivec2 hi = (ivec2(x + 1, y + 1) * raySize) >> level;
            survivors[atomicAdd(cmdInstances, 1u)] = ChcDraw(ivec4(lo, hi - lo), ivec4(base, nb, q.info.z, q.info.w));
            atomicAdd(chcPassed[pixelSlot], uint((hi.x - lo.x) * (hi.y - lo.y)));
            atomicAdd(chcPassed[pixelSlot + 1], 1u);
        }
    }
}

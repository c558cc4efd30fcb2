// CHC+RT, GPU-driven queries, step 2: one invocation per query record. A query whose boxes all lie
// farther from every ray origin of its tile than the farthest distance a ray of the tile may still
// reach (chc_tilebounds.comp) cannot pass: it is culled here, without a fragment. The others are
// appended to the records of ONE indirect instanced query draw. Conservative: the gap between the
// origin box and a query box is a lower bound of every ray's entry distance; a relative margin
// covers the rounding of both sides.
layout(local_size_x = 64) in;
struct ChcDraw { ivec4 rect; ivec4 info; };  // info.w = level << 24 | tx << 12 | ty of the query's tile
struct ChcItem { vec3 bmin; int ref; vec3 bmax; int count; int id; int p0; int p1; int p2; };
struct TileBound { vec4 omin; vec4 omax; };
layout(std430, binding = BIND_CHC_ITEMS) readonly buffer ChcItems { ChcItem items[]; };
layout(std430, binding = BIND_CHC_QUERIES) readonly buffer ChcQueries { ChcDraw queries[]; };
layout(std430, binding = BIND_CHC_TILES) readonly buffer ChcTiles { TileBound tiles[]; };
layout(std430, binding = BIND_CHC_DRAWS) writeonly buffer ChcSurvivors { ChcDraw survivors[]; };
layout(std430, binding = BIND_CHC_INDIRECT) buffer ChcIndirect { uint cmdCount; uint cmdInstances; uint cmdFirst;
                                                                 uint cmdBase; };
// slots pixelSlot, pixelSlot + 1 of the query counts: pixels and number of the queries drawn (stats)
layout(std430, binding = BIND_CHC_QUERY_COUNTS) buffer ChcQueryCounts { uint chcPassed[]; };
uniform int pixelSlot;
uniform int nQueries;
uniform int level;  // finest tile level
void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= nQueries) return;
    ChcDraw q = queries[i];
    int ql = q.info.w >> 24, qx = (q.info.w >> 12) & 4095, qy = q.info.w & 4095;
    int s = level - ql, n = 1 << level;
    vec3 omin = vec3(3.0e38), omax = vec3(-3.0e38);
    float dmax = -1.0;
    for (int y = qy << s; y < (qy + 1) << s; ++y) {
        for (int x = qx << s; x < (qx + 1) << s; ++x) {
            TileBound t = tiles[y * n + x];
            if (t.omax.w > 0.0) {
                omin = min(omin, t.omin.xyz);
                omax = max(omax, t.omax.xyz);
                dmax = max(dmax, t.omin.w);
            }
        }
    }
    if (dmax < 0.0) return;  // no active ray in the tile
    float reach = dmax * (1.0 + 1e-4);
    for (int k = 0; k < q.info.y; ++k) {
        ChcItem it = items[q.info.x + k];
        vec3 gap = max(max(it.bmin - omax, omin - it.bmax), vec3(0.0));
        if (length(gap) * (1.0 - 1e-4) <= reach) {
            survivors[atomicAdd(cmdInstances, 1u)] = q;
            atomicAdd(chcPassed[pixelSlot], uint(q.rect.z * q.rect.w));
            atomicAdd(chcPassed[pixelSlot + 1], 1u);
            return;
        }
    }
}

// CHC+RT device front, plan step 2 (one work group): per finest tile, whether it traverses the
// lowest common ancestor of all its pairs (a "heavy" tile: over lcaSubtrees visible pairs or
// lcaPairs pairs in all, chcrt_pass.py _heavy_tiles) and that ancestor (the deepest node whose triangle
// range holds the tile's), where its items go in the visible and invisible item lists (prefix sums
// in tile order), its visible records (at most maxBatch items each, in tile order), the cull tiles'
// ranges over the invisible items, and the indirect draw and dispatch arguments of the pass. Items
// over their capacity (the host sizes it from earlier passes' copies, a front at most doubles per
// pass) make every tile heavy: one ancestor item per tile, still exact.
layout(local_size_x = 256) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_NODES) readonly buffer Nodes { ChcNode nodes[]; };
// coherent: the cull ranges below read other invocations' tile plans (memoryBarrierBuffer + barrier)
layout(std430, binding = BIND_FR_TILES) coherent buffer Tiles { ChcTilePlan tiles[]; };
layout(std430, binding = BIND_FR_VIS_ITEMS) writeonly buffer VisItems { ChcItem visItems[]; };
layout(std430, binding = BIND_FR_RECORDS) writeonly buffer Records { ChcDraw records[]; };
layout(std430, binding = BIND_FR_CULL) writeonly buffer Cull { ChcDraw cullTiles[]; };
layout(std430, binding = BIND_FR_ARGS) buffer Args { uint args[]; };
layout(std430, binding = BIND_FR_TMP) writeonly buffer Tmp { ivec2 tmp[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int nTiles;
uniform int maxLevel;
uniform ivec2 raySize;
uniform int maxBatch;
uniform int lcaPairs;     // 0: no limit
uniform int lcaSubtrees;  // 0: no limit
uniform int heavyAllowed;  // 0: no tile takes the LCA (primary rays without lca_primary)
uniform int visCap;
uniform int invCap;
uniform int recCap;
uniform int cullSub;  // cull tiles are this many levels below the finest tiles
uniform int frontSlot;
uniform int statBase;  // META slot of the statistics: 0 = the frame's, else a slot nobody reads

shared int sVis[256];
shared int sInv[256];
shared int sRec[256];
shared int sHeavy[256];
shared int sCopies[256];
shared int sForce;

bool heavyTile(int cv, int ci, bool force) {
    if (cv + ci == 0) return false;
    if (force) return true;
    if (heavyAllowed == 0) return false;
    return (lcaSubtrees > 0 && cv > lcaSubtrees) || (lcaPairs > 0 && cv + ci > lcaPairs);
}

// deepest node whose triangle range holds [lo, hi): walk down from the root
int lowestCommonAncestor(int lo, int hi) {
    int a = 0;
    for (int depth = 0; depth < 4096; ++depth) {
        ChcNode nd = nodes[a];
        if (nd.left < 0) break;
        ChcNode l = nodes[nd.left];
        ChcNode r = nodes[nd.right];
        if (l.first <= lo && l.first + l.count >= hi) a = nd.left;
        else if (r.first <= lo && r.first + r.count >= hi) a = nd.right;
        else break;
    }
    return a;
}

void main() {
    int li = int(gl_LocalInvocationIndex);
    int per = (nTiles + 255) / 256;
    int t0 = min(nTiles, li * per), t1 = min(nTiles, t0 + per);
    if (li == 0) sForce = 0;
    for (int pass = 0; pass < 2; ++pass) {  // a second pass only when the items overflow
        barrier();
        bool force = sForce != 0;
        int vis = 0, inv = 0, rec = 0, heavy = 0, copies = 0;
        for (int t = t0; t < t1; ++t) {
            int cv = tiles[t].cv, ci = tiles[t].ci;
            bool h = heavyTile(cv, ci, force);
            int vc = h ? 1 : cv;
            vis += vc;
            inv += h ? 0 : ci;
            rec += (vc + maxBatch - 1) / maxBatch;
            heavy += h ? 1 : 0;
            copies += cv + ci;
        }
        sVis[li] = vis; sInv[li] = inv; sRec[li] = rec; sHeavy[li] = heavy; sCopies[li] = copies;
        barrier();
        if (li == 0) {  // exclusive prefix sums over the 256 ranges of tiles
            int av = 0, ai = 0, ar = 0, ah = 0, ac = 0;
            for (int k = 0; k < 256; ++k) {
                int v = sVis[k], n = sInv[k], r = sRec[k];
                sVis[k] = av; sInv[k] = ai; sRec[k] = ar;
                av += v; ai += n; ar += r; ah += sHeavy[k]; ac += sCopies[k];
            }
            if (!force) {
                meta[16 * frontSlot + META_HEAVY] = ah;
                meta[16 * frontSlot + META_COPIES] = ac;
                meta[16 * frontSlot + META_TILES] = nTiles;
            }
            if (!force && (av > visCap || ai > invCap || ar > recCap)) {
                sForce = 1;
                meta[16 * frontSlot + META_OVERFLOW] |= 2;
                atomicAdd(meta[statBase + STAT_OVERFLOWS], 1);
            } else {
                sForce = force ? 2 : 3;  // done
                args[0] = 6u; args[1] = uint(ar); args[2] = 0u; args[3] = 0u;  // visible records: indirect draw
                args[128] = uint((ar + 63) / 64); args[129] = 1u; args[130] = 1u;  // chc_visorder.comp
                args[192] = uint((av + ai + 63) / 64); args[193] = 1u; args[194] = 1u;  // chc_front_items.comp
                args[256] = uint(av); args[257] = uint(ai);
                meta[statBase + STAT_LCA_TILES] += ah;
                meta[statBase + STAT_SCHEDULED] += av;
                meta[statBase + STAT_BATCHES] += ar;
            }
        }
        barrier();
        if (sForce != 1) break;
    }
    bool force = sForce == 2;
    int vb = sVis[li], ib = sInv[li], rb = sRec[li];
    int side = 1 << maxLevel;
    for (int t = t0; t < t1; ++t) {
        ChcTilePlan tp = tiles[t];
        bool h = heavyTile(tp.cv, tp.ci, force);
        int vc = h ? 1 : tp.cv, ic = h ? 0 : tp.ci, nr = (vc + maxBatch - 1) / maxBatch;
        tp.heavy = h ? 1 : 0;
        tp.visBase = vb; tp.visCount = vc; tp.invBase = ib; tp.invCount = ic; tp.recBase = rb; tp.nrec = nr;
        tp.visFill = 0; tp.invFill = 0;
        if (h) {
            tp.lca = lowestCommonAncestor(tp.lo, tp.hi);
            visItems[vb] = nodeItem(nodes[tp.lca], tp.lca, -1);  // not counted (chcrt_pass_gpu.py _tile_plan)
            tmp[vb] = ivec2(-1, t);  // chc_front_items.comp: nothing to place here
        }
        ivec4 rect = tileRect(maxLevel, t % side, t / side, raySize);
        for (int r = 0; r < nr; ++r) {
            records[rb + r] = ChcDraw(rect, ivec4(vb + r * maxBatch, min(maxBatch, vc - r * maxBatch), 0, t));
        }
        tiles[t] = tp;
        vb += vc; ib += ic; rb += nr;
    }
    memoryBarrierBuffer();  // the tile plans written above, visible to the whole group after the barrier
    barrier();
    // the cull tiles (cullSub levels below the finest): each reads its finest tile's invisible items
    int cl = maxLevel + cullSub;
    int m = 1 << cl;
    for (int c = li; c < m * m; c += 256) {
        int sx = c % m, sy = c / m;
        int parent = (sy >> cullSub) * side + (sx >> cullSub);
        cullTiles[c] = ChcDraw(tileRect(cl, sx, sy, raySize), ivec4(tiles[parent].invBase, tiles[parent].invCount, 0, 0));
    }
}

// CHC+RT device-resident fronts (chcrt_devfront.py): the records every chc_front_*.comp shares.
// Layouts match chcrt_devfront.py's NODE_DTYPE, PAIR_DTYPE, TILE_BYTES and META slots.
#include "chc_records.glsl"

// Per canonical BVH node (NodeTables): its box, what an intersection item needs (ref: GPU inner-node
// index, or first triangle of a leaf; gcount: 0 for inner nodes, triangles of a leaf), the children
// (-1: leaf), the subtree's triangle range [first, first + count) in leaf order (ranges nest, so the
// deepest node whose range holds a set of ranges is their lowest common ancestor), and what the
// split rule reads (height, surface area / the root's).
struct ChcNode { vec3 bmin; int ref; vec3 bmax; int gcount; int left; int right; int first; int count;
                 int height; float area; int pad0; int pad1; };

// One query pair (screen tile, BVH node) of the pair hierarchy (chcrt_front.PairFront's fields):
// tile = level << 24 | ty << 12 | tx; kids = state | nchild << 8 (children are contiguous from
// `child`); offset = re-query phase of a visible leaf; pixels = rays counted at its last query;
// age = consecutive passes it was tested and found invisible.
struct ChcPair { int node; int tile; int parent; int child; int kids; int offset; int pixels; int age; };

// Per finest screen tile, one pass's plan (zeroed by chc_front_clear.comp): leaf pairs over it
// (visible, invisible candidates), the triangle range their subtrees span (lo = min first, hi = max
// end), whether it traverses their lowest common ancestor (heavy) and which (lca), its items in the
// visible and invisible item lists (base, count; a heavy tile: one visible item, no invisible one),
// the scatter cursors, its visible records (base, count) and the invisible items the cull kept for it
// and merged into its last visible record (chc_querycull.comp mergeKept: keptBase indexes the item
// buffer of the visible draw; keptCount 0 = none merged).
struct ChcTilePlan { int cv; int ci; int lo; int hi; int heavy; int lca; int visBase; int visCount;
                     int invBase; int invCount; int visFill; int invFill; int recBase; int nrec; int keptBase;
                     int keptCount; };

// Whether visible record `record` (its index in the visible draw's records = its instance) carries
// its tile's merged kept pairs: the tile's last record, which holds the fewest of its own items
// (chc_front_plan.comp fills records of maxBatch items in order), so that own and kept items each
// stay within the intersection's 32-bit masks.
bool keptCarrier(ChcTilePlan tp, int record) { return tp.nrec > 0 && record == tp.recBase + tp.nrec - 1; }

// chc_front_clear.comp writes, in the plan's argument buffer (ARGS_PAIRS in chcrt_devfront.py), the
// dispatch of the pass's per-pair steps (count, scatter, refine, merge, write): a work group per 64
// of the front's pairs as it stands (META_N), not per 64 of its capacity (kept at 8x)
#define ARG_PAIRS 176

#define CHC_INVISIBLE 0
#define CHC_VISIBLE 1
#define CHC_INNER 2

// per-pair scratch flags (chc_front_count/scatter/refine/merge/scan.comp): x = bits, y = action
// (0, or the number of children a split makes: 2 object space, 4 ray space) | MERGE, z = new index,
// w = first new child
#define CHC_F_TESTED 1       // an invisible pair tested over at least one tile that is not heavy
#define CHC_F_LCA_COVERED 2  // a visible pair over a heavy tile: its own count is not its own
#define CHC_F_MERGE 16       // an inner pair whose children are all invisible: pulled up this pass

// META: 16 ints per slot; slot 0 = the frame's statistics (chcrt_devfront.STAT_NAMES, added at
// `statBase`: 0, or slot 1's for a pass whose statistics are not reported), slot s >= 2 = front s: n pairs, overflow bits, and what the last plan found (read by the host after the frame)
#define META_N 0          // pairs in the front
#define META_OVERFLOW 1   // 1: splits refused (pair capacity), 2: items over capacity (all tiles heavy)
#define META_HEAVY 2      // finest tiles that chose the LCA in the last plan (before any overflow fallback)
#define META_COPIES 3     // leaf pairs copied onto finest tiles in the last plan (visible + invisible)
#define META_WANTED 4     // pairs the last refinement wanted (kept + new children), refused ones included
#define META_TILES 5      // finest tiles of the last plan
#define META_N_OLD 6      // pairs before the last refinement (chc_front_write.comp's bound)
// work probe of the front's last pass (ChcrtParams.work_probe; zeroed by each pass's first dispatch):
#define META_PROBE_FRONT 7  // box + triangle tests (+ 1 per fragment) of the sampled rays in this pass
#define META_PROBE_FULL 8   // the same rays' box + triangle tests (+ 1 per ray) in a full traversal
#define META_PROBE_RAYS 9   // the sampled rays (active ones)
#define META_SPLITS 10      // pairs the frame's refinement of the front split (chcrt_params settle_splits)

// slot 0 of META: the frame's statistics, summed over its device passes (chcrt_devfront.STAT_NAMES)
#define STAT_RAYS 0
#define STAT_QUERY_PIXELS 1
#define STAT_RECORDS_DRAWN 2
#define STAT_VISIBLE 3
#define STAT_INVISIBLE 4
#define STAT_INNER 5
#define STAT_LCA_TILES 6
#define STAT_REQUERIES 7
#define STAT_NEWLY_VISIBLE 8
#define STAT_PULL_UPS 9
#define STAT_SCHEDULED 10
#define STAT_QUERIES 11
#define STAT_BATCHES 12
#define STAT_PHASE1 13
#define STAT_SPLITS 14  // pairs the refinements split (the fronts settling: ChcrtParams.cold_start)
#define STAT_OVERFLOWS 15

int pairState(ChcPair p) { return p.kids & 255; }
int pairKids(ChcPair p) { return p.kids >> 8; }
int pairLevel(ChcPair p) { return p.tile >> 24; }
int pairTx(ChcPair p) { return p.tile & 4095; }
int pairTy(ChcPair p) { return (p.tile >> 12) & 4095; }
int packTile(int level, int tx, int ty) { return (level << 24) | (ty << 12) | tx; }

// a visible leaf's re-query is due this frame (chcrt_front.PairFront.requery_due)
bool requeryDue(ChcPair p, int frame, int interval) { return (frame + p.offset) % interval == 0; }

// a re-query phase in 0..interval-1 for a new or merged pair: a hash of (seed, frame, slot); the
// host front draws it from a generator instead (only the spread matters)
int randomPhase(int seed, int frame, int slot, int interval) {
    uint h = uint(seed) * 0x9E3779B9u ^ uint(frame) * 0x85EBCA6Bu ^ uint(slot) * 0xC2B2AE35u;
    h ^= h >> 16; h *= 0x7FEB352Du; h ^= h >> 15; h *= 0x846CA68Bu; h ^= h >> 16;
    return int(h % uint(max(interval, 1)));
}

// tile_rects (viewer/screen_tiles.py): pixel rectangle (x, y, w, h) of quadtree tile (level, tx, ty)
ivec4 tileRect(int level, int tx, int ty, ivec2 size) {
    ivec2 lo = (ivec2(tx, ty) * size) >> level;
    ivec2 hi = (ivec2(tx + 1, ty + 1) * size) >> level;
    return ivec4(lo, hi - lo);
}

// the intersection item of canonical node `node` (chcrt_pass.py _subtree_items): its box, what the
// traversal starts from, its triangle range for the subtree overlay and the pair's count slot
ChcItem nodeItem(ChcNode nd, int node, int slot) {
    return ChcItem(nd.bmin, 0.0, nd.bmax, nd.gcount, nd.ref, slot, nd.first, nd.count, node, 0, 0, 0);
}

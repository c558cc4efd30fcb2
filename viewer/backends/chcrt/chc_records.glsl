// The CHC+RT draw records and their items, as chcrt_layout.py declares them (ITEM_DTYPE, DRAW_DTYPE): one
// declaration for every shader that reads or writes them.
// A box with a payload: query boxes (ref/count unused) or scheduled subtrees (GPU inner-node index,
// or first triangle + count for a BVH leaf; id = canonical node index and p0/p1 = the subtree's
// triangle range, for the overlay; p2 = the pair's count slot, -1 = not counted; gap = a lower bound
// of the distance from every ray origin of the record's tile to the box, world units: written, with
// the record sorted by it, by chc_querycull.comp (invisible pairs) and chc_visorder.comp (visible
// pairs, closest-hit passes), 0 elsewhere). What the intersection's item loop reads of every item
// (box, gap, count) is in the first 8 words, two of the item's four texels (chc_common.glsl
// loadItem); ref and p2 are read for the entered items only.
struct ChcItem { vec3 bmin; float gap; vec3 bmax; int count; int ref; int p2; int p0; int p1;
                 int id; int q0; int q1; int q2; };
// rect = x, y, w, h (pixels); info = item base, item count, query slot, finest tile (the visible
// pairs' records of the GPU-driven pass; read by chc_visorder.comp)
struct ChcDraw { ivec4 rect; ivec4 info; };

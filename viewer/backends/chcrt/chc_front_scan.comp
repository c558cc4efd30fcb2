// CHC+RT device front, refinement step 3 (one work group): the next front's layout. Kept pairs (all
// but the children of a merged pair) keep their order and are numbered first, then the children of
// this pass's object-space splits, then those of its ray-space splits, each in the order of their
// parents (as PairFront.subdivide appends them on the host, so both fronts list their pairs, and
// hence their items, in the same order; siblings stay contiguous either way). If
// they would not fit in the capacity, no pair splits this pass: chc_front_write.comp terminates them
// as visible instead (exact; the host grows the capacity after reading META_OVERFLOW).
layout(local_size_x = 256) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_PAIRS) readonly buffer Pairs { ChcPair pairs[]; };
layout(std430, binding = BIND_FR_FLAGS) buffer Flags { ivec4 flags[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int capacity;
uniform int frontSlot;
uniform int statBase;

shared int sKept[256];
shared int sObj[256];
shared int sRay[256];
shared int sTotal;
shared int sObjTotal;

bool kept(int i) {
    int par = pairs[i].parent;
    return par < 0 || (flags[par].y & CHC_F_MERGE) == 0;
}

void main() {
    int li = int(gl_LocalInvocationIndex);
    int n = meta[16 * frontSlot + META_N];
    int per = (n + 255) / 256;
    int i0 = min(n, li * per), i1 = min(n, i0 + per);
    int nk = 0, no = 0, nr = 0;
    for (int i = i0; i < i1; ++i) {
        if (!kept(i)) continue;
        int a = flags[i].y & 7;
        nk += 1;
        no += a == 2 ? 2 : 0;
        nr += a == 4 ? 4 : 0;
    }
    sKept[li] = nk;
    sObj[li] = no;
    sRay[li] = nr;
    barrier();
    if (li == 0) {
        int ak = 0, ao = 0, ar = 0;
        for (int k = 0; k < 256; ++k) {
            int a = sKept[k], b = sObj[k], c = sRay[k];
            sKept[k] = ak; sObj[k] = ao; sRay[k] = ar;
            ak += a; ao += b; ar += c;
        }
        int an = ao + ar;
        sObjTotal = ao;
        int s = 16 * frontSlot;
        bool over = ak + an > capacity;
        meta[s + META_WANTED] = ak + an;
        meta[s + META_N_OLD] = n;
        meta[s + META_N] = over ? ak : ak + an;
        if (over) {
            meta[s + META_OVERFLOW] |= 1;
            atomicAdd(meta[statBase + STAT_OVERFLOWS], 1);
        }
        sTotal = ak;
    }
    barrier();
    int nextIdx = sKept[li], nextObj = sTotal + sObj[li], nextRay = sTotal + sObjTotal + sRay[li];
    for (int i = i0; i < i1; ++i) {
        if (!kept(i)) { flags[i].z = -1; continue; }
        int a = flags[i].y & 7;
        flags[i].z = nextIdx++;
        flags[i].w = a == 4 ? nextRay : nextObj;
        nextObj += a == 2 ? 2 : 0;
        nextRay += a == 4 ? 4 : 0;
    }
}

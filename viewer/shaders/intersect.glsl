// Ray/triangle and ray/box tests and full-BVH traversal.
//  * Watertight ray/triangle test (Woop, Benthin, Wald 2013) with a double-precision fallback for
//    edge values that are exactly zero, so rays through shared edges and vertices never leak.
//  * Conservative slab test: the far distance is scaled by 1 + 2*gamma(3) (Ize 2013) and
//    reciprocals of zero components are replaced by a huge finite value of the same sign
//    (no 0 * inf = NaN for axis-parallel rays).
//  * Numeric contract (docs/numerics.md): every value a hit/miss decision or t depends on is
//    `precise` (evaluated as written: no a*b+c fused into an FMA, which NVIDIA does otherwise), dot
//    products are written out in the order the OpenCL kernels (geometry.cl) and the float32
//    emulation of the tests use, and divisions are correctly rounded (divRounded), so the same ray
//    gives the same bits on every driver.
#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

// Work counters (diagnostics, RTWALK_COUNT_WORK=1): per invocation, then one atomicAdd each into
// slots [base, base+4) of workTotals: invocations, nodes fetched, box tests, triangle tests
// (workFlushPixel: also per pixel).
// WORK_PROBE keeps the per-invocation counts without workFlush's sums, for a shader that reports
// them itself (chcrt's work probe, ChcrtParams.work_probe).
#if defined(COUNT_WORK) || defined(WORK_PROBE)
uint workNode = 0u, workBox = 0u, workTri = 0u;
#define WORK(v) (v += 1u)
#else
#define WORK(v)
#endif
#ifdef COUNT_WORK
layout(std430, binding = BIND_WORK) buffer WorkCounters { uint workTotals[16]; };
// The same nodes and triangle tests per pixel (the ray traced there, summed over the draws that
// trace it): what a SIMD group of neighbouring pixels waits for is its busiest lane, so
// WorkCounters (viewer/backends/base.py) reads these to count the work of lane groups as well.
layout(r32i, binding = BIND_IMG_WORK_NODES) uniform coherent iimage2D workPixelNodes;
layout(r32i, binding = BIND_IMG_WORK_TRIS) uniform coherent iimage2D workPixelTris;
void workFlush(int base) {
    atomicAdd(workTotals[base], 1u);
    atomicAdd(workTotals[base + 1], workNode);
    atomicAdd(workTotals[base + 2], workBox);
    atomicAdd(workTotals[base + 3], workTri);
}
// workFlush of a ray traced at pixel px (the intersection shaders)
void workFlushPixel(int base, ivec2 px) {
    workFlush(base);
    imageAtomicAdd(workPixelNodes, px, int(workNode));
    imageAtomicAdd(workPixelTris, px, int(workTri));
}
#else
void workFlush(int base) {}
void workFlushPixel(int base, ivec2 px) {}
#endif

struct RayPre {
    vec3 o;
    vec3 d;
    vec3 invD;
    int kx, ky, kz;
    vec3 S;  // shear constants Sx, Sy, Sz
};

// a / b correctly rounded to float32 on every driver: GLSL allows 2.5 ulp for a float `/` (NVIDIA
// uses a reciprocal), while the quotient of two floats is never within a few double ulps of a
// float32 rounding boundary, so rounding a double quotient gives the IEEE float32 quotient
// (infinities and NaN as in float32).
float divRounded(float a, float b) {
    precise double q = double(a) / double(b);
    return float(q);
}

// x . y summed left to right: ((x0 y0 + x1 y1) + x2 y2), no fused multiply-add
float dotPrecise(vec3 x, vec3 y) {
    precise float s = x.x * y.x + x.y * y.y + x.z * y.z;
    return s;
}

float safeRcp(float x) {
    // keep the sign of -0.0: floatBitsToInt(-0.0) < 0
    float s = floatBitsToInt(x) < 0 ? -1.0 : 1.0;
    return abs(x) < 1e-30 ? s * 1e30 : divRounded(1.0, x);
}

RayPre prepareRay(vec3 o, vec3 d) {
    RayPre r;
    r.o = o;
    r.d = d;
    r.invD = vec3(safeRcp(d.x), safeRcp(d.y), safeRcp(d.z));
    vec3 ad = abs(d);
    int kz = (ad.x > ad.y) ? ((ad.x > ad.z) ? 0 : 2) : ((ad.y > ad.z) ? 1 : 2);
    int kx = (kz + 1) % 3;
    int ky = (kx + 1) % 3;
    if (d[kz] < 0.0) { int tmp = kx; kx = ky; ky = tmp; }
    r.kx = kx; r.ky = ky; r.kz = kz;
    r.S = vec3(divRounded(d[kx], d[kz]), divRounded(d[ky], d[kz]), divRounded(1.0, d[kz]));
    return r;
}

// cross(a, b) rounded once per component: float32 products are exact in float64, so only the
// difference rounds (then to float32). A float32 cross product of a needle's or sliver's edges
// cancels instead: relative error ~1e-7 / sin of the angle between them, up to 1e-1 at aspect 1e4.
vec3 crossRounded(vec3 a, vec3 b) {
    dvec3 da = dvec3(a), db = dvec3(b);
    precise dvec3 c = dvec3(da.y * db.z - da.z * db.y, da.z * db.x - da.x * db.z, da.x * db.y - da.y * db.x);
    return vec3(c);
}

// Returns true and the distance t (tmin < t < tmax) on a hit; bary receives (u, v) weights of v1, v2.
bool intersectTriangle(RayPre r, vec3 v0, vec3 v1, vec3 v2, float tmin, float tmax, out float t, out vec2 bary) {
    precise vec3 A = v0 - r.o, B = v1 - r.o, C = v2 - r.o;
    precise float Ax = A[r.kx] - r.S.x * A[r.kz], Ay = A[r.ky] - r.S.y * A[r.kz];
    precise float Bx = B[r.kx] - r.S.x * B[r.kz], By = B[r.ky] - r.S.y * B[r.kz];
    precise float Cx = C[r.kx] - r.S.x * C[r.kz], Cy = C[r.ky] - r.S.y * C[r.kz];
    precise float U = Cx * By - Cy * Bx;
    precise float V = Ax * Cy - Ay * Cx;
    precise float W = Bx * Ay - By * Ax;
    if (U == 0.0 || V == 0.0 || W == 0.0) {
        precise double CxBy = double(Cx) * double(By), CyBx = double(Cy) * double(Bx);
        precise double AxCy = double(Ax) * double(Cy), AyCx = double(Ay) * double(Cx);
        precise double BxAy = double(Bx) * double(Ay), ByAx = double(By) * double(Ax);
        U = float(CxBy - CyBx);
        V = float(AxCy - AyCx);
        W = float(BxAy - ByAx);
    }
    if ((U < 0.0 || V < 0.0 || W < 0.0) && (U > 0.0 || V > 0.0 || W > 0.0)) return false;
    precise float det = U + V + W;
    if (det == 0.0) return false;
    // Distance from the plane equation t = dot(n, v0 - o) / dot(n, d), n = cross(v1 - v0, v2 - v0):
    // far more accurate than the sheared-space T / det for grazing rays and thin triangles (the
    // watertight edge test above still decides inside/outside). n must be the correctly rounded
    // cross product (crossRounded): a float32 one loses most of its accuracy on needles and slivers
    // (t off by up to 1e-1 relative, and its sign flips for rays starting just in front of the
    // triangle). Vertex differences of nearby float32 vertices are exact (Sterbenz), so n is then
    // within an ulp per component and t is as exact as v0 - o and the two float dot products allow,
    // for any triangle shape. A ray parallel to the computed plane (dot(n, d) == 0) falls back to
    // T / det.
    precise vec3 e1 = v1 - v0, e2 = v2 - v0;
    precise vec3 n = crossRounded(e1, e2);
    precise float dn = dotPrecise(n, r.d);
    if (dn != 0.0) {
        t = divRounded(dotPrecise(n, A), dn);
    } else {
        precise float Az = r.S.z * A[r.kz], Bz = r.S.z * B[r.kz], Cz = r.S.z * C[r.kz];
        precise float T = U * Az + V * Bz + W * Cz;
        t = divRounded(T, det);
    }
    if (!(t > tmin && t < tmax)) return false;
    bary = vec2(divRounded(V, det), divRounded(W, det));
    return true;
}

const float GAMMA3_SCALE = 1.0 + 2.0 * (3.0 * 5.960464477539063e-08) / (1.0 - 3.0 * 5.960464477539063e-08);

// Conservative slab test; tEntry is the (clamped) entry distance.
bool intersectBox(RayPre r, vec3 bmin, vec3 bmax, float tmin, float tmax, out float tEntry) {
    WORK(workBox);
    precise vec3 t0 = (bmin - r.o) * r.invD;
    precise vec3 t1 = (bmax - r.o) * r.invD;
    vec3 tn = min(t0, t1), tf = max(t0, t1);
    float enter = max(max(tn.x, tn.y), max(tn.z, tmin));
    precise float exit = min(min(tf.x, tf.y), tf.z) * GAMMA3_SCALE;
    exit = min(exit, tmax);
    tEntry = enter;
    return enter <= exit;
}

struct Hit { float t; int id; };

// The triangle in `slot` against the ray, between tmin and the hit so far: a nearer hit replaces
// `hit` (and returns true). The one triangle test of every loop over leaves.
bool intersectSlot(RayPre r, int slot, float tmin, inout Hit hit) {
    Tri tri = loadTri(slot);
    WORK(workTri);
    float t; vec2 b;
    if (!intersectTriangle(r, tri.v0, tri.v1, tri.v2, tmin, hit.t, t, b)) return false;
    hit = Hit(t, slot);
    return true;
}

// Intersect `count` triangles starting at slot `first`; updates hit, returns true if any was hit.
bool intersectLeaf(RayPre r, int first, int count, float tmin, inout Hit hit) {
    bool found = false;
    for (int i = 0; i < count; ++i) {
        if (intersectSlot(r, first + i, tmin, hit)) found = true;
    }
    return found;
}

// The entered leaf children of node `nd` (hl, hr: their boxes were entered), in ONE triangle loop:
// a SIMD group then waits for its longest sum, not for its longest left leaf and then its longest
// right one (city-near 1280x720 on llvmpipe: glsl 0.8x its time). Clears hl / hr for leaf children
// (nothing to push); with anyHit it stops at the first hit. Returns true if a triangle was hit.
bool intersectLeafChildren(RayPre r, Node nd, inout bool hl, inout bool hr, float tmin, bool anyHit,
                           inout Hit hit) {
    int lc = hl && nd.left < 0 ? nd.lcount : 0;
    int rc = hr && nd.right < 0 ? nd.rcount : 0;
    hl = hl && nd.left >= 0;
    hr = hr && nd.right >= 0;
    bool found = false;
    for (int i = 0; i < lc + rc; ++i) {
        int slot = i < lc ? ~nd.left + i : ~nd.right + (i - lc);
        if (intersectSlot(r, slot, tmin, hit)) {
            found = true;
            if (anyHit) break;
        }
    }
    return found;
}

// Stack traversal of the subtree rooted at inner node `root` (nearer child first). With anyHit
// it stops at the first hit (shadow and AO rays). hit.t must hold tmax on entry.
void traverseBVH(RayPre r, int root, float tmin, bool anyHit, inout Hit hit) {
    int stackNode[STACK_SIZE];
    float stackT[STACK_SIZE];
    int sp = 0;
    int ni = root;
    while (true) {
        Node nd = loadNode(ni);
        WORK(workNode);
        float tl, tr;
        bool hl = intersectBox(r, nd.lmin, nd.lmax, tmin, hit.t, tl);
        bool hr = intersectBox(r, nd.rmin, nd.rmax, tmin, hit.t, tr);
        if (intersectLeafChildren(r, nd, hl, hr, tmin, anyHit, hit) && anyHit) return;
        hl = hl && tl <= hit.t;
        hr = hr && tr <= hit.t;
        if (hl && hr) {
            bool leftFirst = tl <= tr;
            stackNode[sp] = leftFirst ? nd.right : nd.left;
            stackT[sp] = leftFirst ? tr : tl;
            sp = min(sp + 1, STACK_SIZE - 1);
            ni = leftFirst ? nd.left : nd.right;
        } else if (hl) {
            ni = nd.left;
        } else if (hr) {
            ni = nd.right;
        } else {
            bool found = false;
            while (sp > 0) {
                --sp;
                if (stackT[sp] <= hit.t) { ni = stackNode[sp]; found = true; break; }
            }
            if (!found) return;
        }
    }
}

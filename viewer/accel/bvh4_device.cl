// BVH4 collapse on the OpenCL device (viewer/accel/bvh4_device.py): the same greedy, level by level,
// as viewer/accel/bvh4.py (NODE4 layout there), so the same nodes bit for bit. Needs cl_khr_fp64:
// the child areas are compared in float64, as the host collapse does. Defines: WG.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

inline double area64(__global const float* lo, __global const float* hi, int v) {
    double ex = (double)hi[3 * v] - (double)lo[3 * v];
    double ey = (double)hi[3 * v + 1] - (double)lo[3 * v + 1];
    double ez = (double)hi[3 * v + 2] - (double)lo[3 * v + 2];
    return ex * ey + ey * ez + ez * ex;
}

// The children of the BVH4 node made from binary inner node frontier[i]: its two children, then
// twice the inner child of largest area (first on ties) replaced by its two children.
__kernel void b4_open(uint k, __global const int* frontier, __global const float* nmin, __global const float* nmax,
                      __global const int* left, __global const int* right, __global int4* ch4,
                      __global uint* ninner) {
    uint i = get_global_id(0);
    if (i >= k) return;
    int f = frontier[i];
    int ch[4] = {left[f], right[f], -1, -1};
    int filled = 2;
    for (int round = 0; round < 2; ++round) {
        int j = -1;
        double best = -INFINITY;
        for (int s = 0; s < 4; ++s) {
            int c = ch[s];
            if (c < 0 || left[c] < 0) continue;
            double a = area64(nmin, nmax, c);
            if (j < 0 || a > best) {  // np.argmax: the first largest
                best = a;
                j = s;
            }
        }
        if (j < 0 || !isfinite(best)) break;
        int c = ch[j];
        ch[j] = left[c];
        ch[filled++] = right[c];
    }
    uint m = 0;
    for (int s = 0; s < 4; ++s) m += ch[s] >= 0 && left[ch[s]] >= 0;
    ch4[i] = (int4)(ch[0], ch[1], ch[2], ch[3]);
    ninner[i] = m;
}

// Node base + i (8 float4: minx, maxx, miny, maxy, minz, maxz over the 4 slots, child, count);
// inner children are numbered row-major after the level (base + k + offset), and listed, in that
// order, as the next level's frontier.
__kernel void b4_write(uint k, uint base, __global const int* frontier, __global const int4* ch4,
                       __global const uint* offset, __global const float* nmin, __global const float* nmax,
                       __global const int* left, __global const int* first, __global const int* count,
                       __global float4* nodes, __global int* source, __global int* next) {
    uint i = get_global_id(0);
    if (i >= k) return;
    int4 c4 = ch4[i];
    int ch[4] = {c4.x, c4.y, c4.z, c4.w};
    float lo[3][4], hi[3][4];
    int child[4], cnt[4];
    uint o = offset[i];
    for (int s = 0; s < 4; ++s) {
        int c = ch[s];
        if (c < 0) {
            for (int a = 0; a < 3; ++a) {
                lo[a][s] = INFINITY;
                hi[a][s] = -INFINITY;
            }
            child[s] = ~0;
            cnt[s] = 0;
            continue;
        }
        for (int a = 0; a < 3; ++a) {
            lo[a][s] = nmin[3 * c + a];
            hi[a][s] = nmax[3 * c + a];
        }
        if (left[c] < 0) {
            child[s] = ~first[c];
            cnt[s] = count[c];
        } else {
            next[o] = c;
            child[s] = (int)(base + k + o);
            cnt[s] = 0;
            ++o;
        }
    }
    __global float4* n = nodes + 8 * (size_t)(base + i);
    for (int a = 0; a < 3; ++a) {
        n[2 * a] = (float4)(lo[a][0], lo[a][1], lo[a][2], lo[a][3]);
        n[2 * a + 1] = (float4)(hi[a][0], hi[a][1], hi[a][2], hi[a][3]);
    }
    n[6] = as_float4((int4)(child[0], child[1], child[2], child[3]));
    n[7] = as_float4((int4)(cnt[0], cnt[1], cnt[2], cnt[3]));
    source[base + i] = frontier[i];
}

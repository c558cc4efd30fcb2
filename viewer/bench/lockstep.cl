// The lockstep lane-utilisation model of viewer/bench/lockstep.py on the device, so the study
// need not copy every ray's step sequence to the host. One work-item per group of W consecutive
// rays; out[3 g + (0, 1, 2)] = (steps, issue slots, longest ray) of group g, where
//   steps   = sum over the group's rays of min(len, L),
//   slots   = sum over iterations j of the number of distinct step kinds among lanes with j < len,
//   longest = max over the group of min(len, L)   (the "merged" model's slots).
// seq: uchar (n, L) step kinds (1-4) of each ray's first L steps; entries at j >= len are not read
// (the recording kernel does not clear them). rec: int4 per ray, the step counts whose sum is len.
#ifndef MAXW
#define MAXW 64
#endif

__kernel void lockstep(__global const uchar *seq, __global const int4 *rec, const int n, const int L, const int W,
                       __global int *out) {
    int g = get_global_id(0);
    int lo = g * W;
    if (lo >= n || W > MAXW) return;
    int m = min(W, n - lo);
    int len[MAXW];
    int steps = 0, longest = 0;
    for (int l = 0; l < m; ++l) {
        int4 c = rec[lo + l];
        len[l] = min(c.x + c.y + c.z + c.w, L);
        steps += len[l];
        longest = max(longest, len[l]);
    }
    __global const uchar *s = seq + (size_t)lo * L;
    int slots = 0;
    for (int j = 0; j < longest; ++j) {
        uint kinds = 0;
        for (int l = 0; l < m; ++l)
            if (j < len[l]) kinds |= 1u << s[(size_t)l * L + j];
        slots += popcount(kinds);
    }
    out[3 * g] = steps;
    out[3 * g + 1] = slots;
    out[3 * g + 2] = longest;
}

// CHC+RT work probe (ChcrtParams.work_probe): the sampled pixels, shared by the front's side
// (chc_intersect.frag with WORK_PROBE) and the full traversal's (chc_probe.comp). Runs of 8
// neighbours in a row, so that a SIMD group holds neighbouring rays as in the passes it stands
// for, every `stride`-th run of every `stride`-th row (stride 8: 1/64 of the pixels).
bool probePixel(ivec2 px, int stride) {
    return px.y % stride == stride / 2 && (px.x >> 3) % stride == 0;
}

// the n-th sampled pixel of an image `size` wide (chc_probe.comp's invocation n; rows beyond the
// image are the caller's to drop)
ivec2 probePixelAt(int n, int width, int stride) {
    int run = n >> 3;
    int runsPerRow = (width + 8 * stride - 1) / (8 * stride);
    return ivec2((run % runsPerRow) * 8 * stride + (n & 7), (run / runsPerRow) * stride + stride / 2);
}

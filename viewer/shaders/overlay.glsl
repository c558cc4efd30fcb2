// Backend overlay views (viewer/passes/overlay.py mirrors these functions in NumPy for the legend
// and the tests: keep the two in step).
//  * Capture texture, one per overlay view (RGBA32I, row 0 = bottom): r = the view's per-pixel value
//    (kind "heat": a count >= 0; kind "ids": an id, -1 = none), g = the view's per-pixel `counts`
//    value (-1 = none or not reported), b = 0, a = flags (1 = the pixel had a ray, 2 = it hit).
//  * Heat scale: position of v in [0, vmax] on a log2(1 + v) (or linear) axis, looked up in a
//    256-entry colormap texture (inferno: perceptually uniform, lightness increases with the value).

const int OVERLAY_FLAG_RAY = 1;
const int OVERLAY_FLAG_HIT = 2;
const vec3 OVERLAY_NO_DATA = vec3(46.0 / 255.0);  // dark grey: no ray / no data at this pixel

// Smallest of 1, 2, 5, 10, 20, 50, ... that is >= n: a scale maximum that changes only when the
// data crosses a step, so the colours of a walkthrough do not flicker with every frame's maximum.
int overlayNiceCeil(int n) {
    int d = 1;
    for (int i = 0; i < 9; ++i) {
        if (n <= d) return d;
        if (n <= 2 * d) return 2 * d;
        if (n <= 5 * d) return 5 * d;
        d *= 10;
    }
    return n;
}

float overlayHeatPos(int v, int vmax, bool logScale) {
    float x = float(max(v, 0));
    float m = float(max(vmax, 1));
    float p = logScale ? log2(1.0 + x) / log2(1.0 + m) : x / m;
    return clamp(p, 0.0, 1.0);
}

vec3 overlayHeatColor(sampler2D lut, float p) {
    return texelFetch(lut, ivec2(int(floor(p * 255.0 + 0.5)), 0), 0).rgb;
}

// A bright, well spread colour per id (neighbouring ids must be told apart).
vec3 overlayIdColor(int id) {
    uint h = uint(id) * 747796405u + 2891336453u;
    h = ((h >> ((h >> 28u) + 4u)) ^ h) * 277803737u;
    h = (h >> 22u) ^ h;
    vec3 c = vec3(float(h & 255u), float((h >> 8) & 255u), float((h >> 16) & 255u)) / 255.0;
    return 0.3 + 0.7 * c;
}

// Screen-tile column (or row) of pixel coordinate x at quadtree level `level`: tile t covers
// [t*w >> L, (t+1)*w >> L) (viewer/screen_tiles.py: tile_rects, tile_index).
int overlayTileOf(int x, int w, int level) {
    return (((x + 1) << level) - 1) / w;
}

// One step of a max-reduction over BLOCK x BLOCK texels: (max value, max counts) of a capture
// texture (channels r, g; layout overlay.glsl) or of the previous step, never below 0.
// Render-to-texture steps (no atomics, no memory barriers) down to 1x1, which the view shader reads.
#define BLOCK 16
uniform isampler2D src;
uniform ivec2 srcSize;
out ivec2 outMax;

void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * BLOCK;
    ivec2 hi = min(base + BLOCK, srcSize);
    ivec2 m = ivec2(0);
    for (int y = base.y; y < hi.y; ++y) {
        for (int x = base.x; x < hi.x; ++x) {
            m = max(m, texelFetch(src, ivec2(x, y), 0).rg);
        }
    }
    outMax = m;
}

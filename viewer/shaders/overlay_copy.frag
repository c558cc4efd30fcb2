// Copies one overlay view's backend textures of the pass just traced into that view's capture
// texture (layout: overlay.glsl), so that the next trace() call, which overwrites the backend's
// textures, does not lose them.
#include "overlay.glsl"
uniform isampler2D srcValue;   // the OverlaySpec's texture
uniform isampler2D srcCounts;  // its `counts` texture (hasCounts = 0: none)
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform isampler2D hitId;
uniform int hasCounts;
out ivec4 outOverlay;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int value = texelFetch(srcValue, px, 0).r;
    int counts = hasCounts != 0 ? texelFetch(srcCounts, px, 0).r : -1;
    bool ray = texelFetch(rayDir, px, 0).w > texelFetch(rayOrigin, px, 0).w;
    bool hit = texelFetch(hitId, px, 0).r >= 0;
    outOverlay = ivec4(value, counts, 0, (ray ? OVERLAY_FLAG_RAY : 0) | (hit ? OVERLAY_FLAG_HIT : 0));
}

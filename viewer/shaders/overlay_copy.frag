// Copies one pass's backend overlays into the renderer's capture texture (layout: overlay.glsl),
// so that the next trace() call, which overwrites the backend's textures, does not lose them.
#include "overlay.glsl"
uniform isampler2D srcOverdraw;
uniform isampler2D srcSubtree;
uniform isampler2D srcBatch;
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform isampler2D hitId;
uniform int hasOverdraw, hasSubtree, hasBatch;
out ivec4 outOverlay;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int od = hasOverdraw != 0 ? texelFetch(srcOverdraw, px, 0).r : -1;
    int sub = hasSubtree != 0 ? texelFetch(srcSubtree, px, 0).r : -1;
    int batch = hasBatch != 0 ? texelFetch(srcBatch, px, 0).r : -1;
    bool ray = texelFetch(rayDir, px, 0).w > texelFetch(rayOrigin, px, 0).w;
    bool hit = texelFetch(hitId, px, 0).r >= 0;
    outOverlay = ivec4(od, sub, batch, (ray ? OVERLAY_FLAG_RAY : 0) | (hit ? OVERLAY_FLAG_HIT : 0));
}

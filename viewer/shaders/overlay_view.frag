// Shows one captured overlay view (layout: overlay.glsl) in place of the final image; the mode is
// the OverlaySpec's kind (viewer/passes/overlay.py VIEW_SHADER_MODES), never its name.
//  mode 0 (kind "heat"): the value per pixel as a heat map; pixels without a ray and with a value
//    of 0 (or no value) are dark grey.
//  mode 1 (kind "ids"): the id per pixel in a colour of its own (dark grey: -1, none); screen-tile
//    outlines (tileLevel >= 0), coloured by the tile's `counts` value on the heat scale when the
//    backend reports one (white otherwise).
#include "overlay.glsl"
uniform isampler2D overlay;
uniform isampler2D reduced;  // 1x1: (max value, max counts)
uniform sampler2D lut;
uniform int mode;
uniform int fixedMax;  // > 0: heat scale maximum chosen by the user; else from the frame's maximum
uniform int logScale;
uniform int tileLevel;  // < 0: no tile outlines
out vec4 fragColor;

bool tileEdge(ivec2 px, ivec2 size) {
    if (tileLevel < 0) return false;
    int tx = overlayTileOf(px.x, size.x, tileLevel);
    int ty = overlayTileOf(px.y, size.y, tileLevel);
    return (px.x > 0 && overlayTileOf(px.x - 1, size.x, tileLevel) != tx)
        || (px.x + 1 < size.x && overlayTileOf(px.x + 1, size.x, tileLevel) != tx)
        || (px.y > 0 && overlayTileOf(px.y - 1, size.y, tileLevel) != ty)
        || (px.y + 1 < size.y && overlayTileOf(px.y + 1, size.y, tileLevel) != ty);
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(overlay, 0);
    ivec4 o = texelFetch(overlay, px, 0);
    ivec2 mx = texelFetch(reduced, ivec2(0), 0).rg;
    bool log2Scale = logScale != 0;
    vec3 c;
    if (mode == 0) {
        int vmax = fixedMax > 0 ? fixedMax : overlayNiceCeil(max(mx.x, 1));
        bool noData = o.r < 0 || (o.r == 0 && (o.a & OVERLAY_FLAG_RAY) == 0);
        c = noData ? OVERLAY_NO_DATA : overlayHeatColor(lut, overlayHeatPos(o.r, vmax, log2Scale));
    } else {
        c = o.r >= 0 ? overlayIdColor(o.r) : OVERLAY_NO_DATA;
        if (tileEdge(px, size)) {
            c = vec3(1.0);
            if (o.g >= 0 && mx.y > 0) {
                float p = overlayHeatPos(o.g, overlayNiceCeil(mx.y), true);
                c = overlayHeatColor(lut, 0.3 + 0.7 * p);  // skip the near-black start of the map
            }
        }
    }
    fragColor = vec4(c, 1.0);
}

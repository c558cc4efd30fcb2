// Distance pyramid for the G-buffer's occlusion culling (viewer/passes/occlusion.py): per texel the
// FARTHEST primary-ray distance of the pixels it covers, +inf where no triangle was drawn.
// srcLevel < 0: level 0 from the G-buffer (id < 0 = nothing drawn): the exact raster's depth
// (fromDepth = 1; it writes no position until its resolve) or the preview's position.w (distance
// along the pixel's ray). srcLevel >= 0: level srcLevel + 1 from level srcLevel, max of the 2x2 texels
// below, and on an odd-sized level's last row/column also the third one, so the last texel of every
// level covers the image to its edge: pixel p lies in texel min(p >> k, size_k - 1) of level k.
layout(local_size_x = 8, local_size_y = 8) in;
layout(r32f, binding = BIND_IMG_HIZ) writeonly uniform image2D dst;
uniform sampler2D gPosition;
uniform sampler2D gDepth;  // t / (t + depthScale), float32 (gbuffer.frag)
uniform int fromDepth;
uniform float depthScale;
uniform isampler2D gTriId;
uniform sampler2D src;  // the pyramid itself (srcLevel >= 0)
uniform int srcLevel;
const float FAR = 3.0e38;

// An upper bound of the distance t whose depth gbuffer.frag wrote as z = t / (t + s) in float32: z
// is within 4.2e-7 relative of the exact ratio (the sum rounded, a division GLSL allows 2.5 ulp),
// so z * (1 + 1e-6) (rounded: still >= z (1 + 9e-7)) is at least the exact ratio and s z / (1 - z),
// increasing in z, at least t; its own three roundings are covered by the final 1 + 1e-6. Farther
// than the truth only makes the culling keep more, never drop what is visible.
float distanceAbove(float z) {
    float zu = z * (1.0 + 1e-6);
    if (!(zu < 1.0)) return FAR;
    precise float t = depthScale * zu / (1.0 - zu) * (1.0 + 1e-6);
    return min(t, FAR);
}

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    ivec2 size = imageSize(dst);
    if (p.x >= size.x || p.y >= size.y) return;
    float v;
    if (srcLevel < 0) {
        if (texelFetch(gTriId, p, 0).r < 0) v = FAR;
        else v = fromDepth != 0 ? distanceAbove(texelFetch(gDepth, p, 0).r) : texelFetch(gPosition, p, 0).w;
    } else {
        ivec2 below = textureSize(src, srcLevel);
        ivec2 hi = 2 * p + 1;
        if (p.x == size.x - 1) hi.x = below.x - 1;  // an odd level's last column also takes the third
        if (p.y == size.y - 1) hi.y = below.y - 1;
        v = 0.0;
        for (int y = 2 * p.y; y <= hi.y; ++y)
            for (int x = 2 * p.x; x <= hi.x; ++x) v = max(v, texelFetch(src, ivec2(x, y), srcLevel).r);
    }
    imageStore(dst, p, vec4(v));
}

// Edge-aware a-trous wavelet filter of the shaded image (Dammertz et al. 2010, with SVGF's
// edge-stopping functions, Schied et al. 2017), guided by the G-buffer. Three modes, one draw each:
//   mode 0 (prepare): the display image (RGBA8, gamma 2.2) -> linear radiance divided by the
//          G-buffer albedo (texture detail is not noise: only the illumination is filtered), with
//          in alpha the luminance variance of its 3x3 neighbourhood (SVGF's spatial estimate); and a
//          compact guide (octahedral normal, distance, distance gradient) so that each later tap
//          costs two fetches;
//   mode 1 (filter): one 3x3 step (weights 1/4, 1/2, 1/4) with holes `stepPx` apart; weights stop
//          at normals, at distance differences large against the local distance gradient, and at
//          luminance differences large against the local standard deviation; variance filtered too;
//   mode 2 (filter and finish): as mode 1, then multiplied by the albedo again and gamma-encoded.
// Background and mirror pixels (albedo.a > 0.5: a reflected image, noise-free) are kept as shaded
// (marked by alpha -1 in the intermediate images) and never mix into their neighbours.
uniform sampler2D src;      // mode 0: the display image; else the previous step (float RGBA)
uniform sampler2D display;  // the display image (kept pixels, mode 2)
uniform sampler2D guide;    // modes 1, 2: the prepare pass's guide
uniform sampler2D gPos;     // w: distance along the primary ray
uniform sampler2D gNormal;
uniform sampler2D gAlbedo;
uniform isampler2D gId;
uniform int mode;
uniform int stepPx;
uniform float sigmaL;       // luminance edge-stop, in local standard deviations
#ifndef NORMAL_SQUARINGS
#define NORMAL_SQUARINGS 6  // normal edge-stop: cos^(2^6) = cos^64 (SVGF: 128)
#endif
uniform float sigmaZ;       // distance edge-stop, in local distance gradients per pixel of offset
layout(location = 0) out vec4 outColor;
layout(location = 1) out vec4 outGuide;

const float ALBEDO_FLOOR = 0.02;  // demodulation of near-black albedo: no division blow-up

float lum(vec3 c) { return dot(c, vec3(0.2126, 0.7152, 0.0722)); }

bool kept(ivec2 q) {
    return texelFetch(gId, q, 0).r < 0 || texelFetch(gAlbedo, q, 0).a > 0.5;
}

vec3 demodulated(ivec2 q) {
    vec3 lin = pow(texelFetch(display, q, 0).rgb, vec3(2.2));
    return lin / max(texelFetch(gAlbedo, q, 0).rgb, vec3(ALBEDO_FLOOR));
}

vec2 octEncode(vec3 n) {
    n /= abs(n.x) + abs(n.y) + abs(n.z);
    vec2 e = n.xy;
    if (n.z < 0.0) e = (1.0 - abs(n.yx)) * vec2(n.x >= 0.0 ? 1.0 : -1.0, n.y >= 0.0 ? 1.0 : -1.0);
    return e;
}

vec3 octDecode(vec2 e) {
    vec3 n = vec3(e, 1.0 - abs(e.x) - abs(e.y));
    if (n.z < 0.0) n.xy = (1.0 - abs(n.yx)) * vec2(n.x >= 0.0 ? 1.0 : -1.0, n.y >= 0.0 ? 1.0 : -1.0);
    return normalize(n);
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(src, 0);
    if (mode == 0) {
        float d = texelFetch(gPos, px, 0).w;
        float grad = fwidthFine(d);  // before any return: derivatives need the whole 2x2 quad (fine: the
        // same on every driver, fwidth may be either)
        if (kept(px)) {  // marked by a negative variance: later steps skip it with one fetch
            outColor = vec4(0.0, 0.0, 0.0, -1.0);
            outGuide = vec4(0.0);
            return;
        }
        float s = 0.0, s2 = 0.0, n = 0.0;
        for (int dy = -1; dy <= 1; ++dy)
            for (int dx = -1; dx <= 1; ++dx) {
                ivec2 q = clamp(px + ivec2(dx, dy), ivec2(0), size - 1);
                if (kept(q)) continue;
                float l = lum(demodulated(q));
                s += l; s2 += l * l; n += 1.0;
            }
        float m = s / n;
        outColor = vec4(demodulated(px), max(s2 / n - m * m, 0.0));
        // a silhouette's gradient (the quad spans two surfaces) is no slope: cap it at the distance
        outGuide = vec4(octEncode(texelFetch(gNormal, px, 0).xyz), d, min(grad, 0.05 * d));
        return;
    }
    vec4 cp = texelFetch(src, px, 0);
    if (cp.a < 0.0) {
        outColor = mode == 2 ? vec4(texelFetch(display, px, 0).rgb, 1.0) : cp;
        return;
    }
    vec4 gp = texelFetch(guide, px, 0);
    vec3 np = octDecode(gp.xy);
    float lp = lum(cp.rgb);
    float zscale = sigmaZ * gp.w + 1e-4 * gp.z;  // relative floor: flat-on surfaces have no gradient
    float lscale = sigmaL * sqrt(cp.a) + 1e-3 * max(lp, 1e-6) + 1e-8;
    const float h[2] = float[](0.5, 0.25);
    vec3 sum = vec3(0.0);
    float wsum = 0.0, vsum = 0.0;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
            ivec2 q = px + ivec2(dx, dy) * stepPx;
            if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
            vec4 cq = texelFetch(src, q, 0);
            if (cq.a < 0.0) continue;  // background or mirror
            vec4 gq = texelFetch(guide, q, 0);
            float dist = float(stepPx) * length(vec2(dx, dy));
            float wn = max(dot(np, octDecode(gq.xy)), 0.0);
            for (int k = 0; k < NORMAL_SQUARINGS; ++k) wn *= wn;  // cos^64: no pow per tap
            // distance and luminance stops in one exp (one transcendental per tap)
            float e = abs(gq.z - gp.z) / (zscale * max(dist, 1.0)) + abs(lum(cq.rgb) - lp) / lscale;
            float w = h[abs(dx)] * h[abs(dy)] * wn * exp(-e);
            sum += w * cq.rgb;
            vsum += w * w * cq.a;
            wsum += w;
        }
    vec3 c = sum / max(wsum, 1e-30);  // the centre always contributes (weight 1/4 > 0)
    float var = vsum / max(wsum * wsum, 1e-30);
    if (mode == 2) {
        vec3 lin = c * max(texelFetch(gAlbedo, px, 0).rgb, vec3(ALBEDO_FLOOR));
        outColor = vec4(pow(clamp(lin, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
    } else {
        outColor = vec4(c, var);
    }
}

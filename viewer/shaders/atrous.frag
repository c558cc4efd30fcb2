// Edge-aware a-trous wavelet filter of the shaded image (Dammertz et al. 2010, with SVGF's
// edge-stopping functions, Schied et al. 2017), guided by the G-buffer. Three modes, one draw each:
//   mode 0 (prepare): the display image (RGBA8, gamma 2.2) -> linear radiance divided by the
//          G-buffer albedo (texture detail is not noise: only the illumination is filtered), and in
//          alpha the luminance variance of its 3x3 neighbourhood (SVGF's spatial estimate);
//   mode 1 (filter): one 5x5 B3-spline step with holes `stepPx` apart; weights stop at normals,
//          at distance from the pixel's tangent plane (relative to the pixel footprint) and at
//          luminance differences large against the local standard deviation; variance filtered too;
//   mode 2 (filter and finish): as mode 1, then multiplied by the albedo again and gamma-encoded.
// Background and mirror pixels (albedo.a > 0.5: a reflected image, noise-free) are kept as shaded.
uniform sampler2D src;      // mode 0: the display image; else the previous step (float RGBA)
uniform sampler2D display;  // the display image (kept pixels, mode 2)
uniform sampler2D gPos;     // xyz world position, w distance along the primary ray
uniform sampler2D gNormal;
uniform sampler2D gAlbedo;
uniform isampler2D gId;
uniform int mode;
uniform int stepPx;
uniform float pixelAngle;   // 2 tan(fov_y / 2) / height: a pixel's footprint per unit distance
uniform float sigmaL;       // luminance edge-stop, in local standard deviations
uniform float sigmaN;       // normal edge-stop exponent
uniform float sigmaP;       // plane-distance edge-stop, in pixel footprints
out vec4 outColor;

const float ALBEDO_FLOOR = 0.02;  // demodulation of near-black albedo: no division blow-up

float lum(vec3 c) { return dot(c, vec3(0.2126, 0.7152, 0.0722)); }

bool kept(ivec2 q) {
    return texelFetch(gId, q, 0).r < 0 || texelFetch(gAlbedo, q, 0).a > 0.5;
}

vec3 demodulated(ivec2 q) {
    vec3 lin = pow(texelFetch(display, q, 0).rgb, vec3(2.2));
    return lin / max(texelFetch(gAlbedo, q, 0).rgb, vec3(ALBEDO_FLOOR));
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(gId, 0);
    if (kept(px)) {
        outColor = mode == 2 ? vec4(texelFetch(display, px, 0).rgb, 1.0) : vec4(0.0);
        return;
    }
    if (mode == 0) {
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
        return;
    }
    vec4 cp = texelFetch(src, px, 0);
    vec4 pp = texelFetch(gPos, px, 0);
    vec3 np = texelFetch(gNormal, px, 0).xyz;
    float lp = lum(cp.rgb);
    float footprint = pixelAngle * pp.w;
    float lscale = sigmaL * sqrt(cp.a) + 1e-3 * max(lp, 1e-6) + 1e-8;
    const float h[3] = float[](3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0);
    vec3 sum = vec3(0.0);
    float wsum = 0.0, vsum = 0.0;
    for (int dy = -2; dy <= 2; ++dy)
        for (int dx = -2; dx <= 2; ++dx) {
            ivec2 q = px + ivec2(dx, dy) * stepPx;
            if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size)) || kept(q)) continue;
            vec4 cq = texelFetch(src, q, 0);
            vec3 pq = texelFetch(gPos, q, 0).xyz;
            vec3 nq = texelFetch(gNormal, q, 0).xyz;
            float dist = float(stepPx) * length(vec2(dx, dy));
            float wn = pow(max(dot(np, nq), 0.0), sigmaN);
            float wp = exp(-abs(dot(np, pq - pp.xyz)) / (sigmaP * footprint * max(dist, 1.0) + 1e-30));
            float wl = exp(-abs(lum(cq.rgb) - lp) / lscale);
            float w = h[abs(dx)] * h[abs(dy)] * wn * wp * wl;
            sum += w * cq.rgb;
            vsum += w * w * cq.a;
            wsum += w;
        }
    vec3 c = sum / max(wsum, 1e-30);  // the centre always contributes (weight h0^2 > 0)
    float var = vsum / max(wsum * wsum, 1e-30);
    if (mode == 2) {
        vec3 lin = c * max(texelFetch(gAlbedo, px, 0).rgb, vec3(ALBEDO_FLOOR));
        outColor = vec4(pow(clamp(lin, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
    } else {
        outColor = vec4(c, var);
    }
}

// Composes the G-buffer and the effect accumulators into the final image, or shows one pass alone.
#include "sampling.glsl"
#include "lighting.glsl"
uniform sampler2D gPos;
uniform sampler2D gNormal;
uniform sampler2D gAlbedo;
uniform isampler2D gId;
uniform sampler2D accShadow;
uniform sampler2D accSoft;
uniform sampler2D accAO;
uniform sampler2D accDiffuse;
uniform sampler2D accReflect;
uniform int shadowOn, softOn, aoOn, diffuseOn, reflectOn;
uniform int numShadowLights;
uniform float exposure;
uniform int viewMode;  // see viewer/passes/shade.py SHADE_MODES
uniform float depthScale;
uniform float accScale[5];  // requested / accumulated sample passes (progressive), else 1
out vec4 fragColor;

vec4 acc(sampler2D t, int k, ivec2 px) { return texelFetch(t, px, 0) * accScale[k]; }

vec3 toDisplay(vec3 c) { return pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)); }

vec3 idColor(int id) {
    uint h = pcgHash(uint(id));
    return vec3(float(h & 255u), float((h >> 8) & 255u), float((h >> 16) & 255u)) / 255.0;
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int id = texelFetch(gId, px, 0).r;
    vec4 pos = texelFetch(gPos, px, 0);
    vec3 n = texelFetch(gNormal, px, 0).xyz;
    vec4 alb = texelFetch(gAlbedo, px, 0);
    vec3 sky = skyColor * ambient;
    vec3 c;
    if (id < 0) {
        c = (viewMode == 0) ? toDisplay(sky * exposure) : vec3(0.0);
        fragColor = vec4(c, 1.0);
        return;
    }
    float ao = aoOn != 0 ? acc(accAO, 2, px).r : 1.0;
    if (viewMode == 0) {
        vec3 e = vec3(0.0);
        if (shadowOn != 0) e += acc(accShadow, 0, px).rgb;
        else for (int i = 0; i < numPointLights; ++i) e += pointIrradiance(i, pos.xyz, n);
        if (softOn != 0) e += acc(accSoft, 1, px).rgb;
        else for (int i = 0; i < numRectLights; ++i) e += rectSampleIrradiance(i, rectCentre(i), pos.xyz, n);
        vec3 indirect = diffuseOn != 0 ? acc(accDiffuse, 3, px).rgb : sky * ao;
        vec3 l = alb.rgb / PI * e + alb.rgb * indirect;
        if (alb.a > 0.5 && reflectOn != 0) l = alb.rgb * acc(accReflect, 4, px).rgb;
        c = toDisplay(l * exposure);
    } else if (viewMode == 1) {
        c = alb.rgb;
    } else if (viewMode == 2) {
        c = n * 0.5 + 0.5;
    } else if (viewMode == 3) {
        c = vec3(1.0 - pos.w / (pos.w + depthScale));
    } else if (viewMode == 4) {
        c = vec3(acc(accShadow, 0, px).a / float(max(numShadowLights, 1)));
    } else if (viewMode == 5) {
        c = vec3(acc(accSoft, 1, px).a);
    } else if (viewMode == 6) {
        c = vec3(acc(accAO, 2, px).r);
    } else if (viewMode == 7) {
        c = toDisplay(acc(accDiffuse, 3, px).rgb * exposure);
    } else if (viewMode == 8) {
        c = alb.a > 0.5 ? toDisplay(acc(accReflect, 4, px).rgb * exposure) : vec3(0.0);
    } else {
        c = idColor(id);
    }
    fragColor = vec4(c, 1.0);
}

// Lights and the shading formula shared by the accumulate and shade passes.
#define MAX_POINT_LIGHTS 8
#define MAX_RECT_LIGHTS 4
uniform int numPointLights;
uniform vec3 pointPos[MAX_POINT_LIGHTS];
uniform vec3 pointIntensity[MAX_POINT_LIGHTS];
uniform int numRectLights;
uniform vec3 rectCorner[MAX_RECT_LIGHTS];
uniform vec3 rectU[MAX_RECT_LIGHTS];
uniform vec3 rectV[MAX_RECT_LIGHTS];
uniform vec3 rectRadiance[MAX_RECT_LIGHTS];
uniform vec3 skyColor;     // radiance of the environment (misses)
uniform float ambient;     // scale of sky light used as ambient term
uniform float lightRadius; // point lights are treated as tiny spheres: r^2 >= lightRadius^2 (no 1/r^2 blow-up)

// Irradiance at p (normal n) from point light i, unshadowed.
vec3 pointIrradiance(int i, vec3 p, vec3 n) {
    vec3 l = pointPos[i] - p;
    float d2 = max(dot(l, l), 1e-30);
    return pointIntensity[i] * max(0.0, dot(n, l)) * inversesqrt(d2) / max(d2, lightRadius * lightRadius);
}

// Irradiance at p from a point q on rect light i (one sample of an area of size A: A * L cos cos / r^2).
vec3 rectSampleIrradiance(int i, vec3 q, vec3 p, vec3 n) {
    vec3 nl = cross(rectU[i], rectV[i]);
    float area = length(nl);
    nl /= area;
    vec3 l = q - p;
    float d2 = max(dot(l, l), 1e-30);
    vec3 ld = l * inversesqrt(d2);
    float cosS = max(0.0, dot(n, ld));
    float cosL = max(0.0, -dot(nl, ld));
    return rectRadiance[i] * area * cosS * cosL / max(d2, lightRadius * lightRadius);
}

vec3 rectCentre(int i) { return rectCorner[i] + 0.5 * rectU[i] + 0.5 * rectV[i]; }

// Unshadowed direct irradiance from every light (rect lights approximated by their centre).
vec3 directIrradiance(vec3 p, vec3 n) {
    vec3 e = vec3(0.0);
    for (int i = 0; i < numPointLights; ++i) e += pointIrradiance(i, p, n);
    for (int i = 0; i < numRectLights; ++i) e += rectSampleIrradiance(i, rectCentre(i), p, n);
    return e;
}

// Radiance leaving a secondary hit towards the ray origin: Lambertian with unshadowed direct light
// plus the ambient sky term (one bounce; the hit point casts no further rays).
vec3 shadeSecondaryHit(vec3 p, vec3 n, vec3 albedo) {
    return albedo / PI * directIrradiance(p, n) + albedo * skyColor * ambient;
}

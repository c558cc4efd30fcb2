// Sampling helpers: per-pixel hashes, orthonormal bases, cosine-weighted hemisphere directions,
// cone perturbation, and scale-independent ray-origin offsets.
const float PI = 3.14159265358979;

uint pcgHash(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Two uniform numbers in [0,1) that depend only on the pixel and a stream id (stable over frames).
vec2 pixelRandom2(ivec2 px, uint stream) {
    uint h = pcgHash(uint(px.x) * 73856093u ^ uint(px.y) * 19349663u ^ stream * 83492791u);
    uint h2 = pcgHash(h);
    return vec2(float(h >> 8) * (1.0 / 16777216.0), float(h2 >> 8) * (1.0 / 16777216.0));
}

// Branchless ONB (Duff et al. 2017): the same normal always gives the same frame, so pixels on one
// plane share world-space directions (coherent rays, as CHC+RT sec. 5.3 relies on).
void makeBasis(vec3 n, out vec3 t, out vec3 b) {
    float s = n.z >= 0.0 ? 1.0 : -1.0;
    float a = -1.0 / (s + n.z);
    float c = n.x * n.y * a;
    t = vec3(1.0 + s * n.x * n.x * a, s * c, -s * n.x);
    b = vec3(c, s + n.y * n.y * a, -n.y);
}

vec3 cosineHemisphere(vec2 u) {
    float r = sqrt(u.x);
    float phi = 2.0 * PI * u.y;
    return vec3(r * cos(phi), r * sin(phi), sqrt(max(0.0, 1.0 - u.x)));
}

// Rotate direction d by a random angle of at most maxAngle (uniform over the spherical cap).
vec3 perturbInCone(vec3 d, float maxAngle, vec2 u) {
    if (maxAngle <= 0.0) return d;
    float cosMax = cos(maxAngle);
    float cosT = 1.0 - u.x * (1.0 - cosMax);
    float sinT = sqrt(max(0.0, 1.0 - cosT * cosT));
    float phi = 2.0 * PI * u.y;
    vec3 t, b;
    makeBasis(d, t, b);
    return normalize(t * (sinT * cos(phi)) + b * (sinT * sin(phi)) + d * cosT);
}

// Wächter & Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray Tracing Gems 6):
// move p a few float ulps along n. Scale-independent: no per-scene epsilon.
vec3 offsetRayOrigin(vec3 p, vec3 n) {
    const float originEps = 1.0 / 32.0;
    const float floatScale = 1.0 / 65536.0;
    const float intScale = 256.0;
    ivec3 ofi = ivec3(intScale * n);
    vec3 pi = vec3(
        intBitsToFloat(floatBitsToInt(p.x) + (p.x < 0.0 ? -ofi.x : ofi.x)),
        intBitsToFloat(floatBitsToInt(p.y) + (p.y < 0.0 ? -ofi.y : ofi.y)),
        intBitsToFloat(floatBitsToInt(p.z) + (p.z < 0.0 ? -ofi.z : ofi.z)));
    precise vec3 q = vec3(abs(p.x) < originEps ? p.x + floatScale * n.x : pi.x,
                          abs(p.y) < originEps ? p.y + floatScale * n.y : pi.y,
                          abs(p.z) < originEps ? p.z + floatScale * n.z : pi.z);
    return q;
}

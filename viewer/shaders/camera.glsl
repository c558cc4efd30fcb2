// Pinhole camera shared by rasterization and ray generation so both use the same pixel rays.
uniform vec3 camPos;
uniform vec3 camRight;   // unit
uniform vec3 camUp;      // unit
uniform vec3 camForward; // unit
uniform float tanHalfFov;
uniform vec2 viewport;   // width, height in pixels

vec3 primaryDir(vec2 fragCoord) {
    // precise: no fused multiply-adds, the same directions on every driver (docs/numerics.md)
    precise vec2 ndc = fragCoord / viewport * 2.0 - 1.0;  // fragCoord is the pixel centre (x + 0.5, y + 0.5)
    precise float aspect = viewport.x / viewport.y;
    precise vec3 d = camRight * (ndc.x * tanHalfFov * aspect) + camUp * (ndc.y * tanHalfFov) + camForward;
    return normalize(d);
}

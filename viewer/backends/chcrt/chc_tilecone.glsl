// CHC+RT, GPU-driven pass: what a tile's rays can reach (chc_tilebounds.comp writes it), and the two
// lower bounds the cull (chc_querycull.comp) and the gap order (chc_visorder.comp) test a box with.
// origin box; omin.w = farthest distance a ray may still reach, omax.w = active rays; cone.xyz = unit
// axis, cone.w = half angle in radians around it of every active ray's direction (> 3.2: no cone);
// side[i].xyz = unit normal of a plane through the origin box's centre (spanned by two corner rays of
// the tile), side[i].w = the least n . d / |d| over the tile's active rays, at most 0 (n = 0: none)
struct TileBound { vec4 omin; vec4 omax; vec4 cone; vec4 side[4]; };

// a lower bound of the distance from every ray origin of the tile to the box (the relative margin
// covers the rounding of the gap and of the rays' own box tests)
float tileGap(vec3 bmin, vec3 bmax, TileBound t) {
    vec3 gap = max(max(bmin - t.omax.xyz, t.omin.xyz - bmax), vec3(0.0));
    return length(gap) * (1.0 - 1e-4);
}

// may a ray of the tile point at the box? Every ray starts in the sphere around the origin box and
// points inside the tile's cone; the box lies in its bounding sphere. A ray from o through p (p in
// the box) has the direction of (c - oc) + (p - c) - (o - oc), a vector within R = r + ro of
// v = c - oc, so at least phi - beta from the axis (phi: angle of v, sin beta = R / |v|).
// Beyond the half angle (with a margin of 1e-3 radians, far above the rounding of these angles and
// of the rays' conservative slab tests) no ray of the tile can enter the box. Angles only: no scale.
bool tileCone(vec3 bmin, vec3 bmax, TileBound t) {
    if (t.cone.w > 3.0) return true;
    vec3 oc = 0.5 * (t.omin.xyz + t.omax.xyz);
    float ro = 0.5 * length(t.omax.xyz - t.omin.xyz);
    vec3 v = 0.5 * (bmin + bmax) - oc;
    // the centres' rounding is absolute (bounded by the coordinates' size, e.g. a scene at 1e6): R
    // grows by a bound of it, so the computed v is within R of the true one
    vec3 m = max(max(abs(bmin), abs(bmax)), max(abs(t.omin.xyz), abs(t.omax.xyz)));
    float R = (0.5 * length(bmax - bmin) + ro) * (1.0 + 1e-4) + 1e-6 * max(max(m.x, m.y), m.z);
    float dist = length(v);
    if (!(dist > R * 1.0001)) return true;  // an origin may lie inside the sphere (or NaN: keep)
    float phi = atan(length(cross(v, t.cone.xyz)), dot(v, t.cone.xyz));
    float beta = asin(R / dist);
    return phi - beta <= t.cone.w + 1e-3;
}

// may a ray of the tile reach the box across the side planes? A ray from o (within ro of the origin
// box's centre oc) along unit d with n . d >= s (s <= 0) has n . (p - oc) >= -ro + s |p - o| at every
// point p, and |p - o| <= reach + ro for p in the box. A box whose largest n . (x - oc) lies below that
// (a relative margin of 1e-4 of the distance, and the centres' absolute rounding e) is entered by no
// ray. For camera rays (one origin, s ~ 0) these are the tile's frustum planes: tighter than the cone
// for a rectangular tile and a long box.
bool tileSides(vec3 bmin, vec3 bmax, TileBound t) {
    vec3 oc = 0.5 * (t.omin.xyz + t.omax.xyz);
    float ro = 0.5 * length(t.omax.xyz - t.omin.xyz);
    vec3 h = 0.5 * (bmax - bmin);
    vec3 v = 0.5 * (bmin + bmax) - oc;
    vec3 m = max(max(abs(bmin), abs(bmax)), max(abs(t.omin.xyz), abs(t.omax.xyz)));
    float e = 1e-6 * max(max(m.x, m.y), m.z);
    float far = length(v) + length(h) + e + ro;
    for (int i = 0; i < 4; ++i) {
        vec3 n = t.side[i].xyz;
        float top = dot(n, v) + dot(abs(n), h) + e;
        if (top < -ro + t.side[i].w * far - 1e-4 * far) return false;
    }
    return true;
}

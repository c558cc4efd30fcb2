// CHC+RT: one representative ray per finest tile (the first active ray among the tile's centre
// and four inner points), for the approximate front-to-back order of scheduled subtrees.
uniform sampler2D rayOrigin;
uniform sampler2D rayDir;
uniform ivec2 raySize;
uniform int level;
layout(location = 0) out vec4 outOrigin;
layout(location = 1) out vec4 outDir;
void main() {
    ivec2 t = ivec2(gl_FragCoord.xy);
    ivec2 lo = (t * raySize) >> level;
    ivec2 hi = ((t + 1) * raySize) >> level;
    ivec2 sz = max(hi - lo, ivec2(1));
    outOrigin = vec4(0.0);
    outDir = vec4(0.0, 0.0, 0.0, -1.0);
    const vec2 pts[5] = vec2[5](vec2(0.5, 0.5), vec2(0.25, 0.25), vec2(0.75, 0.25), vec2(0.25, 0.75),
                                vec2(0.75, 0.75));
    for (int i = 0; i < 5; ++i) {
        ivec2 px = min(lo + ivec2(vec2(sz) * pts[i]), raySize - 1);
        vec4 o = texelFetch(rayOrigin, px, 0);
        vec4 d = texelFetch(rayDir, px, 0);
        if (d.w > o.w) { outOrigin = o; outDir = d; return; }
    }
}

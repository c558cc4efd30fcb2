// The glsl traversal as a full-screen fragment draw: one fragment per ray, hits through the
// framebuffer (the ray batch's HitBuffer: t, triangle id). The traversal: trace_glsl_body.glsl.
layout(location = 0) out float outT;
layout(location = 1) out int outId;
#define TRACE_PIXEL ivec2(gl_FragCoord.xy)
#define TRACE_OUTSIDE(px) false
#define TRACE_KEEP(px) discard
#define TRACE_WRITE(px, t, id) { outT = (t); outId = (id); }
#include "trace_glsl_body.glsl"

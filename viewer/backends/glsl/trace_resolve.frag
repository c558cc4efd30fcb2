// The compute stage's hits (trace_glsl.comp's TraceHits words) into the HitBuffer's attachments, one
// full-screen draw after the run's dispatches; a pixel marked KEEP_HIT keeps the hit it has.
layout(std430, binding = BIND_TRACE_HITS) readonly buffer TraceHits { uint hitWords[]; };
uniform int width;
layout(location = 0) out float outT;
layout(location = 1) out int outId;
#define KEEP_HIT -3

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    int i = 2 * (px.y * width + px.x);
    int id = int(hitWords[i + 1]);
    if (id == KEEP_HIT) discard;
    outT = uintBitsToFloat(hitWords[i]);
    outId = id;
}

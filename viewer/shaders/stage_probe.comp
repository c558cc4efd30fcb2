// The stage probe, compute stage (viewer/gl/stages.py): one invocation per pixel, 8x8 per group.
#include "stage_probe.glsl"
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = BIND_STAGE_PROBE) writeonly buffer ProbeOut { float probeOut[]; };
uniform int width;
void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    probeOut[p.y * width + p.x] = probeWork(p);
}

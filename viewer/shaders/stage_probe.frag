// The stage probe, fragment stage (viewer/gl/stages.py): one fragment per pixel of its target.
#include "stage_probe.glsl"
layout(location = 0) out float outValue;
void main() { outValue = probeWork(ivec2(gl_FragCoord.xy)); }

// The glsl traversal as a compute dispatch (stage=compute, gl_traversal.py): one invocation per ray
// in work groups of 8x8 pixels, the same traversal (trace_glsl_body.glsl), the same bits. Why a
// second stage: a GPU may run compute shaders on many more of its processors than fragment shaders
// (an NVIDIA H100 or H200 has its graphics pipeline on a few of them; docs/device-limits.md).
// Hits go to an SSBO, 2 words per pixel (row-major): t's bits and the triangle id, or KEEP_HIT
// where the pixel keeps the hit it has (trace_resolve.frag writes them into the HitBuffer).
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = BIND_TRACE_HITS) writeonly buffer TraceHits { uint hitWords[]; };
uniform ivec2 raySize;
uniform int firstDispatch;  // 1: the run's first dispatch (every pixel's words written)
#define KEEP_HIT -3
#define TRACE_PIXEL ivec2(gl_GlobalInvocationID.xy)
#define TRACE_OUTSIDE(px) any(greaterThanEqual(px, raySize))
#define TRACE_WORD(px) (2 * ((px).y * raySize.x + (px).x))
// (a later dispatch of the run leaves a finished pixel's words alone)
#define TRACE_KEEP(px) { if (firstDispatch != 0) hitWords[TRACE_WORD(px) + 1] = uint(KEEP_HIT); return; }
#define TRACE_WRITE(px, t, id) { hitWords[TRACE_WORD(px)] = floatBitsToUint(t); hitWords[TRACE_WORD(px) + 1] = uint(id); }
#include "trace_glsl_body.glsl"

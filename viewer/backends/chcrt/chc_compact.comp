// CHC+RT, GPU-driven steady state: query results are used on the GPU. One invocation per query
// record of this pass: a query of pairs that were invisible (info.y > 0 intersection items) whose
// shader-counted passing fragments exceed the threshold appends its intersection record (the
// tile's rectangle and the pairs' subtrees) to the visible list and bumps the instance count of the
// indirect draw command, so the newly visible pairs are intersected in the same pass by ONE
// indirect instanced draw, without the host waiting for the query. The host reads the counts a
// frame later, to refine the front.
layout(local_size_x = 64) in;
struct ChcDraw { ivec4 rect; ivec4 info; };  // rect = x, y, w, h; info = item base, count, query slot
layout(std430, binding = BIND_CHC_QUERY_COUNTS) readonly buffer ChcQueryCounts { uint chcPassed[]; };
layout(std430, binding = BIND_CHC_CANDIDATES) readonly buffer ChcCandidates { ChcDraw cand[]; };
layout(std430, binding = BIND_CHC_DRAWS) writeonly buffer ChcVisible { ChcDraw vis[]; };
// DrawArraysIndirectCommand: vertices (6), instances (set here), first vertex, base instance
layout(std430, binding = BIND_CHC_INDIRECT) buffer ChcIndirect { uint cmdCount; uint cmdInstances; uint cmdFirst;
                                                                 uint cmdBase; };
uniform int nCandidates;
uniform uint threshold;
void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= nCandidates) return;
    ChcDraw c = cand[i];
    if (c.info.y > 0 && chcPassed[c.info.z] > threshold) vis[atomicAdd(cmdInstances, 1u)] = c;
}

// CHC+RT device front, end of a pass (one invocation): the pass's active rays (the init draw's
// ray-count slots), query tests x pixels and records drawn (chc_querycull.comp's slots after the
// pairs') added to the frame's statistics (META slot 0), read once after the frame.
layout(local_size_x = 1) in;
#include "chc_front.glsl"
layout(std430, binding = BIND_FR_COUNTS) readonly buffer Counts { uint counts[]; };
layout(std430, binding = BIND_FR_META) buffer Meta { int meta[]; };
uniform int raySlots;
uniform int capacity;
uniform int statBase;

void main() {
    uint rays = 0u;
    for (int k = 0; k < raySlots; ++k) rays += counts[k];
    // int adds wrap like uint ones: the host reads the statistics as uint32
    meta[statBase + STAT_RAYS] += int(rays);
    meta[statBase + STAT_QUERY_PIXELS] += int(counts[raySlots + capacity]);
    meta[statBase + STAT_RECORDS_DRAWN] += int(counts[raySlots + capacity + 1]);
}

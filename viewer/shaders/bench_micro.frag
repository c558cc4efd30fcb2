// GL micro-benchmark: a flat colour, optionally counting fragments per instance with atomics.
uniform vec4 value;
uniform int countAtomics;
layout(std430, binding = BIND_MICRO) buffer MicroCounts { uint counts[]; };
flat in int inst;
out vec4 color;
void main() {
    if (countAtomics != 0) atomicAdd(counts[inst], 1u);
    color = value;
}

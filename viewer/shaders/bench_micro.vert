// GL micro-benchmark (viewer/bench/gl_micro.py): one big triangle kept to a tile by the scissor
// box, or an instanced grid of small quads (one per "query").
uniform int instanced;
uniform ivec2 grid;  // instance grid (columns, rows) over the target
uniform vec2 cell;   // NDC step between grid cells
uniform vec2 quad;   // NDC size of one instance
flat out int inst;
void main() {
    inst = gl_InstanceID;
    if (instanced == 0) {  // one big triangle; the scissor box keeps it to a tile
        gl_Position = vec4(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0, 0.0, 1.0);
        return;
    }
    vec2 corner = vec2(gl_VertexID & 1, gl_VertexID >> 1);
    ivec2 c = ivec2(gl_InstanceID % grid.x, (gl_InstanceID / grid.x) % grid.y);
    gl_Position = vec4(-1.0 + vec2(c) * cell + corner * quad, 0.0, 1.0);
}

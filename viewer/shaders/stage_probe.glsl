// The stage probe's work (viewer/gl/stages.py): the same arithmetic per pixel in a fragment draw
// (stage_probe.frag) and a compute dispatch (stage_probe.comp), `iterations` long, so that their
// times compare how much of the device each stage gets.
uniform int iterations;
float probeWork(ivec2 p) {
    float x = float(p.x) * 0.001, y = float(p.y) * 0.001;
    for (int i = 0; i < iterations; ++i) {
        x = fract(x * 1.37 + y);
        y = fract(y * 0.91 + x * 0.5);
    }
    return x + y;
}

"""Check the GL timer queries of this device against wall time (why profiler.py syncs on llvmpipe).

Run: python3 -m viewer.timer_check. Draws one full-screen pass of equal total work on targets
of growing size and prints what GL_TIME_ELAPSED reports next to glFinish-bracketed wall time.
"""

from __future__ import annotations

import time

import numpy as np

HEAVY_VS = "#version 330\nin vec2 p; void main() { gl_Position = vec4(p, 0.0, 1.0); }"
HEAVY_FS = """#version 330
uniform int n; out vec4 c;
void main() { float a = gl_FragCoord.x; for (int i = 0; i < n; ++i) a = sin(a * 1.0001 + float(i)); c = vec4(a); }"""


def measure(ctx, sizes=(64, 128, 256, 512), work: int = 1000 * 512 * 512) -> list[dict]:
    """Per target size: timer ms and wall ms of one draw (best of two after a warm-up)."""
    prog = ctx.program(vertex_shader=HEAVY_VS, fragment_shader=HEAVY_FS)
    vbo = ctx.buffer(np.array([-1, -1, 3, -1, -1, 3], "f4").tobytes())
    vao = ctx.vertex_array(prog, vbo, "p")
    q = ctx.query(time=True)
    rows = []
    for size in sizes:
        fbo = ctx.framebuffer(color_attachments=[ctx.texture((size, size), 4, dtype="f4")])
        fbo.use()
        prog["n"] = max(1, work // (size * size))
        best = None
        for rep in range(3):
            ctx.finish()
            t0 = time.perf_counter()
            with q:
                vao.render()
            ctx.finish()
            wall = (time.perf_counter() - t0) * 1e3
            timer = q.elapsed / 1e6
            if rep and (best is None or wall < best[1]):
                best = (timer, wall)
        rows.append({"size": size, "timer_ms": best[0], "wall_ms": best[1]})
        fbo.release()
    return rows


def main() -> None:
    from viewer.gl.context import shared_context

    ctx = shared_context()
    print(f"device: {ctx.info.get('GL_RENDERER')}")
    print(f"{'target':>10} {'timer ms':>10} {'wall ms':>10} {'timer/wall':>10}")
    for r in measure(ctx):
        print(f"{r['size']:>4}x{r['size']:<5} {r['timer_ms']:>10.1f} {r['wall_ms']:>10.1f} "
              f"{r['timer_ms'] / r['wall_ms']:>10.2f}")


if __name__ == "__main__":
    main()

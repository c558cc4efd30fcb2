"""Where the ray traversals run on this device: fragment or compute shaders.

Every GL traversal can run in either stage with the same bits (glsl `stage`, chcrt `visible_stage`
and `full_bvh_stage`). Which is faster depends on the device: llvmpipe runs the traversals' fragment
stage 1.3-1.8x faster (docs/results/chcrt.md), while an NVIDIA H100 or H200 runs fragment shaders on
4 of its 132 processors and compute shaders on all of them (docs/device-limits.md). `auto` (the
default) therefore takes the fragment stage on a software rasterizer, and elsewhere what a probe
measures once per context: the same arithmetic per pixel in a fragment draw and a compute dispatch,
sized up until the fragment draw takes PROBE_MIN_MS, best of PROBE_TRIALS alternated trials; the
compute stage only when it is COMPUTE_MARGIN times faster (a device that runs both alike keeps the
fragment stage, whose traversals need no copy of their hits).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import moderngl

from viewer.gl.bindings import BIND_STAGE_PROBE
from viewer.gl.limits import is_software_renderer
from viewer.gl.programs import FullscreenQuad, ProgramCache, compute_shader

STAGES = ("fragment", "compute")
STAGE_CHOICES = ("auto", *STAGES)
COMPUTE_MARGIN = 2.0
PROBE_MIN_MS = 10.0
PROBE_TRIALS = 3
PROBE_SIDE = 256  # pixels a side of the probe's target (64 Ki invocations: every processor of a large GPU)
PROBE_MAX_ITERATIONS = 1 << 16
_KEY = "rtwalk_stage_probe"  # where a context keeps its probe (ctx.extra)


@dataclass
class StageProbe:
    """The probe's result: each stage's best time for the same work, and the stage it chose."""

    fragment_ms: float
    compute_ms: float
    iterations: int  # per pixel, of PROBE_SIDE x PROBE_SIDE pixels

    @property
    def choice(self) -> str:
        return "compute" if self.fragment_ms > COMPUTE_MARGIN * self.compute_ms else "fragment"


def measure_stages(ctx: moderngl.Context) -> StageProbe:
    """Time the probe's work in both stages (module docstring); a few milliseconds on most devices."""
    side = PROBE_SIDE
    programs = ProgramCache(ctx)
    frag = programs.get("fullscreen.vert", "stage_probe.frag")
    comp = compute_shader(ctx, "stage_probe.comp")
    target = ctx.texture((side, side), 1, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[target])
    out = ctx.buffer(reserve=4 * side * side)
    quad = FullscreenQuad(ctx)
    comp["width"] = side

    def timed(run) -> float:
        ctx.finish()
        t0 = time.perf_counter()
        run()
        ctx.finish()
        return (time.perf_counter() - t0) * 1e3

    def fragment() -> None:
        fbo.use()
        quad.render(frag)

    def compute() -> None:
        out.bind_to_storage_buffer(BIND_STAGE_PROBE)
        comp.run(side // 8, side // 8)

    try:
        iterations = 16
        while True:
            frag["iterations"] = comp["iterations"] = iterations
            times = [(timed(fragment), timed(compute)) for _ in range(PROBE_TRIALS)]
            frag_ms, comp_ms = min(t[0] for t in times), min(t[1] for t in times)
            if max(frag_ms, comp_ms) >= PROBE_MIN_MS or iterations >= PROBE_MAX_ITERATIONS:
                return StageProbe(frag_ms, comp_ms, iterations)
            iterations *= 4
    finally:
        ctx.memory_barrier(moderngl.ALL_BARRIER_BITS)  # (the probe's writes, before anything else runs)
        for obj in (quad, fbo, target, out, comp, programs):
            obj.release()


def preferred_stage(ctx: moderngl.Context) -> str:
    """The stage `auto` takes on this context: fragment on a software rasterizer, else the probe's
    choice (measured once per context)."""
    if is_software_renderer(ctx.info.get("GL_RENDERER")):
        return "fragment"
    return stage_probe(ctx).choice


def stage_probe(ctx: moderngl.Context) -> StageProbe:
    """This context's probe, measured on first use."""
    extra = ctx.extra if isinstance(ctx.extra, dict) else {}
    probe = extra.get(_KEY)
    if probe is None:
        probe = extra[_KEY] = measure_stages(ctx)
        ctx.extra = extra
    return probe


def resolve_stage(ctx: moderngl.Context, stage: str) -> str:
    """`stage` ("auto", "fragment" or "compute") as the stage to run on this context."""
    return preferred_stage(ctx) if stage == "auto" else stage

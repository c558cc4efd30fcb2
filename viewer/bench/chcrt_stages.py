"""`rtwalk bench-chcrt --study stages`: where the ray traversals run, fragment or compute shaders.

glsl traverses in a full-screen fragment draw or a compute dispatch (its `stage`); chcrt's visible
records and whole-BVH passes likewise (`visible_stage`, `full_bvh_stage`). The hits are the same
bits either way (tests/test_trace_stage.py); the time is not: a GPU may run compute shaders on many
more processors than fragment shaders (an NVIDIA H100 or H200 has its graphics pipeline on a few,
docs/device-limits.md), while llvmpipe runs its fragment shaders faster. Per recording x size x
effect (table2's options), four configurations interleaved frame by frame: glsl and chcrt, each in
both stages; the speedups of compute over fragment, and chcrt's over glsl within each stage.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from viewer.bench.chcrt_common import finish_study, table2_rows
from viewer.bench.plots import figure, finish
from viewer.bench.report import fmt, md_table, notes_md, ratio, size_text

#: (label, backend, parameters) of the four configurations, fragment stage first
CONFIGS = (("glsl fragment", "glsl", "stage=fragment"), ("glsl compute", "glsl", "stage=compute"),
           ("chcrt fragment", "chcrt", "visible_stage=fragment,full_bvh_stage=fragment"),
           ("chcrt compute", "chcrt", "visible_stage=compute,full_bvh_stage=compute"))


@dataclass
class StagesRow:
    """One (recording, size, effect): steady trace ms of the four configurations and their ratios."""

    recording: str
    size: str
    effect: str
    rays_per_frame: float
    glsl_fragment_ms: float
    glsl_compute_ms: float
    chcrt_fragment_ms: float
    chcrt_compute_ms: float
    glsl_compute_speedup: float  # glsl fragment / glsl compute (> 1: compute faster)
    chcrt_compute_speedup: float  # chcrt fragment / chcrt compute
    chcrt_speedup_fragment: float  # glsl / chcrt, both fragment (table2's figure)
    chcrt_speedup_compute: float  # glsl / chcrt, both compute
    chcrt_speedup_best: float  # the faster glsl / the faster chcrt


def study_stages(b) -> dict:
    """The four configurations per recording x size x effect (module docstring). `b` is bench.chcrt.Bench."""
    o = b.o
    rows: list[StagesRow] = []
    runs = []
    for path, size, effect, results in table2_rows(b, "stages", CONFIGS):
        runs += [asdict(r) for r in results]
        gf, gc, cf, cc = (r.best.trace_ms for r in results)
        rows.append(StagesRow(path.stem, size_text(size), effect, results[0].best.rays, gf, gc, cf, cc,
                              ratio(gf, gc), ratio(cf, cc), ratio(gf, cf), ratio(gc, cc),
                              ratio(min(gf, gc), min(cf, cc))))
    report = b.header("stages", o, {"recordings": [p.stem for p in o.recordings], "effects": o.effects,
                                    "configs": [list(c) for c in CONFIGS]})
    report.update(rows=[asdict(r) for r in rows], runs=runs)
    md = [f"## Fragment or compute stages: glsl and chcrt in both (steady state of {o.frames} consecutive frames)",
          "", f"Device: {b.device_text}. Trace ms = the GPU tracing phases per frame (mean of frames 2..N), the "
          "four configurations interleaved frame by frame. 'compute / fragment' = fragment ms / compute ms "
          "(> 1: compute faster); 'chcrt vs glsl' = glsl ms / chcrt ms in the same stage, and between the "
          "faster stage of each.", ""]
    md.append(md_table(
        ["recording", "size", "effect", "glsl frag ms", "glsl comp ms", "chcrt frag ms", "chcrt comp ms",
         "glsl compute / fragment", "chcrt compute / fragment", "chcrt vs glsl, fragment", "chcrt vs glsl, compute",
         "chcrt vs glsl, best"],
        [[r.recording, r.size, r.effect, fmt(r.glsl_fragment_ms), fmt(r.glsl_compute_ms), fmt(r.chcrt_fragment_ms),
          fmt(r.chcrt_compute_ms), fmt(r.glsl_compute_speedup, 2), fmt(r.chcrt_compute_speedup, 2),
          fmt(r.chcrt_speedup_fragment, 2), fmt(r.chcrt_speedup_compute, 2), fmt(r.chcrt_speedup_best, 2)]
         for r in rows]))
    md += notes_md(report["notes"])
    _plot(rows, o.out / "stages.png", b.device["renderer"])
    return finish_study(o, "stages", report, "\n".join(md))


def _plot(rows: list[StagesRow], path, device: str) -> None:
    fig, axes = figure(1, 1, size=(max(6.0, 1.6 * len(rows) + 2), 3.6), squeeze=False)
    ax = axes[0][0]
    width = 0.2
    for k, (label, key) in enumerate((("glsl fragment", "glsl_fragment_ms"), ("glsl compute", "glsl_compute_ms"),
                                      ("chcrt fragment", "chcrt_fragment_ms"), ("chcrt compute", "chcrt_compute_ms"))):
        ax.bar([i + (k - 1.5) * width for i in range(len(rows))], [getattr(r, key) for r in rows], width, label=label)
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels([f"{r.recording}\n{r.size} {r.effect}" for r in rows], fontsize=7)
    ax.set_ylabel("trace ms per frame")
    ax.legend(fontsize=7)
    finish(fig, path, f"fragment or compute stages - {device}")

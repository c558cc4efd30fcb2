"""`rtwalk bench-chcrt --study coherence`: ray coherence vs per-pixel sample rotation (CHC+RT section 5.3,
Table 5 and Figure 10).

All pixels of one AO / diffuse sample pass share one Halton direction, rotated per pixel by a
random angle of at most `perturb` degrees (raygen.frag). No rotation makes the rays of a tile
parallel (coherent: few visible pairs per tile, cheap queries) but shows structured artifacts
(the colour bleeding of Figure 10 comes in bands); a full rotation (180) decorrelates pixels.
Per path x effect, glsl and chcrt run at each rotation (interleaved frame by frame): steady trace
ms and chcrt's queries and scheduled subtrees (Table 5 analog), and the last frame's images side by
side, chcrt above glsl (Figure 10 analog; conservative chcrt gives glsl's image).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from viewer.bench.chcrt_common import finish_study, join_params, save_png
from viewer.bench.harness import RunSpec
from viewer.bench.plots import figure, finish
from viewer.bench.report import fmt, md_table, notes_md, ratio


@dataclass
class Table5Row:
    recording: str
    effect: str
    perturb_deg: float
    glsl_trace_ms: float
    chcrt_trace_ms: float
    speedup: float  # glsl / chcrt
    queries: float
    subtrees_scheduled: float
    visible_pairs: float
    max_abs_diff: float  # chcrt vs glsl image, last frame (0..255)


def study_coherence(b) -> dict:
    """Table 5 / Figure 10 analogs (module docstring). `b` is bench.chcrt.Bench."""

    o = b.o
    size = o.sizes[0]
    rows: list[Table5Row] = []
    runs = []
    shots: dict[tuple[str, str], list[tuple[float, np.ndarray, np.ndarray]]] = {}
    img_dir = o.out / "coherence-images"
    img_dir.mkdir(parents=True, exist_ok=True)
    b.progress("coherence", len(o.coherence_recordings) * len(o.coherence_effects) * len(o.perturbs) * 2 * o.frames)
    try:
        for path in o.coherence_recordings:
            for effect in o.coherence_effects:
                images: list[list[np.ndarray]] = []
                specs = []
                for deg in o.perturbs:
                    for backend in ("glsl", "chcrt"):
                        store: list[np.ndarray] = []
                        images.append(store)

                        def sink(k: int, n: int, img: np.ndarray, store=store) -> None:
                            store[:] = [img]  # keep the last frame

                        params = join_params("overdraw_overlay=0", o.chcrt) if backend == "chcrt" else None
                        specs.append(RunSpec(f"{backend} {deg:g}", f"{effect}@perturb={deg:g}", backend, params, sink))
                results = b.run_many(path, size, specs)
                runs += [asdict(r) for r in results]
                for i, deg in enumerate(o.perturbs):
                    g, c = results[2 * i], results[2 * i + 1]
                    ig, ic = images[2 * i][0], images[2 * i + 1][0]
                    diff = float(np.abs(ig.astype(np.int16) - ic.astype(np.int16)).max())
                    cs = c.best.counters
                    rows.append(Table5Row(path.stem, effect, deg, g.best.trace_ms, c.best.trace_ms,
                                          ratio(g.best.trace_ms, c.best.trace_ms), cs.get("queries", 0.0),
                                          cs.get("subtrees_scheduled", 0.0), cs.get("visible_pairs", 0.0), diff))
                    shots.setdefault((path.stem, effect), []).append((deg, ic, ig))
                    save_png(img_dir / f"{path.stem}-{effect.replace(':', '')}-perturb{deg:g}.png", ic)
    finally:
        b.done()
    report = b.header("coherence", o, {"recordings": [p.stem for p in o.coherence_recordings], "size": list(size),
                                       "effects": o.coherence_effects, "perturbs": o.perturbs})
    report.update(rows=[asdict(r) for r in rows], runs=runs)
    md = [f"## Table 5 analog: per-pixel sample rotation ({o.frames} consecutive frames, steady state)", "",
          f"Device: {b.device_text}. perturb = maximum per-pixel rotation of the shared sample direction "
          "(degrees; 180 = full). 'img diff' = largest channel difference chcrt vs glsl on the last frame.", ""]
    md.append(md_table(["path", "effect", "perturb", "glsl trace ms", "chcrt trace ms", "glsl/chcrt", "queries",
                        "subtrees", "visible pairs", "img diff"],
                       [[r.recording, r.effect, fmt(r.perturb_deg, 0), fmt(r.glsl_trace_ms), fmt(r.chcrt_trace_ms),
                         fmt(r.speedup, 2), fmt(r.queries, 0), fmt(r.subtrees_scheduled, 0), fmt(r.visible_pairs, 0),
                         fmt(r.max_abs_diff, 0)] for r in rows]))
    md += ["", "Figure 10 analog: coherence.png (per path and effect: chcrt above glsl, rotation left to right); "
               "single images in coherence-images/."]
    md += notes_md(report["notes"])
    _plot(shots, o.out / "coherence.png", b.device["renderer"])
    return finish_study(o, "coherence", report, "\n".join(md))


def _plot(shots: dict, path, device: str) -> None:
    keys = list(shots)
    ncols = max(len(v) for v in shots.values())
    fig, axes = figure(2 * len(keys), ncols, size=(3.2 * ncols, 2.0 * 2 * len(keys)), squeeze=False)
    for i, key in enumerate(keys):
        for j, (deg, ic, ig) in enumerate(shots[key]):
            for r, (img, who) in enumerate(((ic, "chcrt"), (ig, "glsl"))):
                ax = axes[2 * i + r][j]
                ax.imshow(img)
                ax.set_xticks([])
                ax.set_yticks([])
                ax.set_title(f"{key[0]} {key[1]} {who}, rotation {deg:g} deg", fontsize=6)
    finish(fig, path, f"CHC+RT sample rotation (Figure 10 analog) - {device}")

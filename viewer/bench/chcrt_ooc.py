"""`rtwalk bench-chcrt --study ooc`: the out-of-core tables of CHC+RT (Mattausch et al., EG 2015, section 5.4).

The city recordings (near and far paths) are re-run on a larger city (``--ooc-scene-size``, the
City-200 analog) with chcrt fully in core and with GPU budgets that hold the paper's 47 %, 32 % and
20 % of the scene's BVH + triangles (``gpu_budget_fraction``, chcrt_cache):

- Table 1 analog: triangles, total / BVH / geometry MB, budget, % in core, the resident BVH top
  and the cache buffers, per budget;
- Table 3 analog: per path x effect x budget, trace ms, Mrays/s, queries and the MB transferred per
  frame (BVH and geometry), subtrees uploaded, cache hits, uploads that waited for the GPU;
- a plot of the transfers per frame over the path next to the chc phase bars (Figure 8 style);
- peak memory (VmHWM) of loading + building the scene and of rendering.

The budgets of one row are interleaved frame by frame (harness protocol), one renderer each.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from viewer.bench.chcrt_common import chc_phases, finish_study, join_params
from viewer.bench.harness import RunSpec, is_trace_phase
from viewer.bench.plots import figure, finish, stacked
from viewer.bench.report import fmt, md_table, notes_md, ratio, size_text

GIB = float(1 << 30)
MB = float(1 << 20)


def _proc_status_kb(key: str) -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


def peak_rss_gib() -> float:
    """Peak resident memory of this process since start or the last reset_peak_rss()."""
    return _proc_status_kb("VmHWM") / (1 << 20)


def reset_peak_rss() -> bool:
    """Reset VmHWM to the current RSS (Linux: 5 > /proc/self/clear_refs); False where not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def scaled_recording(path: Path, size: int, out: Path) -> Path:
    """A copy of a builtin-scene recording whose scene has `size` triangles (same camera path)."""
    data = json.loads(path.read_text())
    data["scene"] = {**data["scene"], "size": int(size)}
    out.mkdir(parents=True, exist_ok=True)
    dst = out / f"{path.stem}-{size}.json"
    dst.write_text(json.dumps(data, indent=1))
    return dst


@dataclass
class Table1Row:
    config: str
    triangles: int
    total_mb: float
    bvh_mb: float
    geometry_mb: float
    budget_mb: float
    in_core_pct: float
    resident_top_mb: float
    top_nodes: int
    cache_bvh_mb: float
    cache_geometry_mb: float


@dataclass
class Table3Row:
    recording: str
    effect: str
    config: str
    trace_ms: float
    wall_ms: float
    mrays_per_s: float
    queries: float
    upload_bvh_mb: float  # per frame
    upload_geom_mb: float
    subtrees_uploaded: float
    cache_hits: float
    upload_syncs: float
    slowdown: float  # trace ms / in-core trace ms (same path and effect)


def configs(fractions: list[float]) -> list[tuple[str, str]]:
    """In core, then each budget; the in-core run cuts its fronts as the out-of-core runs do
    (ChcrtParams.subtree_tri_bound: out of core it bounds the subtrees, in core by default not), so
    that the slowdown is the cache's alone."""
    from viewer.backends.chcrt.chcrt_params import OOC_SUBTREE_TRIS

    return ([("in-core", f"max_subtree_tris={OOC_SUBTREE_TRIS}")]
            + [(f"{round(100 * f)}% in core", f"gpu_budget_fraction={f:g}") for f in fractions])


def study_ooc(b) -> dict:
    """Paper Tables 1 and 3 analogs (module docstring). `b` is bench.chcrt.Bench."""
    from viewer.backends.chcrt import ChcrtParams
    from viewer.backends.chcrt.chcrt_cache import NODE_BYTES, TRI_BYTES, CachePlan
    from viewer.backends.chcrt.chcrt_params import OOC_SUBTREE_TRIS
    from viewer.backends.interface import parse_params

    o = b.o
    size = o.sizes[0]
    recs = [scaled_recording(p, o.ooc_scene_size, o.out / "recordings") for p in o.ooc_recordings]
    cfgs = configs(o.ooc_fractions)
    reset_ok = reset_peak_rss()
    rss0 = peak_rss_gib()
    b.progress("ooc", len(recs) * len(o.ooc_effects) * len(cfgs) * o.ooc_frames)
    try:
        prep = b.scene(recs[0])  # all paths share the scene: load + build once
        build_peak = peak_rss_gib()
        reset_peak_rss()
        p = parse_params(ChcrtParams, join_params(os.environ.get("RTWALK_CHCRT", ""), o.chcrt), "--chcrt")
        scene_bytes = CachePlan.scene_bytes_of(prep.bvh)
        t1 = []
        for label, params in cfgs:
            frac = float(params.split("=")[1]) if params.startswith("gpu_budget_fraction=") else 1.0
            tris = p.max_subtree_tris or OOC_SUBTREE_TRIS  # (the subtrees an out-of-core run schedules)
            plan = CachePlan.of(prep.bvh, int(frac * scene_bytes), tris, p.max_subtree_height)
            t1.append(Table1Row(label, plan.triangles, plan.scene_bytes / MB, plan.scene_bvh_bytes / MB,
                                plan.scene_geom_bytes / MB, plan.budget_bytes / MB, 100 * plan.in_core_fraction,
                                plan.resident_bytes / MB, plan.top_nodes, plan.node_cap * NODE_BYTES / MB,
                                plan.tri_cap * TRI_BYTES / MB))
        rows: list[Table3Row] = []
        runs = []
        for path in recs:
            for effect in o.ooc_effects:
                specs = [RunSpec(label, effect, "chcrt", join_params(params, "overdraw_overlay=0", o.chcrt))
                         for label, params in cfgs]
                results = b.run_many(path, size, specs, b.frames_for(path, o.ooc_frames))
                base = results[0].best.trace_ms
                for spec, run in zip(specs, results, strict=True):
                    s, c = run.best, run.best.counters
                    rows.append(Table3Row(path.stem, effect, spec.label, s.trace_ms, s.wall_ms, s.mrays_per_s,
                                          c.get("queries", 0.0), c.get("upload_bvh_mb", 0.0),
                                          c.get("upload_geom_mb", 0.0), c.get("subtrees_uploaded", 0.0),
                                          c.get("cache_hits", 0.0), c.get("upload_syncs", 0.0),
                                          ratio(s.trace_ms, base)))
                    runs.append(asdict(run))
        render_peak = peak_rss_gib()
    finally:
        b.done()
    memory = {"rss_before_gib": rss0, "build_peak_gib": build_peak, "render_peak_gib": render_peak,
              "peak_reset": reset_ok}
    report = b.header("ooc", o, {"recordings": [r.stem for r in recs], "size": list(size),
                                 "scene_size": o.ooc_scene_size, "fractions": o.ooc_fractions,
                                 "effects": o.ooc_effects})
    report.update(table1=[asdict(r) for r in t1], table3=[asdict(r) for r in rows], memory=memory, runs=runs)
    md = [f"## Table 1 analog: {prep.scene.name}, {t1[0].triangles:,} triangles (out-of-core budgets)", "",
          f"Device: {b.device_text}. BVH = GPU inner nodes (64 B), geometry = GPU triangles (48 B). The BVH top "
          "(nodes above every schedulable subtree) stays resident; the rest of the budget is the round-robin "
          "subtree cache (nodes : triangles in the scene's ratio).", ""]
    md.append(md_table(["config", "triangles", "total MB", "BVH MB", "geometry MB", "budget MB", "% in core",
                        "resident top MB", "cache BVH MB", "cache geometry MB"],
                       [[r.config, f"{r.triangles:,}", fmt(r.total_mb), fmt(r.bvh_mb), fmt(r.geometry_mb),
                         fmt(r.budget_mb), fmt(r.in_core_pct), fmt(r.resident_top_mb, 2), fmt(r.cache_bvh_mb),
                         fmt(r.cache_geometry_mb)] for r in t1]))
    md += ["", f"Peak memory (VmHWM): loading + building the scene {fmt(build_peak, 2)} GiB; rendering all rows "
               f"{fmt(render_peak, 2)} GiB" + ("" if reset_ok else " (peak could not be reset: includes the build)")
               + f" ({len(cfgs)} renderers alive per row).", ""]
    md += [f"## Table 3 analog: out-of-core chcrt ({size_text(size)}, steady state of {o.ooc_frames} consecutive "
           "frames)",
           "", "Per frame; 'slowdown' = trace ms / in-core trace ms of the same path and effect. 'syncs' = uploads "
           "that had to wait for queued draws reading the slots they overwrite.", ""]
    md.append(md_table(["path", "effect", "config", "trace ms", "Mrays/s", "queries", "BVH MB", "geometry MB",
                        "uploaded", "cache hits", "syncs", "slowdown"],
                       [[r.recording, r.effect, r.config, fmt(r.trace_ms), fmt(r.mrays_per_s, 2), fmt(r.queries, 0),
                         fmt(r.upload_bvh_mb, 2), fmt(r.upload_geom_mb, 2), fmt(r.subtrees_uploaded, 0),
                         fmt(r.cache_hits, 0), fmt(r.upload_syncs, 0), fmt(r.slowdown, 2)] for r in rows]))
    md += notes_md(report["notes"])
    _plot(runs, cfgs, o.out / "ooc.png", b.device["renderer"], chc_phases())
    return finish_study(o, "ooc", report, "\n".join(md))


def _plot(runs: list[dict], cfgs: list[tuple[str, str]], path: Path, device: str, own: tuple[str, ...]) -> None:
    """Per path (and the last effect): MB transferred per frame for each budget (solid: total,
    dashed: BVH part), and the chc phase bars of the smallest budget."""
    keys = list(dict.fromkeys((r["recording"], r["effect"]) for r in runs))
    last_effect = keys[-1][1]
    paths = [k for k in keys if k[1] == last_effect]
    fig, axes = figure(2, len(paths), size=(6 * len(paths), 7), squeeze=False, sharex="col")
    for j, (rec, effect) in enumerate(paths):
        ax, ax2 = axes[0][j], axes[1][j]
        for label, _ in cfgs[1:]:
            run = next(r for r in runs if r["recording"] == rec and r["effect"] == effect and r["label"] == label)
            x = [f["frame"] for f in run["frames"]]
            bvh = [f["backend_stats"].get("upload_bvh_mb", 0.0) for f in run["frames"]]
            geo = [f["backend_stats"].get("upload_geom_mb", 0.0) for f in run["frames"]]
            line = ax.plot(x, [a + g for a, g in zip(bvh, geo, strict=True)], "o-", ms=3, label=f"{label}: total")[0]
            ax.plot(x, bvh, "--", color=line.get_color(), label=f"{label}: BVH")
        ax.set_ylabel("MB transferred per frame")
        ax.set_title(f"{rec} {effect}: transfers (first frame cold)", fontsize=8)
        ax.legend(fontsize=6)
        ax.grid(alpha=0.3)
        run = next(r for r in runs if r["recording"] == rec and r["effect"] == effect and r["label"] == cfgs[-1][0])
        x = [f["frame"] for f in run["frames"]]
        phases = sorted({p for f in run["frames"] for p in f["gpu_ms"] if p.startswith("chc:")})
        layers = {p.removeprefix("chc:"): [f["gpu_ms"].get(p, 0.0) for f in run["frames"]] for p in phases}
        layers["other phases"] = [sum(v for p, v in f["gpu_ms"].items() if not is_trace_phase(p, own))
                                  for f in run["frames"]]
        stacked(ax2, x, layers, ylabel="GPU ms", xlabel="frame", colors={"other phases": "0.75"},
                title=f"phases, {cfgs[-1][0]}")
        ax2.legend(fontsize=6)
    finish(fig, path, f"CHC+RT out-of-core - {device}")

"""Trace-speed study: Mrays/s of backends and of raw Embree on the very same rays.

Rays are captured once per frame (Renderer.render(capture=True) with the glsl backend: every
ray type of the frame, one RayArrays per pass), then, in interleaved rounds, each backend traces
each captured pass again from the ray textures and Embree (EmbreeTracer.time_raw: embreex's bare
`run()` on the rays as EmbreeTracer gives them to it) traces the same active rays on 1 thread and
on N Python threads over equal slices (embreex releases the GIL in run(): checked by a Python loop
that keeps running beside it). A backend's time is the sum of its profiler phases named
trace:<ray type> (for clbvh the kernel; its mapped ray/hit transfers are reported apart as
"with transfer"); Embree's is the wall time of run(). Medians over rounds; ratios are taken
per round (interleaved), then the median. Hit/miss agreement of each backend with the Embree
reference (viewer.reference.EmbreeTracer) is reported once per pass.

Output in --out: bench_trace.json (every pass and round), bench_trace.md (a table per scene
and size) and bench_trace.png (Mrays/s per ray type, log scale).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viewer.bench.common import log
from viewer.bench.harness import is_trace_phase
from viewer.bench.partial import write_plots
from viewer.bench.plots import bars, figure, finish
from viewer.bench.report import md_table, write_study
from viewer.cli_args import check_output_dir, check_report_free, parse_image_sizes
from viewer.errors import RtwalkError
from viewer.paths import resolve_recording

DEFAULT_RECORDINGS = "city-near.json,sponza-walk.json,conference-walk.json"
DEFAULT_EFFECTS = "primary,shadows,soft,ao,diffuse,reflections"


HELP = "Mrays/s per ray type of backends and raw Embree on the same captured rays"


def add_arguments(p) -> None:
    p.add_argument("--recordings", default=DEFAULT_RECORDINGS,
                   help=f"comma-separated recordings (names in recordings/ or paths; default {DEFAULT_RECORDINGS})")
    p.add_argument("--sizes", default="640x360,1280x720", help="comma-separated WxH (default 640x360,1280x720)")
    p.add_argument("--frames", type=int, default=1,
                   help="frames per recording, evenly spaced inside it (default 1: the middle frame)")
    p.add_argument("--backends", default="", help="comma-separated registered backends (default: every registered "
                                                  "exact backend but the reference)")
    p.add_argument("--effects", default=DEFAULT_EFFECTS, help=f"ray types to capture (default {DEFAULT_EFFECTS})")
    p.add_argument("--embree-threads", default="1,2", help="Embree raw thread counts (default 1,2; empty: none)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds (default 3)")
    p.add_argument("--no-check", action="store_true", help="skip the hit/miss agreement with the Embree reference")
    p.add_argument("--out", default="out/bench-trace", help="output folder (default out/bench-trace)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


@dataclass
class Pass:
    """One captured pass: rays as RGBA32F texel data, the active rays as Embree is given them."""

    label: str
    any_hit: bool
    ray_type: object  # viewer.effects.RayType
    sample: int
    light: int
    origin4: np.ndarray  # float32 (H, W, 4) origin + tmin
    dir4: np.ndarray  # float32 (H, W, 4) direction + tmax
    active: np.ndarray  # bool (H*W,)
    embree: object  # viewer.reference.RawRays of the active rays, or None without Embree timings

    @property
    def rays(self) -> int:
        return int(self.active.sum())


def capture_passes(renderer, camera, tracer=None) -> list[Pass]:
    """Render one frame with capture and keep every pass that has active rays (with `tracer`, an
    EmbreeTracer, also as the raw rays Embree is timed on)."""
    rep = renderer.render(camera, capture=True)
    w, h = renderer.size
    out = []
    for cp in rep.captured:
        r = cp.rays
        active = r.active & np.isfinite(r.origins).all(1) & np.isfinite(r.directions).all(1)
        if not active.any():
            continue
        o4 = np.concatenate([r.origins, r.tmin[:, None]], 1).astype(np.float32).reshape(h, w, 4)
        d4 = np.concatenate([r.directions, r.tmax[:, None]], 1).astype(np.float32).reshape(h, w, 4)
        raw = None if tracer is None else tracer.raw_rays(r.origins[active], r.directions[active], r.tmin[active],
                                                          r.tmax[active])
        out.append(Pass(cp.ray_type.label, cp.ray_type.any_hit, cp.ray_type, cp.sample, cp.light, o4, d4, active,
                        raw))
    return out


def time_backend(renderer, name: str, passes: list[Pass]) -> tuple[list[float], list[float], list[float], list]:
    """Per pass: ms in tracing phases (trace:* and the backend's declared phases), ms in all phases of
    the call, process CPU ms of the call (all threads: llvmpipe's, PoCL's), and (t, tri) read back."""
    from viewer.rays import PassInfo

    renderer.set_backend(name)
    be = renderer.backend
    prof = renderer.profiler
    trace_ms, total_ms, cpu_ms, hits = [], [], [], []
    for p in passes:
        renderer.rays.origin.write(p.origin4.tobytes())
        renderer.rays.direction.write(p.dir4.tobytes())
        renderer.ctx.finish()
        prof.begin_frame()
        prof.label = p.label
        c0 = time.process_time()
        be.trace(renderer.rays, PassInfo(p.ray_type, p.sample, p.light), renderer.hits)
        renderer.ctx.finish()
        cpu_ms.append((time.process_time() - c0) * 1e3)
        end = getattr(be, "end_frame", None)  # counters kept on the device (read after the finish: no wait)
        if callable(end):
            end()
        prof.label = None
        phases = prof.end_frame()
        trace_ms.append(sum(v for k, v in phases.items() if is_trace_phase(k, be.info.phases)))
        total_ms.append(sum(phases.values()))
        hits.append(renderer.hits.read())
    return trace_ms, total_ms, cpu_ms, hits


def _by_label(values: list[float], passes: list[Pass], label: str) -> float:
    """Sum of per-pass values over the passes of one ray type."""
    return float(sum(v for v, p in zip(values, passes, strict=True) if p.label == label))


def _median(xs) -> float:
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(statistics.median(xs)) if xs else float("nan")


def study_frame(renderer, tracer, reference, passes: list[Pass], backends: list[str], threads: list[int],
                rounds: int, check: bool) -> list[dict]:
    """Interleaved rounds over backends and Embree thread counts; one row per ray type."""
    from viewer.reference import compare_hits

    labels = list(dict.fromkeys(p.label for p in passes))
    configs = [("backend", b) for b in backends] + [("embree", t) for t in threads]
    # per round, per config, per label: ms
    ms = {c: {lb: [] for lb in labels} for c in configs}
    ms_total = {b: {lb: [] for lb in labels} for b in backends}
    ms_cpu = {c: {lb: [] for lb in labels} for c in configs}
    agree: dict[str, dict[str, list[float]]] = {b: {lb: [] for lb in labels} for b in backends}
    for r in range(rounds):
        order = configs[r % len(configs):] + configs[: r % len(configs)]  # rotate: interleave
        for kind, what in order:
            if kind == "backend":
                tr, tot, cpu, hits = time_backend(renderer, what, passes)
                for lb in labels:
                    ms_cpu[(kind, what)][lb].append(_by_label(cpu, passes, lb))
                    ms[(kind, what)][lb].append(_by_label(tr, passes, lb))
                    ms_total[what][lb].append(_by_label(tot, passes, lb))
                if check and r == 0:
                    for p, (t, tri), ref in zip(passes, hits, reference, strict=True):
                        a = p.active
                        st = compare_hits(t[a], tri[a], ref[0], ref[1])
                        agree[what][p.label].append(st["hitmiss_agree"])
            else:
                per = [tracer.time_raw(p.embree, p.any_hit, what) for p in passes]
                for lb in labels:
                    ms[(kind, what)][lb].append(_by_label([t[0] for t in per], passes, lb))
                    ms_cpu[(kind, what)][lb].append(_by_label([t[1] for t in per], passes, lb))
    rows = []
    for lb in labels:
        n = sum(p.rays for p in passes if p.label == lb)
        row: dict = {"ray_type": lb, "rays": n, "passes": sum(p.label == lb for p in passes),
                     "any_hit": next(p.any_hit for p in passes if p.label == lb), "ms": {}, "mrays_s": {},
                     "ms_rounds": {}, "cpu_ms": {}, "mrays_per_cpu_s": {}}
        for kind, what in configs:
            key = what if kind == "backend" else f"embree_{what}t"
            vals = ms[(kind, what)][lb]
            row["ms_rounds"][key] = vals
            row["ms"][key] = _median(vals)
            row["mrays_s"][key] = n / 1e3 / row["ms"][key] if row["ms"][key] > 0 else float("nan")
            cpu = _median(ms_cpu[(kind, what)][lb])
            row["cpu_ms"][key] = cpu
            row["mrays_per_cpu_s"][key] = n / 1e3 / cpu if cpu > 0 else float("nan")
        for b in backends:
            tot = ms_total[b][lb]
            if any(t > 0 for t in tot) and tot != ms[("backend", b)][lb]:
                row["ms"][f"{b}+transfer"] = _median(tot)
                row["mrays_s"][f"{b}+transfer"] = n / 1e3 / row["ms"][f"{b}+transfer"]
            if agree[b][lb]:
                row.setdefault("hitmiss_agree", {})[b] = float(min(agree[b][lb]))
        # interleaved ratios: per round, then the median
        ratios = {}
        keys = list(row["ms_rounds"])
        for a in keys:
            for b in keys:
                if a != b:
                    rr = [y / x for x, y in zip(row["ms_rounds"][a], row["ms_rounds"][b], strict=True) if x > 0]
                    ratios[f"{a}/{b}"] = _median(rr)  # speed of a over b (time b / time a)
        row["speedup"] = ratios
        rows.append(row)
    return rows


def _markdown(report: dict) -> str:
    lines = [f"# Trace speed on the same rays ({report['device_cl']})", "",
             f"Command: `{report['command']}`", "",
             "Mrays/s = active rays / median time over interleaved rounds; a backend's time is its tracing phases "
             "(trace:* and those it declares; '+transfer' adds a staged backend's ray/hit copies), "
             "Embree's the wall time of embreex run() on N Python threads. Ratios are per-round, then the median.", ""]
    backends = report["backends"]
    emb = [f"embree_{t}t" for t in report["embree_threads"]]
    nan = float("nan")
    for group in report["groups"]:
        lines += [f"## {group['recording']} frame {group['frame']} at {group['size'][0]}x{group['size'][1]}"
                  f" ({group['triangles']:,} triangles)", ""]
        transfer = [f"{b}+transfer" for b in backends
                    if any(f"{b}+transfer" in row["ms"] for row in group["rows"])]
        cols = [*backends, *transfer, *emb]
        # every other backend against the first one named (the baseline), every backend against Embree
        base = backends[0] if backends else None
        ratio_cols = [(f"{b}/{base}", f"{b} vs {base}") for b in backends[1:]]
        ratio_cols += [(f"{b}/{e}", f"{b} vs {e.replace('_', ' ')}") for b in backends for e in emb]
        head = ["ray type", "rays", *[f"{c} Mrays/s" for c in cols], *[r[1] for r in ratio_cols], "hit/miss vs Embree"]
        rows = [[row["ray_type"], f"{row['rays']:,}",
                 *[f"{row['mrays_s'].get(c, nan):.3g}" for c in cols],
                 *[f"{row['speedup'].get(k, nan):.2f}x" for k, _ in ratio_cols],
                 ", ".join(f"{b} {v:.5f}" for b, v in row.get("hitmiss_agree", {}).items())] for row in group["rows"]]
        lines.append(md_table(head, rows))
        keys = [*backends, *emb]
        lines += ["", "Mrays per CPU-second (process CPU time of all threads: llvmpipe's, PoCL's, Embree's; "
                  "less sensitive to other load on the machine, but blind to idle cores):", ""]
        lines.append(md_table(["ray type", *keys], [[row["ray_type"], *[
            f"{row['mrays_per_cpu_s'].get(k, nan):.3g}" for k in keys]] for row in group["rows"]]))
        lines.append("")
    return "\n".join(lines)


def _plot(report: dict, path: Path) -> None:
    groups = report["groups"]
    fig, axes = figure(len(groups), 1, size=(10, 3.2 * len(groups)), dpi=100, squeeze=False)
    keys = [*report["backends"], *[f"embree_{t}t" for t in report["embree_threads"]]]
    for ax, g in zip(axes[:, 0], groups, strict=True):
        series = {k: [r["mrays_s"].get(k, np.nan) for r in g["rows"]] for k in keys}
        bars(ax, [r["ray_type"] for r in g["rows"]], series, ylabel="Mrays/s", log=True, legend_cols=len(keys),
             title=f"{g['recording']} frame {g['frame']} {g['size'][0]}x{g['size'][1]}")
    finish(fig, path)


def run(args) -> int:
    from viewer.backends import backend_info, backend_names
    from viewer.effects import parse_effects
    from viewer.gl.context import shared_context
    from viewer.gl.limits import check_target_size
    from viewer.reference import REFERENCE_BACKEND, EmbreeTracer

    sizes = parse_image_sizes(args.sizes)
    backends = [b.strip() for b in args.backends.split(",") if b.strip()] or [
        b for b in backend_names() if b != REFERENCE_BACKEND and backend_info(b).exact]
    for b in backends:
        if b not in backend_names():
            raise RtwalkError(f"--backends: unknown backend '{b}' (choose from {', '.join(backend_names())})")
    try:
        threads = [int(t) for t in args.embree_threads.split(",") if t.strip()]
    except ValueError:
        raise RtwalkError(f"--embree-threads: expected integers like 1,2 (got '{args.embree_threads}')") from None
    if any(t < 1 for t in threads):
        raise RtwalkError("--embree-threads: thread counts must be >= 1")
    if args.frames < 1 or args.rounds < 1:
        raise RtwalkError("--frames and --rounds must be >= 1")
    if threads and not EmbreeTracer.available():
        raise RtwalkError("Embree timings need the embreex package (pip install embreex)")
    recs = [resolve_recording(n) for n in args.recordings.split(",") if n.strip()]
    settings = parse_effects(args.effects)
    out = check_output_dir(args.out, "--out")
    check_report_free([out / "bench_trace.json"], getattr(args, "force", False))
    ctx = shared_context()
    for size in sizes:  # before any scene (each was refused only after its recording's scene loaded)
        check_target_size(ctx, size)
    device_cl = ""
    if any(backend_info(b).device == "cl" for b in backends):
        from viewer.cl import cl_context

        device_cl = cl_context().name
    report = {"command": getattr(args, "command_line", ""),
              "backends": backends, "embree_threads": threads, "rounds": args.rounds, "effects": args.effects,
              "device_cl": device_cl or "no OpenCL backend", "complete": False, "groups": []}
    try:
        _measure(args, ctx, recs, sizes, backends, threads, settings, report)
    except KeyboardInterrupt:  # Ctrl-C: the groups measured so far are kept, marked incomplete
        if not report["groups"]:
            raise
        files = write_study(out, "bench_trace", report, _markdown(report))
        write_plots(lambda: _plot(report, files["png"]))  # a plot failing on partial data: a note, never a traceback
        raise KeyboardInterrupt(f"interrupted after {len(report['groups'])} groups (recording, frame, size): "
                                f"partial report {files['json']} (\"complete\": false)") from None
    report["complete"] = True
    files = write_study(out, "bench_trace", report, _markdown(report))
    if report["groups"]:
        write_plots(lambda: _plot(report, files["png"]))  # a plot failing on partial data: a note, never a traceback
    print(files["markdown"])
    return 0


def _measure(args, ctx, recs, sizes, backends, threads, settings, report: dict) -> None:
    """Every (recording, frame, size) group, appended to report["groups"] as it is finished."""
    from viewer.backends import DEFAULT_BACKEND
    from viewer.recording import load_recording, resolve_scene_spec
    from viewer.reference import EmbreeTracer
    from viewer.renderer import Renderer
    from viewer.session import prepare_scene

    for rec_path in recs:
        rec = load_recording(rec_path)
        rs = resolve_scene_spec(rec, rec_path)
        log(args, f"bench-trace: loading {rec_path.name}")
        prep = prepare_scene(rs.spec, scene_size=rs.size, seed=rs.seed if rs.seed is not None else 1, quiet=True)
        reference = None
        tracer = EmbreeTracer(prep.scene.triangles) if threads or not args.no_check else None
        count = rec.frame_count()
        frames = sorted({int(count * (k + 1) / (args.frames + 1)) for k in range(args.frames)})
        for size in sizes:
            renderer = Renderer(ctx, prep.scene, prep.bvh, size, backends[0] if backends else DEFAULT_BACKEND,
                                settings)
            try:
                for fr in frames:
                    passes = capture_passes(renderer, rec.camera_for_frame(fr), tracer if threads else None)
                    if not args.no_check:
                        reference = [_reference(tracer, p) for p in passes]
                    # warm up outside the timing: kernel builds and first-use costs of both query kinds
                    warm = list({p.any_hit: p for p in passes}.values())
                    for b in backends:
                        time_backend(renderer, b, warm)
                    log(args, f"bench-trace: {rec_path.stem} frame {fr} {size[0]}x{size[1]}: "
                               f"{sum(p.rays for p in passes):,} rays in {len(passes)} passes")
                    rows = study_frame(renderer, tracer, reference, passes, backends, threads, args.rounds,
                                       not args.no_check)
                    report["groups"].append({"recording": rec_path.stem, "frame": fr, "size": list(size),
                                             "triangles": prep.scene.triangle_count, "rows": rows})
                    for row in rows:
                        log(args, f"  {row['ray_type']:12s} " + "  ".join(
                            f"{k} {v:.3g}" for k, v in row["mrays_s"].items()) + " Mrays/s")
            finally:
                renderer.release()
        del tracer


def _reference(tracer, p: Pass) -> tuple[np.ndarray, np.ndarray]:
    """Embree reference hits for the pass's active rays (full convention of viewer.reference)."""
    o4 = p.origin4.reshape(-1, 4)[p.active]
    d4 = p.dir4.reshape(-1, 4)[p.active]
    return tracer.trace(o4[:, :3], d4[:, :3], o4[:, 3], d4[:, 3], any_hit=p.any_hit)

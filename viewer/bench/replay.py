"""`rtwalk bench`: deterministic replay of a recording: time per phase, rays per type, Mrays/s and
error vs Embree.

Frames are sampled from the recording at a fixed rate (never the wall clock). Timing frames are
rendered without readbacks; frames checked against the reference are rendered a second time with
capture on (same rays: the pipeline is deterministic), so error checks never pollute timings.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from viewer.backends import backend_names
from viewer.backends.interface import params_text
from viewer.bench.harness import frame_numbers, frame_row, image_error
from viewer.bench.plots import figure, finish, stacked
from viewer.bench.report import write_json
from viewer.effects import EffectSettings
from viewer.errors import RtwalkError
from viewer.gl.limits import host_time_label
from viewer.interrupt import deferred_interrupt
from viewer.reference import REFERENCE_BACKEND
from viewer.renderer import Renderer
from viewer.session import PreparedScene


@dataclass
class BenchOptions:
    backend: str = field(default_factory=lambda: backend_names()[0])
    size: tuple[int, int] = (640, 360)
    fps: float | None = None  # None: the recording's rate
    max_frames: int | None = None
    reference: str = REFERENCE_BACKEND  # or "none"
    reference_every: int = 1
    warmup: int = 1
    frames_dir: Path | None = None  # write PNG frames here (every `frame_every` frames)
    frame_every: int = 10
    backend_options: dict[str, str] | None = None  # per backend: parameter text (--backend-params)
    first_frame: int | None = None  # consecutive frames from here (None: spread over the path)
    denoise: bool = False  # saved frames denoised (viewer.denoise); every error is measured on the raw image


def reference_errors(renderer: Renderer, camera, tracer) -> dict:
    """Per ray type: agreement of the backend's hits with Embree on exactly the same rays."""
    from viewer.reference import compare_hits

    rep = renderer.render(camera, capture=True)
    image = renderer.read_image()
    by_type: dict[str, list[dict]] = {}
    coord_scale = np.float32(np.abs(renderer.scene.triangles).max())
    for cp in rep.captured:
        act = cp.rays.active
        if not act.any():
            continue
        r = cp.rays
        t_ref, id_ref = tracer.trace(r.origins[act], r.directions[act], r.tmin[act], r.tmax[act],
                                     any_hit=cp.ray_type.any_hit)
        # distance tolerance: 1e-5 relative plus 4 float32 ulps of the coordinates (a float32
        # origin-to-vertex difference is only that exact; it dominates for hits near the origin)
        abs_tol = 4 * (np.spacing(coord_scale) + np.spacing(np.abs(r.origins[act]).max(1)))
        st = compare_hits(cp.t[act], cp.tri[act], t_ref, id_ref, renderer.scene.triangles, abs_tol=abs_tol)
        any_hit = cp.ray_type.any_hit  # only occluded-or-not is defined for any-hit rays
        by_type.setdefault(cp.ray_type.label, []).append({
            "rays": st["n_rays"], "hit_agreement": st["hitmiss_agree"],
            "id_agreement": st["hitmiss_agree"] if any_hit else st["id_agree"],
            "max_rel_t_error": 0.0 if any_hit else st["max_rel_err"],
            "p999_rel_t_error": 0.0 if any_hit else st["p999_rel_err"],
            "t_beyond_tolerance": 0 if any_hit else st["n_t_exceed"]})
    out = {}
    for ray, items in by_type.items():
        n = sum(i["rays"] for i in items)
        out[ray] = {
            "rays": n,
            "hit_agreement": sum(i["hit_agreement"] * i["rays"] for i in items) / n,
            "id_agreement": sum(i["id_agreement"] * i["rays"] for i in items) / n,
            "max_rel_t_error": max(i["max_rel_t_error"] for i in items),
            "p999_rel_t_error": max(i["p999_rel_t_error"] for i in items),
            "t_beyond_tolerance": sum(i["t_beyond_tolerance"] for i in items),
        }
    return {"rays": out, "image": image}


def save_overlay_views(renderer: Renderer, camera, folder: Path, frame: int) -> list[str]:
    """The backend's overlay views (its info.overlays) of this frame as PNGs, rendered again after
    the timed frame so diagnostics never cost timed work. Returns the file names (none for a
    backend without overlays)."""
    from PIL import Image

    from viewer.passes.overlay import overlay_view_names

    saved, view = [], renderer.view
    try:
        for name in overlay_view_names(renderer.backend.info):
            renderer.view = name
            renderer.render(camera)
            path = folder / f"{name}_{frame:05d}.png"
            Image.fromarray(renderer.read_image()).save(path)
            saved.append(path.name)
    finally:
        renderer.view = view
    return saved


def duration_text(seconds: float) -> str:
    """"45 s" under a minute and a half, else "2.5 min" (a short replay said "0.0 min more")."""
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def run_bench(prepared: PreparedScene, rec, settings: EffectSettings, opts: BenchOptions,
              ctx, quiet: bool = False) -> dict:
    renderer = Renderer(ctx, prepared.scene, prepared.bvh, opts.size, opts.backend, settings, opts.backend_options)
    tracer = None
    if opts.reference != "none":
        from viewer.reference import EmbreeTracer

        if EmbreeTracer.available():
            tracer = EmbreeTracer(prepared.scene.triangles)
            tracer_version = prepared.scene.geometry_version
        else:
            print("rtwalk: embreex is not installed: no error column (pip install embreex)", file=sys.stderr)
    frames = frame_numbers(rec, opts.fps, opts.max_frames, opts.first_frame)
    fps = opts.fps or rec.fps
    for _ in range(opts.warmup):  # compile shaders, fault in buffers
        renderer.set_scene_time(rec.scene_time_for_frame(frames[0], opts.fps))
        renderer.render(rec.camera_for_frame(frames[0], opts.fps))
    records = []
    every = max(opts.reference_every, 1)
    checked = len(range(0, len(frames), every)) if tracer is not None else 0
    if not quiet:
        print(f"bench: {len(frames)} of the path's {rec.frame_count(opts.fps)} frames"
              + (f", {checked} checked against Embree (every {every})" if checked else ""), file=sys.stderr)
    t_start, t_render0 = time.perf_counter(), 0.0
    complete = True
    with deferred_interrupt() as ctrl_c:  # Ctrl-C: stop after the frame in hand (viewer.interrupt)
        try:
            for k, n in enumerate(tqdm(frames, desc=f"bench {opts.backend}", unit="frame", disable=quiet,
                                       file=sys.stderr)):
                if ctrl_c.requested:  # Ctrl-C arrived during the last frame: keep the frames done
                    complete = False
                    break
                if k == 1 and not quiet:  # the first frame (rendered and checked) times the rest
                    first = time.perf_counter() - t_start
                    # a checked frame costs `first`, an unchecked one its render part
                    est = (first * (checked - 1) + t_render0 * (len(frames) - checked) if checked
                           else first * (len(frames) - 1))
                    tqdm.write(f"bench: estimated {duration_text(est)} more (first frame {first:.1f} s)",
                               file=sys.stderr)
                t_frame = time.perf_counter()
                cam = rec.camera_for_frame(n, opts.fps)
                renderer.set_scene_time(rec.scene_time_for_frame(n, opts.fps))
                rep = renderer.render(cam)
                row = frame_row(rep, rec, n, opts.fps)
                if k == 0:
                    t_render0 = time.perf_counter() - t_frame
                image = None
                if tracer is not None and k % max(opts.reference_every, 1) == 0:
                    if tracer_version != renderer.scene.geometry_version:  # an animated scene moved: judge this frame's
                        tracer = EmbreeTracer(renderer.scene.triangles)
                        tracer_version = renderer.scene.geometry_version
                    err = reference_errors(renderer, cam, tracer)
                    image = err["image"]
                    row["error"] = err["rays"]
                    renderer.set_backend(opts.reference)  # the reference image: the backend of that name
                    renderer.render(cam)
                    ref_image = renderer.read_image()
                    renderer.set_backend(opts.backend)
                    row["image_error"] = image_error(image, ref_image)
                if opts.frames_dir is not None and k % max(opts.frame_every, 1) == 0:
                    from PIL import Image

                    if image is None:
                        image = renderer.read_image()
                    if opts.denoise:  # the picture only: the errors above were taken on the raw image
                        image = renderer.read_denoised("library", cam, image)
                    opts.frames_dir.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(image).save(opts.frames_dir / f"frame_{n:05d}.png")
                    row["overlays"] = save_overlay_views(renderer, cam, opts.frames_dir, n)
                records.append(row)
        except KeyboardInterrupt:  # a second Ctrl-C: keep the frames done; the caller writes them marked incomplete
            complete = False
    if ctrl_c.requested:  # after the last frame
        complete = False
    report = {
        "format": "rtwalk-bench", "version": 1,
        "scene": prepared.scene.identity, "scene_name": prepared.scene.name,
        "triangles": prepared.scene.triangle_count, "bvh": prepared.bvh.stats.to_dict(),
        "backend": opts.backend, "backend_options": opts.backend_options or {},
        "backend_params": params_text(renderer.backend.params),
        "effects": settings.to_dict(), "size": list(opts.size),
        "recording": str(rec.source) if getattr(rec, "source", None) else None, "fps": fps,
        "device": {"renderer": ctx.info.get("GL_RENDERER"), "version": ctx.info.get("GL_VERSION"),
                   "phase_timing": renderer.profiler.method},
        "frames": records, "summary": summarize(records),
        "complete": complete,  # False: interrupted; `frames` holds the frames finished before that
    }
    renderer.release()
    return report


def _mean(values) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def _median(values) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(vals)) if vals else float("nan")


def summarize(records: list[dict]) -> dict:
    phases = sorted({p for r in records for p in r["gpu_ms"]})
    rays = sorted({p for r in records for p in r["rays"]})
    s = {"frames": len(records),
         "gpu_ms_mean": {p: _mean(r["gpu_ms"].get(p, 0.0) for r in records) for p in phases},
         "frame_gpu_ms_mean": _mean(sum(r["gpu_ms"].values()) for r in records),
         "wall_ms_mean": _mean(r["wall_ms"] for r in records),
         "rays_mean": {p: _mean(r["rays"].get(p, 0) for r in records) for p in rays},
         "mrays_per_s_mean": {p: _mean(r["mrays_per_s"].get(p) for r in records) for p in rays + ["all"]}}
    steady = [r["io"] for r in records[1:] if "io" in r] or [r["io"] for r in records if "io" in r]
    if steady:  # steady frames: the first one also uploads, builds and compiles
        s["io_mean"] = {k: _mean(io[k] for io in steady) for k in steady[0]}
    # steady times: medians over the frames after the first, which may still build a backend's
    # temporal state (the warm-up frame before it builds most of it) and so is no steady frame
    later = [r for r in records[1:] if "trace_ms" in r]
    if later:
        s["steady_frames"] = len(later)
        s["steady_frame_gpu_ms_median"] = _median(sum(r["gpu_ms"].values()) for r in later)
        s["steady_trace_ms_median"] = _median(r["trace_ms"] for r in later)
        s["steady_gpu_ms_median"] = {p: _median(r["gpu_ms"].get(p, 0.0) for r in later) for p in phases}
        s["steady_trace_ms_by_ray_median"] = {p: _median(r.get("trace_ms_by_ray", {}).get(p) for r in later)
                                              for p in rays}
    checked = [r for r in records if "error" in r]
    if checked:
        s["error"] = {}
        for p in rays:
            errs = [r["error"][p] for r in checked if p in r["error"]]
            if errs:
                s["error"][p] = {"hit_agreement_min": min(e["hit_agreement"] for e in errs),
                                 "id_agreement_min": min(e["id_agreement"] for e in errs),
                                 "max_rel_t_error": max(e["max_rel_t_error"] for e in errs),
                                 "p999_rel_t_error": max(e["p999_rel_t_error"] for e in errs),
                                 "t_beyond_tolerance": sum(e["t_beyond_tolerance"] for e in errs)}
        s["image_mae_mean"] = _mean(r["image_error"]["mae"] for r in checked)
        s["image_psnr_min_db"] = min(r["image_error"]["psnr_db"] for r in checked)
    return s


def print_summary(report: dict, out=None) -> None:
    out = out or sys.stdout  # looked up per call: a stream bound at import may be closed by now
    s = report["summary"]
    w, h = report["size"]
    print(f"\n{report['scene_name']} ({report['triangles']:,} tris)  backend={report['backend']}  "
          f"{w}x{h}  {s['frames']} frames  device: {report['device']['renderer']}", file=out)
    print(f"  frame: GPU {s['frame_gpu_ms_mean']:.1f} ms   wall {s['wall_ms_mean']:.1f} ms", file=out)
    if "steady_frames" in s:
        by_ray = ", ".join(f"{p} {v:.1f}" for p, v in s["steady_trace_ms_by_ray_median"].items())
        print(f"  steady (median of the {s['steady_frames']} frames after the first): GPU "
              f"{s['steady_frame_gpu_ms_median']:.1f} ms, trace {s['steady_trace_ms_median']:.1f} ms"
              + (f" ({by_ray})" if by_ray else ""), file=out)
    # the mean over every frame carries the first frame's builds (chcrt's cold fronts: seconds), so
    # the steady frames' median stands beside it
    steady = s.get("steady_gpu_ms_median", {})
    print(f"  {'phase':<22}{'GPU ms':>10}" + (f"{'steady':>10}" if steady else ""), file=out)
    for p, v in s["gpu_ms_mean"].items():
        print(f"  {p:<22}{v:>10.2f}" + (f"{steady.get(p, 0.0):>10.2f}" if steady else ""), file=out)
    print(f"  {'ray type':<14}{'rays/frame':>12}{'Mrays/s':>10}{'hit agree':>11}{'id agree':>10}"
          f"{'p99.9 rel t':>13}{'t > tol':>9}", file=out)
    err = s.get("error", {})
    for p, n in s["rays_mean"].items():
        e = err.get(p, {})
        ha = f"{e['hit_agreement_min'] * 100:.3f}%" if e else "-"
        ia = f"{e['id_agreement_min'] * 100:.3f}%" if e else "-"
        te = f"{e['p999_rel_t_error']:.1e}" if e else "-"
        tx = f"{e['t_beyond_tolerance']}" if e else "-"
        print(f"  {p:<14}{n:>12.0f}{s['mrays_per_s_mean'][p]:>10.2f}{ha:>11}{ia:>10}{te:>13}{tx:>9}", file=out)
    io = s.get("io_mean")
    if io:
        px = max(w * h, 1)
        print(f"  I/O per steady frame: to device {io['bytes_to_device'] / 1e6:.2f} MB "
              f"({io['bytes_to_device'] / px:.1f} B/px), to host {io['bytes_to_host'] / 1e6:.2f} MB "
              f"({io['bytes_to_host'] / px:.1f} B/px), host syncs {io['host_syncs']:.0f}, CL launches "
              f"{io['cl_launches']:.0f}, GL draws {io['gl_draws']:.0f}, GL queries {io['gl_queries']:.0f}, "
              f"{host_time_label(report['device']['renderer'])} {io['python_ms']:.1f} ms", file=out)
    if "image_mae_mean" in s:
        print(f"  image vs Embree: mean abs error {s['image_mae_mean']:.3f}/255, min PSNR "
              f"{s['image_psnr_min_db']:.1f} dB", file=out)


def write_report(report: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path = out_dir / f"{stem}.json"
    write_json(json_path, report)
    png_path = out_dir / f"{stem}.png"
    plot_phases(report, png_path)
    return json_path, png_path


def plot_phases(report: dict, path: Path) -> None:
    """GPU time per phase over the replayed frames, stacked."""
    frames = [r["frame"] for r in report["frames"]]
    layers = {p: [r["gpu_ms"].get(p, 0.0) for r in report["frames"]] for p in report["summary"]["gpu_ms_mean"]}
    fig, ax = figure(size=(9, 4.5))
    w, h = report["size"]
    stacked(ax, frames, layers, ylabel="ms", xlabel="frame", area=True,
            title=f"{report['scene_name']} - {report['backend']} - {w}x{h}: GPU time per phase")
    finish(fig, path)


HELP = "replay a recording and report speed and error"
FRAMES = 48  # default: frames spread over the path, a few minutes on 2 cores
REFERENCE_EVERY = 6  # and an Embree check of every 6th of them


def add_arguments(b: argparse.ArgumentParser) -> None:
    from viewer.cli_args import add_denoise_arg, add_effect_args, add_progressive_args, add_scene_args

    add_scene_args(b)
    add_effect_args(b, "shadows,ao:4,reflections")
    b.add_argument("--recording", default=None, help="camera path (default: recordings/city-near.json for city)")
    b.add_argument("--fps", type=float, default=None, help="sample the path at this rate (default: recording's)")
    b.add_argument("--frames", type=int, default=FRAMES,
                   help=f"at most this many frames (>= 1, default {FRAMES}), spread over the path "
                        "(consecutive with --first-frame); a number >= the path's frame count replays all")
    b.add_argument("--first-frame", type=int, default=None,
                   help="replay consecutive frames from this one (temporal coherence as in a walkthrough)")
    b.add_argument("--reference", choices=[REFERENCE_BACKEND, "none"], default=REFERENCE_BACKEND,
                   help=f"check frames against {REFERENCE_BACKEND} (error columns), or none")
    b.add_argument("--reference-every", type=int, default=REFERENCE_EVERY,
                   help=f"check every Nth replayed frame against the reference (default {REFERENCE_EVERY}; "
                        "1 = all, slow)")
    b.add_argument("--save-frames", default=None, help="folder for PNG frames")
    b.add_argument("--frame-every", type=int, default=10,
                   help="with --save-frames: save every Nth replayed frame (and its overlay views)")
    b.add_argument("--out", default="out/bench", help="folder for the JSON report and plot")
    b.add_argument("--name", default=None, help="report file stem")
    add_denoise_arg(b, "off")  # only the saved frames (--save-frames); the errors are measured raw
    add_progressive_args(b, "replay in the window's progressive mode (one pass per effect while moving, "
                            "refine after the path stops) and report its frame times, time to convergence and "
                            "the converged image's error against the full-quality frame (no Embree check, "
                            "no saved frames)")


def run(args: argparse.Namespace) -> int:
    from viewer.cli_args import (
        DEFAULT_RECORDING,
        check_at_least,
        check_device,
        check_output_dir,
        check_positive,
        check_report_free,
        request_from,
        scene_from_args,
        warn_no_mirrors,
    )
    from viewer.gl.context import create_headless_context
    from viewer.gl.limits import check_target_size
    from viewer.recording import load_recording

    rec_path = args.recording or (DEFAULT_RECORDING if args.scene in (None, "city") else None)
    if rec_path is None:
        raise RtwalkError("bench needs --recording FILE for this scene (see recordings/)")
    # everything that needs no scene first: backend, parameters, numbers, output folders, devices
    req = request_from(args, device=False)
    backend_options, size, settings = req.backend_options, req.size, req.settings
    check_positive(args.fps, "--fps")
    check_positive(getattr(args, "frame_target_ms", None), "--frame-target-ms")
    check_at_least(args.frames, 1, "--frames")
    check_at_least(args.reference_every, 1, "--reference-every")
    check_at_least(args.frame_every, 1, "--frame-every")
    check_at_least(getattr(args, "first_frame", None), 0, "--first-frame")
    out_dir = check_output_dir(args.out, "--out")
    frames_dir = check_output_dir(args.save_frames, "--save-frames")
    if frames_dir is not None and getattr(args, "progressive", False):  # it was ignored without a word
        raise RtwalkError("--save-frames does not apply to --progressive (its replay saves no frames)")
    if args.name and (Path(args.name).name != args.name or args.name in (".", "..")):  # ../x wrote beside --out
        raise RtwalkError(f"--name '{args.name}': a file stem, without folders (the folder is --out)")
    rec = load_recording(rec_path)
    opts = BenchOptions(backend=args.backend, size=size, fps=args.fps,
                        max_frames=args.frames, reference=args.reference, reference_every=args.reference_every,
                        frames_dir=frames_dir, frame_every=args.frame_every, backend_options=backend_options,
                        first_frame=getattr(args, "first_frame", None),
                        denoise=getattr(args, "denoise", "off") == "on")
    replayed = frame_numbers(rec, opts.fps, opts.max_frames, opts.first_frame)  # --first-frame within the path
    if frames_dir is not None and not getattr(args, "progressive", False):  # an earlier run's frames are kept
        check_report_free([frames_dir / f"frame_{n:05d}.png" for n in replayed[::args.frame_every]],
                          getattr(args, "force", False), "--save-frames")
    check_device(args.backend)
    ctx = create_headless_context()  # no EGL: fail before loading
    check_target_size(ctx, size)  # before the scene, as every check that needs none
    prepared = scene_from_args(args, rec)
    warn_no_mirrors(settings, prepared.scene)
    stem = args.name or f"{prepared.scene.name}-{Path(rec_path).stem}-{args.backend}-{opts.size[0]}x{opts.size[1]}"
    progressive = getattr(args, "progressive", False)
    names = [f"{stem}-progressive.json"] if progressive else [f"{stem}.json", f"{stem}.png"]
    check_report_free([out_dir / n for n in names], getattr(args, "force", False))
    if progressive:
        from viewer.bench.progressive import replay_progressive

        result = replay_progressive(prepared, rec, settings, opts, ctx, args.frame_target_ms, quiet=args.quiet)
        path = out_dir / names[0]
        write_json(path, result)
        print(f"report: {path}")
        return 0
    report = run_bench(prepared, rec, settings, opts, ctx, quiet=args.quiet)
    if not report["complete"]:  # interrupted (Ctrl-C): the frames done are kept, marked incomplete
        if report["frames"]:
            json_path, _ = write_report(report, out_dir, stem)
            raise KeyboardInterrupt(f"interrupted after {len(report['frames'])} frames: partial report {json_path} "
                                    "(\"complete\": false)")  # cli.main prints it: one line
        raise KeyboardInterrupt
    print_summary(report)
    json_path, png_path = write_report(report, out_dir, stem)
    print(f"report: {json_path}\nplot:   {png_path}")
    return 0

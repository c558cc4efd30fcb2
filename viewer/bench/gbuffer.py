"""`rtwalk bench-gbuffer`: what the G-buffer raster costs, and what its culling saves.

Along a recording's consecutive frames (the occlusion culling's temporal coherence is what a walk
gives it), each frame is rasterized in every configuration, interleaved (so the machine's load
hits all alike): the exact conservative raster or the moving frames' plain `preview` raster,
each with frustum culling alone or with the device's occlusion culling
(viewer/passes/occlusion.py). Per configuration: median and p95 ms (timed with a finish before
and after) and the triangles drawn (the occlusion counts are read back from the device, which a
normal frame never does). The configurations' images are compared too: the share of pixels whose
triangle differs from the frustum-culled raster of the same kind (ties between equal distances).

Report: `gbuffer.json`, `gbuffer.md`, `gbuffer.png` in --out.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from viewer.bench.common import log

HELP = "G-buffer raster cost along a recording: exact vs preview, frustum vs occlusion culling (ms, triangles)"
CONFIGS = (("exact", False), ("exact", True), ("preview", False), ("preview", True))


def config_name(kind: str, occlusion: bool) -> str:
    return f"{kind}+{'occlusion' if occlusion else 'frustum'}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recording", default="city-near", help="shipped recording name or file (default city-near)")
    p.add_argument("--size", default="112x63",
                   help="image size (default 112x63: an 896x504 window's moving frames at render scale 1/8)")
    p.add_argument("--frames", type=int, default=60, help="consecutive frames measured (default 60)")
    p.add_argument("--first-frame", type=int, default=0, help="first frame of the recording (default 0)")
    p.add_argument("--scene-size", type=int, default=None,
                   help="triangles of the recording's procedural scene (city), e.g. 1000000 (default: the recording's)")
    p.add_argument("--out", default="out/bench", help="folder for gbuffer.json/.md/.png (default out/bench)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def measure(prepared, cameras: list, size: tuple[int, int], ctx, progress=None, keep=None, check=None) -> dict:
    """Per configuration: ms per frame, triangles drawn per frame, and the share of pixels whose
    triangle differs from the frustum-culled raster of the same kind. `keep` gets the samples
    before the first frame (an interrupted run summarizes the frames done), `check` runs between
    frames (a deferred Ctrl-C stops there: viewer.bench.partial)."""
    from viewer.gl.textures import read_texture
    from viewer.renderer import Renderer

    r = Renderer(ctx, prepared.scene, prepared.bvh, size)
    g = r.gbuffer
    out = {config_name(*c): {"ms": [], "triangles": [], "differing_pixels": []} for c in CONFIGS}
    if keep is not None:
        keep(out)
    try:
        for i, cam in enumerate(cameras):
            if check is not None:
                check()
            ids = {}
            for kind, occlusion in CONFIGS:
                g.occlusion = occlusion
                ctx.finish()
                t0 = time.perf_counter()
                g.render(cam, preview=kind == "preview")
                ctx.finish()
                rec = out[config_name(kind, occlusion)]
                rec["ms"].append((time.perf_counter() - t0) * 1e3)
                rec["triangles"].append(g.drawn_triangles)
                ids[(kind, occlusion)] = read_texture(g.tri_id)[..., 0].copy()
            for kind in ("exact", "preview"):
                diff = float((ids[(kind, True)] != ids[(kind, False)]).mean())
                out[config_name(kind, True)]["differing_pixels"].append(diff)
                out[config_name(kind, False)]["differing_pixels"].append(0.0)
            if progress is not None:
                progress(i + 1, len(cameras))
    finally:
        g.occlusion = True
        r.release()
    return summarize(out)


def frames_done(samples: dict) -> int:
    """Frames every configuration finished (all of them, unless interrupted mid-frame)."""
    return min(len(rec["differing_pixels"]) for rec in samples.values())


def summarize(samples: dict) -> dict:
    """The per-configuration medians of the frames every configuration finished."""
    n = frames_done(samples)
    out = {}
    for name, rec in samples.items():
        rec = {k: v[:n] for k, v in rec.items()}
        rec["median_ms"] = float(np.median(rec["ms"]))
        rec["p95_ms"] = float(np.percentile(rec["ms"], 95))
        rec["median_triangles"] = float(np.median(rec["triangles"]))
        rec["max_differing_pixels"] = float(max(rec["differing_pixels"]))
        out[name] = rec
    return out


def _markdown(report: dict) -> str:
    from viewer.bench.report import fmt, md_table, ratio

    rows = []
    for name, rec in report["configs"].items():
        base = report["configs"][name.split("+")[0] + "+frustum"]
        rows.append([name, fmt(rec["median_ms"]), fmt(rec["p95_ms"]), fmt(rec["median_triangles"], 0),
                     fmt(ratio(rec["median_triangles"], base["median_triangles"]), 2),
                     fmt(ratio(base["median_ms"], rec["median_ms"]), 2), f"{rec['max_differing_pixels']:.4f}"])
    head = (f"# G-buffer raster: {report['recording']} frames {report['first_frame']}.."
            f"{report['first_frame'] + report['frames'] - 1}, {report['size'][0]}x{report['size'][1]}, "
            f"{report['triangles']:,} triangles\n\n")
    return head + md_table(["configuration", "median ms", "p95 ms", "triangles drawn", "drawn / frustum",
                            "speedup vs frustum", "max differing px"], rows, "lrrrrrr")


def _plot(configs: dict, size: tuple[int, int], path: Path) -> None:
    from viewer.bench.plots import bars, figure, finish

    fig, ax = figure(1, 2, size=(11, 4))
    names = list(configs)
    bars(ax[0], names, {"median ms": [configs[n]["median_ms"] for n in names]}, ylabel="ms per G-buffer",
         texts=[f"{configs[n]['median_ms']:.1f}" for n in names])
    bars(ax[1], names, {"triangles": [configs[n]["median_triangles"] for n in names]}, ylabel="triangles drawn",
         texts=[f"{configs[n]['median_triangles']:,.0f}" for n in names])
    for a in ax:
        a.tick_params(axis="x", labelsize=7)
    finish(fig, path, f"G-buffer raster, {size[0]}x{size[1]}")


def run(args) -> int:
    from viewer.bench.partial import keep_partial, write_plots
    from viewer.bench.report import write_study
    from viewer.cli_args import check_at_least, check_output_dir, check_report_free, parse_size
    from viewer.gl.context import create_headless_context
    from viewer.gl.limits import check_target_size
    from viewer.paths import resolve_recording
    from viewer.recording import load_recording
    from viewer.session import prepare_scene_for_recording

    size = parse_size(args.size)
    check_at_least(args.frames, 1, "--frames")
    check_at_least(args.first_frame, 0, "--first-frame")
    if args.scene_size is not None:
        check_at_least(args.scene_size, 1, "--scene-size")
    out = check_output_dir(args.out, "--out")
    check_report_free([Path(out) / "gbuffer.json"], args.force)
    rec = load_recording(resolve_recording(args.recording))
    cameras = [rec.camera_for_frame(args.first_frame + k) for k in range(args.frames)]  # in range
    ctx = create_headless_context()
    check_target_size(ctx, size)  # before the scene (it was refused only after the load and BVH build)
    prepared = prepare_scene_for_recording(rec, scene_size=args.scene_size, quiet=args.quiet)
    every = max(1, args.frames // 10)
    samples: list[dict] = []

    def write(configs: dict, frames: int, complete: bool) -> dict:
        report = {"complete": complete, "recording": args.recording, "scene": rec.scene_name,
                  "size": list(size), "frames": frames, "first_frame": args.first_frame,
                  "triangles": prepared.scene.triangle_count, "configs": configs}
        md = _markdown(report)
        written = write_study(Path(out), "gbuffer", report, md)
        write_plots(lambda: _plot(configs, size, written["png"]))  # after the JSON: never loses it
        return {**written, "markdown": md}

    def partial(complete: bool) -> Path | None:
        if not samples or frames_done(samples[0]) == 0:
            return None
        return write(summarize(samples[0]), frames_done(samples[0]), complete)["json"]

    with keep_partial("bench-gbuffer", defer=True) as part:  # Ctrl-C: stop after the frame in hand
        part.keep(partial)
        configs = measure(prepared, cameras, size, ctx,
                          lambda k, n: log(args, f"frame {k}/{n}", "bench-gbuffer") if k % every == 0 or k == n
                          else None, keep=samples.append, check=part.check)
    written = write(configs, args.frames, True)
    md = written["markdown"]
    print(md)
    print(f"report: {written['json']}")
    return 0

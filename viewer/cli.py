"""Command line: `rtwalk [view|render|bench|bench-*|info|demo] ...`. Bad input -> one line, exit 2."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from viewer.bench import voxels as bench_voxels

# the argument helpers live in viewer.cli_args (the window and the benchmarks use them without
# importing this module)
from viewer.cli_args import (
    DEFAULT_RECORDING,
    add_denoise_arg,
    add_effect_args,
    add_progressive_args,
    add_scene_args,
    backend_options_from,
    check_at_least,
    check_device,
    check_image_output,
    check_output_dir,
    check_positive,
    parse_camera,
    parse_size,
    parse_sizes,
    scene_from_args,
    settings_from,
)
from viewer.errors import RtwalkError

BENCH_FRAMES = 48  # default bench: frames spread over the path, a few minutes on 2 cores
BENCH_REFERENCE_EVERY = 6  # and an Embree check of every 6th of them
VIEW_SIZE = "896x504"  # the window's image; the panel is beside it (viewer.ui.panel.PANEL_WIDTH)


def cmd_render(args) -> int:
    from PIL import Image

    from viewer.backends import backend_info
    from viewer.gl.context import create_headless_context
    from viewer.passes.overlay import check_view
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    # everything that needs no scene first: backend, parameters, view, size, effects, output, devices
    backend_options = backend_options_from(args)
    check_view(args.view, backend_info(args.backend))
    size = parse_size(args.size)
    settings = settings_from(args)
    check_at_least(args.frame, 0, "--frame")
    camera = parse_camera(args.camera) if args.camera else None
    out = check_image_output(args.output)
    rec = load_recording(args.recording) if args.recording else None
    if camera is None and rec is not None:
        camera = rec.camera_for_frame(args.frame)
    check_device(args.backend)
    ctx = create_headless_context()  # no EGL: fail before loading
    prepared = scene_from_args(args, rec)
    if camera is None:
        camera = prepared.scene.default_camera
    renderer = Renderer(ctx, prepared.scene, prepared.bvh, size, args.backend, settings, backend_options)
    renderer.view = args.view
    if rec is not None:  # an animated scene is shown at the recording's scene time of that frame
        renderer.set_scene_time(rec.scene_time_for_frame(args.frame))
    report = renderer.render(camera)
    denoise = getattr(args, "denoise", "off") == "on"
    Image.fromarray(renderer.read_denoised("library", camera) if denoise else renderer.read_image()).save(out)
    if not args.quiet:
        from viewer.denoise import filter_line

        rays = ", ".join(f"{k} {v:,}" for k, v in report.rays.items()) or "none"
        print(f"wrote {out} ({size[0]}x{size[1]}, GPU {sum(report.gpu_ms.values()):.1f} ms; rays: {rays}"
              f"{filter_line(denoise, renderer)})", file=sys.stderr)
    return 0


def cmd_bench(args) -> int:
    from viewer.bench.harness import frame_numbers
    from viewer.bench.replay import BenchOptions, print_summary, run_bench, write_report
    from viewer.gl.context import create_headless_context
    from viewer.recording import load_recording

    rec_path = args.recording or (DEFAULT_RECORDING if args.scene in (None, "city") else None)
    if rec_path is None:
        raise RtwalkError("bench needs --recording FILE for this scene (see recordings/)")
    # everything that needs no scene first: backend, parameters, numbers, output folders, devices
    backend_options = backend_options_from(args)
    size = parse_size(args.size)
    settings = settings_from(args)
    check_positive(args.fps, "--fps")
    check_positive(getattr(args, "frame_target_ms", None), "--frame-target-ms")
    check_at_least(args.frames, 1, "--frames")
    check_at_least(args.reference_every, 1, "--reference-every")
    check_at_least(args.frame_every, 1, "--frame-every")
    check_at_least(getattr(args, "first_frame", None), 0, "--first-frame")
    out_dir = check_output_dir(args.out, "--out")
    frames_dir = check_output_dir(args.save_frames, "--save-frames")
    rec = load_recording(rec_path)
    opts = BenchOptions(backend=args.backend, size=size, fps=args.fps,
                        max_frames=args.frames, reference=args.reference, reference_every=args.reference_every,
                        frames_dir=frames_dir, frame_every=args.frame_every, backend_options=backend_options,
                        first_frame=getattr(args, "first_frame", None),
                        denoise=getattr(args, "denoise", "off") == "on")
    frame_numbers(rec, opts.fps, opts.max_frames, opts.first_frame)  # --first-frame within the path
    check_device(args.backend)
    ctx = create_headless_context()  # no EGL: fail before loading
    prepared = scene_from_args(args, rec)
    stem = args.name or f"{prepared.scene.name}-{Path(rec_path).stem}-{args.backend}-{opts.size[0]}x{opts.size[1]}"
    if getattr(args, "progressive", False):
        import json

        from viewer.progressive import replay_progressive

        result = replay_progressive(prepared, rec, settings, opts, ctx, args.frame_target_ms, quiet=args.quiet)
        path = out_dir / f"{stem}-progressive.json"
        path.write_text(json.dumps(result, indent=1))
        print(f"report: {path}")
        return 0
    report = run_bench(prepared, rec, settings, opts, ctx, quiet=args.quiet)
    print_summary(report)
    json_path, png_path = write_report(report, out_dir, stem)
    print(f"report: {json_path}\nplot:   {png_path}")
    return 0


def cmd_bench_bvh(args) -> int:
    from viewer.accel.bvh import bench_build
    from viewer.bench.report import write_json
    from viewer.procedural import make_city

    sizes = parse_sizes(args.sizes)
    out = check_output_dir(args.out, "--out")
    rows = []
    for n in sizes:
        scene = make_city(n, args.seed)
        r = bench_build(scene.triangles)
        r["target"] = n
        rows.append(r)
        print(f"city {scene.triangle_count:>10,} tris: build {r['build_time_s']:.2f} s "
              f"({r['throughput_mtris_per_s']:.2f} Mtri/s), {r['nodes']:,} nodes, depth {r['depth']}, "
              f"SAH {r['sah_cost']:.1f}", flush=True)
    write_json(out / "bvh-build.json", rows)
    print(f"report: {out / 'bvh-build.json'}")
    return 0


def cmd_bench_cl(args) -> int:
    from viewer.bench.cl_primitives import run

    return run(args)


def cmd_bench_trace(args) -> int:
    from viewer.bench.trace_vs_embree import run

    return run(args)


def cmd_bench_chcrt(args) -> int:
    from viewer.bench.chcrt import cmd_bench_chcrt as run

    return run(args)


def cmd_bench_pgrid(args) -> int:
    from viewer.bench.pgrid import run

    return run(args)


def cmd_bench_voxelwalk(args) -> int:
    from viewer.bench.voxelwalk import run

    return run(args)


def cmd_bench_denoise(args) -> int:
    from viewer.bench.denoise import run

    return run(args)


def cmd_bench_light(args) -> int:
    from viewer.bench.lit import run

    return run(args)


def cmd_info(args) -> int:
    prepared = scene_from_args(args)
    s = prepared.scene
    lo, hi = s.bounds
    lo, hi = ([round(float(v), 3) for v in b] for b in (lo, hi))
    print(f"scene {s.name}: {s.triangle_count:,} triangles, bounds {lo} .. {hi}")
    for m in s.materials:
        albedo = ", ".join(f"{float(a):.3g}" for a in m.albedo)  # 0.7, not 0.699999988079071
        print(f"  material {m.name}: albedo [{albedo}]{' (mirror)' if m.mirror else ''}")
    for note in s.notes:
        print(f"  note: {note}")
    return 0


def cmd_view(args) -> int:
    from viewer.ui.app import run_viewer

    return run_viewer(args)


def cmd_demo(args) -> int:
    """The main job: a window where there is a display, else a headless replay with a report."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return cmd_view(args)
    print("rtwalk: no display: replaying recordings/city-near.json headless "
          "(frames and report in out/demo/)", file=sys.stderr)
    args.recording = str(DEFAULT_RECORDING)
    args.save_frames = "out/demo/frames"
    args.out = "out/demo"
    args.name = "city-near"
    return cmd_bench(args)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="rtwalk", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command")

    v = sub.add_parser("view", help="interactive window")
    add_scene_args(v)
    add_effect_args(v, "shadows,reflections")
    v.add_argument("--recording", default=None, help="play this recording (P toggles)")
    v.add_argument("--max-frames", type=int, default=None,
                   help="quit after N frames (also RTWALK_VIEW_FRAMES; RTWALK_VIEW_SCREENSHOT=PNG saves the window)")
    add_progressive_args(v, "progressive refinement (default): one pass per effect at a reduced scale while the "
                            "camera moves, more passes when it stops; --no-progressive: full quality every frame",
                         default=True)
    add_denoise_arg(v)
    v.set_defaults(size=VIEW_SIZE)

    r = sub.add_parser("render", help="render one frame headless to PNG")
    add_scene_args(r)
    add_effect_args(r, "shadows,reflections")
    r.add_argument("--camera", default=None, help="eye_x,eye_y,eye_z,target_x,target_y,target_z[,fov]")
    r.add_argument("--recording", default=None, help="take the camera from this recording (see --frame)")
    r.add_argument("--frame", type=int, default=0,
                   help="frame of --recording whose camera is rendered (0 = first; at the recording's fps)")
    r.add_argument("--view", default="final", help="final or one pass alone (albedo, normal, depth, shadows, ...)")
    r.add_argument("-o", "--output", default="out/render.png",
                   help="image file (.png, .jpg, .bmp, .tif, .ppm, .webp, .tga); its folder is created")
    add_denoise_arg(r)

    b = sub.add_parser("bench", help="replay a recording and report speed and error")
    add_scene_args(b)
    add_effect_args(b, "shadows,ao:4,reflections")
    b.add_argument("--recording", default=None, help="camera path (default: recordings/city-near.json for city)")
    b.add_argument("--fps", type=float, default=None, help="sample the path at this rate (default: recording's)")
    b.add_argument("--frames", type=int, default=BENCH_FRAMES,
                   help=f"at most this many frames (>= 1, default {BENCH_FRAMES}), spread over the path "
                        "(consecutive with --first-frame); a number >= the path's frame count replays all")
    b.add_argument("--first-frame", type=int, default=None,
                   help="replay consecutive frames from this one (temporal coherence as in a walkthrough)")
    b.add_argument("--reference", choices=["embree", "none"], default="embree",
                   help="check frames against Embree (error columns), or none")
    b.add_argument("--reference-every", type=int, default=BENCH_REFERENCE_EVERY,
                   help=f"check every Nth replayed frame against Embree (default {BENCH_REFERENCE_EVERY}; "
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

    from viewer.bench.chcrt import add_arguments as add_bench_chcrt_args

    bc = sub.add_parser("bench-chcrt", help="CHC+RT paper tables: glsl vs chcrt, aggressive mode, phases, overhead")
    add_bench_chcrt_args(bc)

    from viewer.bench.pgrid import add_arguments as add_bench_pgrid_args

    bp = sub.add_parser("bench-pgrid", help="perspective-grid thesis studies: pgrid vs uniform grid vs BVH")
    add_bench_pgrid_args(bp)
    from viewer.bench.voxelwalk import add_arguments as add_bench_voxelwalk_args

    add_bench_voxelwalk_args(sub.add_parser("bench-voxelwalk", help="voxel-walk thesis studies: IVW vs EC on "
                                            "reflection rays, with clbvh on the same rays"))
    from viewer.bench.cl_primitives import add_arguments as add_bench_cl_args
    from viewer.bench.trace_vs_embree import add_arguments as add_bench_trace_args

    add_bench_trace_args(sub.add_parser("bench-trace", help="Mrays/s per ray type of backends and raw Embree "
                                                          "on the same captured rays"))
    add_bench_cl_args(sub.add_parser("bench-cl", help="OpenCL sort/scan/compact throughput next to NumPy"))
    bench_voxels.add_parser(sub)
    from viewer.bench.denoise import add_arguments as add_bench_denoise_args
    from viewer.bench.lit import add_arguments as add_bench_light_args

    add_bench_denoise_args(sub.add_parser("bench-denoise", help="denoisers (OIDN, device a-trous) against a "
                                          "256-sample reference: MAE raw vs filtered and cost in ms"))

    add_bench_light_args(sub.add_parser("bench-light", help="share of directly lit pixels (--view shadows) "
                                        "along the shipped recordings, every 60th frame"))

    bb = sub.add_parser("bench-bvh", help="BVH build throughput on the city scene")
    bb.add_argument("--sizes", default="1000000,5000000",
                    help="comma list of city triangle counts to build (each as --scene-size accepts)")
    bb.add_argument("--seed", type=int, default=1, help="seed of the procedural city")
    bb.add_argument("--out", default="out/bench", help="folder for bvh-build.json")

    i = sub.add_parser("info", help="scene statistics")
    add_scene_args(i)

    d = sub.add_parser("demo", help="main job: window if a display exists, else headless replay + report")
    add_scene_args(d)
    add_effect_args(d, "shadows,ao:4,reflections")
    d.add_argument("--frames", type=int, default=24, help="without a display: frames replayed (>= 1)")
    add_denoise_arg(d)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help")):
        argv = ["demo"] + argv  # bare `rtwalk [options]` runs the main job
    args = ap.parse_args(argv)
    args.command_line = shlex.join(["rtwalk", *argv])  # what the reports quote to reproduce a run
    handlers = {"view": cmd_view, "render": cmd_render, "bench": cmd_bench, "bench-bvh": cmd_bench_bvh,
                "bench-chcrt": cmd_bench_chcrt, "bench-pgrid": cmd_bench_pgrid, "bench-voxelwalk": cmd_bench_voxelwalk,
                "bench-trace": cmd_bench_trace, "bench-cl": cmd_bench_cl, "bench-voxels": bench_voxels.run,
                "info": cmd_info, "demo": cmd_demo}
    handlers.update({"bench-light": cmd_bench_light, "bench-denoise": cmd_bench_denoise})
    if args.command == "demo":
        # demo reuses bench/view; fill in what their parsers would have set
        for key, val in {"recording": None, "fps": None, "reference": "embree", "reference_every": 6,
                         "frame_every": 4, "save_frames": None, "out": "out/demo", "name": None}.items():
            if not hasattr(args, key):
                setattr(args, key, val)
    try:
        return handlers[args.command](args)
    except RtwalkError as exc:
        print(f"rtwalk: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rtwalk: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

"""Command line: `rtwalk [view|render|bench|bench-*|info|demo] ...`. Bad input -> one line, exit 2."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from viewer.bench import BENCHMARKS, bench_module

# the argument helpers live in viewer.cli_args (the window and the benchmarks use them without
# importing this module)
from viewer.cli_args import (
    DEFAULT_RECORDING,
    RENDER_SIZE,
    add_denoise_arg,
    add_effect_args,
    add_force_arg,
    add_progressive_args,
    add_scene_args,
    check_at_least,
    check_device,
    check_image_output,
    check_report_free,
    parse_camera,
    request_from,
    scene_from_args,
    warn_no_mirrors,
)
from viewer.errors import RtwalkError

VIEW_SIZE = "896x504"  # the window's image; the panel is beside it (viewer.ui.panel.PANEL_WIDTH)


def cmd_render(args) -> int:
    from PIL import Image
    from tqdm import tqdm

    from viewer.backends import backend_info, registered_infos
    from viewer.effects import effects_for_view
    from viewer.gl.context import create_headless_context
    from viewer.gl.limits import check_target_size
    from viewer.passes.overlay import check_view, check_view_effect
    from viewer.progressive import render_stepped
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    # everything that needs no scene first: backend, parameters, view, size, effects, output, devices
    req = request_from(args, device=False)
    backend_options, size, settings = req.backend_options, req.size, req.settings
    check_view(args.view, backend_info(args.backend), registered_infos())
    check_view_effect(args.view, settings, args.effects)
    settings = effects_for_view(settings, args.view)  # --view depth traces no shadow or reflection rays
    check_at_least(args.frame, 0, "--frame")
    camera = parse_camera(args.camera) if args.camera else None
    out = check_image_output(args.output)
    check_report_free([out], args.force, "-o/--output")  # an earlier picture is kept unless --force
    rec = load_recording(args.recording) if args.recording else None
    if camera is None and rec is not None:
        camera = rec.camera_for_frame(args.frame)
    check_device(args.backend)
    ctx = create_headless_context()  # no EGL: fail before loading
    check_target_size(ctx, size)  # a size the device cannot hold, before the scene (the Renderer checks again)
    prepared = scene_from_args(args, rec)
    warn_no_mirrors(settings, prepared.scene)
    if camera is None:
        camera = prepared.scene.default_camera
    renderer = Renderer(ctx, prepared.scene, prepared.bvh, size, args.backend, settings, backend_options)
    renderer.view = args.view
    if rec is not None:  # an animated scene is shown at the recording's scene time of that frame
        renderer.set_scene_time(rec.scene_time_for_frame(args.frame))
    # steps of sample passes, for a progress bar (shown after 1 s, on a terminal, without --quiet)
    with tqdm(total=1, desc="render", unit="step", delay=1.0, disable=True if args.quiet else None,
              file=sys.stderr, leave=False) as bar:

        def step_done(done: int, steps: int) -> None:
            bar.total = steps
            bar.update(done - bar.n)

        gpu_ms, rays = render_stepped(renderer, camera, step_done)
    out.parent.mkdir(parents=True, exist_ok=True)
    denoise = getattr(args, "denoise", "off") == "on"
    Image.fromarray(renderer.read_denoised("library", camera) if denoise else renderer.read_image()).save(out)
    if not args.quiet:
        from viewer.denoise import filter_line

        ray_list = ", ".join(f"{k} {v:,}" for k, v in rays.items()) or "none"
        print(f"wrote {out} ({size[0]}x{size[1]}, GPU {sum(gpu_ms.values()):.1f} ms; rays: {ray_list}"
              f"{filter_line(denoise, renderer)})", file=sys.stderr)
    return 0


def cmd_info(args) -> int:
    if args.backend:  # a backend's self-description; no scene needed unless one is named
        from viewer.backends import backend_info
        from viewer.backends.interface import describe

        description = describe(backend_info(args.backend))  # an unknown name before any scene is loaded
        if args.scene is None:
            print(description)
            return 0
        _print_scene_info(args)  # `info SCENE --backend NAME`: both (the scene was silently ignored)
        print(description)
        return 0
    _print_scene_info(args)
    return 0


def _print_scene_info(args) -> None:
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


def cmd_view(args) -> int:
    from viewer.ui.app import run_viewer

    return run_viewer(args)


def cmd_demo(args) -> int:
    """The main job: a window where there is a display, else a headless replay with a report."""
    windowed = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if args.size is None:  # the window opened at the replay's 640x360, not at view's own default
        args.size = VIEW_SIZE if windowed else RENDER_SIZE
    if windowed:
        return cmd_view(args)
    request_from(args, device=False)  # what needs no scene is refused before the recording is chosen
    check_at_least(args.frames, 1, "--frames")
    rec = demo_recording(args.scene)
    print(f"rtwalk: no display: replaying recordings/{rec.name} headless "
          "(frames and report in out/demo/)", file=sys.stderr)
    args.recording = str(rec)
    args.save_frames = "out/demo/frames"
    args.out = "out/demo"
    args.name = rec.stem
    args.force = True  # the demo's own folder: each headless demo replaces the last one's report
    return bench_module("bench").run(args)


def demo_recording(scene: str | None) -> Path:
    """The shipped recording the headless demo replays: city-near for the city, else the one made
    for SCENE (its cameras look at that scene; city-near's showed an empty grey frame in the room).
    One line when no shipped recording shows SCENE."""
    from viewer.paths import RECORDINGS
    from viewer.procedural import BUILTIN_SCENES
    from viewer.recording import load_recording, resolve_scene_spec
    from viewer.scene_io import resolve_scene_path

    base = (scene or "city").partition(":")[0]
    if base == "city" or (base not in BUILTIN_SCENES and "/" not in base and "." not in base):
        return DEFAULT_RECORDING  # the city, or an unknown name the scene loader reports
    wanted = base if base in BUILTIN_SCENES else str(resolve_scene_path(scene).resolve())
    shipped = sorted(RECORDINGS.glob("*.json"))
    for path in shipped:
        spec = resolve_scene_spec(load_recording(path)).spec
        if spec == wanted or (spec not in BUILTIN_SCENES and str(Path(spec).resolve()) == wanted):
            return path
    raise RtwalkError(f"no shipped recording shows scene '{scene}' (the headless demo replays one; shipped: "
                      f"{', '.join(p.stem for p in shipped)}); use `rtwalk bench {scene} --recording FILE`")


class DefaultsFormatter(argparse.HelpFormatter):
    """Help that shows each option's default (--size, --effects, --backend, ... did not say theirs,
    and view's 896x504 differs from render's 640x360), unless its text already names it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        shown = action.option_strings and not (d is None or isinstance(d, bool) or d in ([], "", argparse.SUPPRESS))
        if shown and "default" not in text:
            text += " (default: %(default)s)"
        return text


class RtwalkParser(argparse.ArgumentParser):
    """Bad arguments are one line, exit 2, as every other bad input (README); argparse printed its
    usage block (~10 lines) and "rtwalk render: error: ...". Subcommand parsers are of this class too."""

    def error(self, message: str):
        if message.endswith("expected one argument"):  # `--size -5x5`: the value was taken for a flag
            message += " (a value that starts with '-' is written --flag=VALUE)"
        self.exit(2, f"rtwalk: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    ap = RtwalkParser(prog="rtwalk", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command")

    v = sub.add_parser("view", help="interactive window")
    add_scene_args(v)
    add_effect_args(v, "shadows,reflections")
    v.add_argument("--recording", default=None, help="play this recording (P toggles)")
    v.add_argument("--max-frames", type=int, default=None,
                   help="quit after N frames (also RTWALK_VIEW_FRAMES; RTWALK_VIEW_SCREENSHOT=PNG saves the window)")
    v.add_argument("--frame-log", default=None,
                   help="write each frame's time, render scale, G-buffer source and phases to this JSON file "
                        "when the window closes, with fps medians (moving, refining)")
    add_progressive_args(v, "progressive refinement (default): one pass per effect at a reduced scale while the "
                            "camera moves, more passes when it stops; --no-progressive: full quality every frame",
                         default=True)
    v.add_argument("--force", action="store_true",
                   help="replace an existing RTWALK_VIEW_SCREENSHOT image or --frame-log file (default: refuse; "
                        "F12 screenshots always get a new name in screenshots/)")
    add_denoise_arg(v)
    v.set_defaults(size=VIEW_SIZE)
    next(a for a in v._actions if a.dest == "size").help = (
        "WIDTHxHEIGHT of the image; a window (image + panel) larger than the display is fitted to it, "
        "aspect kept, with a warning (larger images: rtwalk render)")

    r = sub.add_parser("render", help="render one frame headless to PNG")
    add_scene_args(r)
    add_effect_args(r, "shadows,reflections")
    r.add_argument("--camera", default=None, help="eye_x,eye_y,eye_z,target_x,target_y,target_z[,fov]")
    r.add_argument("--recording", default=None, help="take the camera from this recording (see --frame)")
    r.add_argument("--frame", type=int, default=0,
                   help="frame of --recording whose camera is rendered (0 = first; at the recording's fps)")
    r.add_argument("--view", default="final",
                   help="final or one pass alone (albedo, normal, depth, triangle_id: the G-buffer, no rays traced; "
                        "shadows, soft, ao, diffuse, reflections: only that effect of --effects traced) or a "
                        "backend's overlay")
    r.add_argument("-o", "--output", default="out/render.png",
                   help="image file (.png, .jpg, .bmp, .tif, .ppm, .webp, .tga); its folder is created")
    r.add_argument("--force", action="store_true", help="replace the image if -o names an existing file "
                                                          "(default: refuse)")
    add_denoise_arg(r)

    for command in BENCHMARKS:  # every benchmark registers itself (viewer/bench/__init__.py)
        module = bench_module(command)
        module.add_arguments(sub.add_parser(command, help=module.HELP))

    for name, parser in sub.choices.items():  # nothing lost: every report writer refuses to overwrite
        if name.startswith("bench") and getattr(bench_module(name), "WRITES_REPORTS", True):
            add_force_arg(parser)

    i = sub.add_parser("info", help="scene statistics, and/or a backend's description and parameters (--backend NAME)")
    add_scene_args(i)
    i.add_argument("--backend", default=None,
                   help="describe this backend: device, exactness, every parameter (alone: no scene is loaded; "
                        "with SCENE: the scene's statistics, then the backend)")

    d = sub.add_parser("demo", help="main job: window if a display exists, else headless replay + report")
    add_scene_args(d)
    add_effect_args(d, "shadows,ao:4,reflections")
    d.add_argument("--frames", type=int, default=24, help="without a display: frames replayed (>= 1)")
    d.set_defaults(size=None)
    next(a for a in d._actions if a.dest == "size").help = (
        f"WIDTHxHEIGHT (default: {VIEW_SIZE} in the window, as view; {RENDER_SIZE} for the headless replay)")
    add_denoise_arg(d)
    for parser in sub.choices.values():
        parser.formatter_class = DefaultsFormatter
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    subcommands = next(a.choices for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    if not argv or (argv[0] not in subcommands and argv[0] not in ("-h", "--help")):
        unknown = _unknown_first_word(argv[0] if argv else "-", subcommands)
        if unknown:  # `rtwalk rendr`: a mistyped command, not a scene (it said "no display: replaying ...")
            print(f"rtwalk: error: {unknown}", file=sys.stderr)
            return 2
        argv = ["demo"] + argv  # bare `rtwalk [SCENE] [options]` runs the main job
    args = ap.parse_args(argv)
    args.command_line = shlex.join(["rtwalk", *argv])  # what the reports quote to reproduce a run
    handlers = {"view": cmd_view, "render": cmd_render, "info": cmd_info, "demo": cmd_demo}
    handlers.update({command: bench_module(command).run for command in BENCHMARKS})
    if args.command == "demo":
        # demo reuses bench/view; fill in what their parsers would have set
        from viewer.reference import REFERENCE_BACKEND

        for key, val in {"recording": None, "fps": None, "reference": REFERENCE_BACKEND, "reference_every": 6,
                         "frame_every": 4, "save_frames": None, "out": "out/demo", "name": None}.items():
            if not hasattr(args, key):
                setattr(args, key, val)
    return _run(handlers[args.command], args)


def _unknown_first_word(word: str, subcommands) -> str | None:
    """Why `rtwalk WORD` cannot be the main job's SCENE, or None: a bare word that is neither a
    command nor a built-in scene (files have a '/' or '.'; the scene loader reports those)."""
    from viewer.procedural import BUILTIN_SCENES

    base = word.partition(":")[0]
    if word.startswith("-") or "/" in base or "." in base or base in BUILTIN_SCENES:
        return None
    return (f"'{word}' is neither a command ({', '.join(subcommands)}) nor a built-in scene "
            f"({', '.join(BUILTIN_SCENES)}); see `rtwalk --help`")


def _run(handler, args: argparse.Namespace) -> int:
    """The command, its errors as one line (exit 2), an interrupt (Ctrl-C, or SIGTERM, which keeps
    partial work as Ctrl-C does: viewer.interrupt) as the line it carries (130)."""
    from viewer.backends.gl_traversal import loop_limit_env
    from viewer.interrupt import terminate_as_interrupt

    try:
        loop_limit_env()  # a bad RTWALK_LOOP_LIMIT is one line before anything loads
        with terminate_as_interrupt():
            return handler(args)
    except RtwalkError as exc:
        print(f"rtwalk: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `rtwalk info SCENE | head -1`: the reader left; no traceback
        try:  # the interpreter flushes stdout at exit: point it at /dev/null so that flush cannot fail
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):  # stdout is not a file (tests capture it)
            pass
        return 1
    except KeyboardInterrupt as exc:  # a command that kept partial work says so in the exception: one line
        print(f"rtwalk: {exc.args[0]}" if exc.args else "rtwalk: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

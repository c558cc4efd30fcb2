"""Command-line argument helpers shared by the CLI, the window and the benchmarks.

Kept apart from viewer.cli (which only registers subcommands and dispatches) so that the window
(viewer.ui.app) and the benchmarks (viewer.bench) can use them without importing the CLI: no
import cycle. Everything here checks input before any scene is loaded; bad input raises
RtwalkError (one line, exit 2).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS

DEFAULT_RECORDING = RECORDINGS / "city-near.json"


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise RtwalkError(f"bad --size '{text}': expected WIDTHxHEIGHT, e.g. 640x360") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise RtwalkError(f"bad --size '{text}': each side must be in 1..16384")
    return w, h


def parse_choices(text: str, allowed, option: str) -> list[str]:
    """"a,b" -> ["a", "b"], each one of `allowed`; "all" -> every allowed one (the studies' lists)."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    if items == ["all"]:
        return list(allowed)
    bad = [s for s in items if s not in allowed]
    if bad or not items:
        raise RtwalkError(f"{option}: unknown {', '.join(bad) or '(none)'} (choose from {', '.join(allowed)})")
    return items


def parse_image_sizes(text: str, option: str = "--sizes") -> list[tuple[int, int]]:
    """"640x360,1280x720" -> [(640, 360), (1280, 720)], each item checked as parse_size does."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise RtwalkError(f"{option} is empty")
    out = []
    for item in items:
        try:
            out.append(parse_size(item))
        except RtwalkError:
            raise RtwalkError(f"bad {option} item '{item}': expected WIDTHxHEIGHT (1..16384 each), "
                              "e.g. 640x360,1280x720") from None
    return out


def parse_camera(text: str):
    from viewer.camera import Camera
    from viewer.recording import MAX_FOV, MIN_FOV

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (6, 7) or not np.all(np.isfinite(vals)):
        raise RtwalkError(f"bad --camera '{text}': expected eye_x,eye_y,eye_z,target_x,target_y,target_z[,fov_deg]")
    if np.allclose(vals[:3], vals[3:6]):
        raise RtwalkError(f"bad --camera '{text}': eye and target coincide")
    if len(vals) == 7 and not MIN_FOV < vals[6] < MAX_FOV:
        raise RtwalkError(f"bad --camera '{text}': fov_deg must be between {MIN_FOV:g} and {MAX_FOV:g}")
    return Camera.look_at(vals[:3], vals[3:6], fov_y=vals[6] if len(vals) == 7 else 60.0)


def scene_size_arg(text: str) -> int:
    """--scene-size: a whole number, with k/M suffixes as `city:2M` and bench-bvh's --triangles take
    them (`--scene-size 2M` was an invalid int)."""
    t = text.strip().replace("_", "")
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:].lower(), 1)
    try:
        v = float(t[:-1] if mult > 1 else t) * mult
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v == int(v)):
        raise argparse.ArgumentTypeError(f"expected a whole number like 150000, 400k or 2M, got '{text}'")
    return int(v)


def add_scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", default=None,
                   help="scene file (OBJ/PLY/GLB/STL/OFF) or built-in name (city, room, room-anim); default: city")
    p.add_argument("--scene-size", type=scene_size_arg, default=None,
                   help="size of a built-in scene: city: triangles (1000..40000000, default 150000); "
                        "room, room-anim: detail level (1..6, default 1)")
    p.add_argument("--seed", type=int, default=1, help="seed for procedural scenes")
    p.add_argument("--mirror", action="append", default=[], metavar="PATTERN",
                   help="material name pattern made a mirror (repeatable, fnmatch, case-insensitive)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--bvh-builder", default=None, choices=("auto", "sah", "device"),
                   help="BVH builder on scene load: sah (CPU binned SAH, the quality reference), device "
                        "(OpenCL Morton + PLOC) or auto (device from 500k triangles when OpenCL is there); "
                        "default: $RTWALK_BVH_BUILDER, else auto")


RENDER_SIZE = "640x360"  # --size of render, bench and the headless demo (the window's: cli.VIEW_SIZE)


def add_effect_args(p: argparse.ArgumentParser, default: str) -> None:
    from viewer.backends import DEFAULT_BACKEND, PARAM_OPTIONS, backend_names

    p.add_argument("--effects", default=default,
                   help="comma list of primary,shadows,soft,ao,diffuse,reflections (NAME:N = N samples), "
                        "'all' or 'none'")
    p.add_argument("--backend", default=DEFAULT_BACKEND, help=f"tracing backend: {', '.join(backend_names())}")
    p.add_argument("--backend-params", default=None, metavar="KEY=VALUE,...",
                   help="parameters of the chosen --backend (also RTWALK_<BACKEND> in the environment; "
                        "`rtwalk info --backend NAME` lists them), e.g. key=value,key=value")
    p.add_argument("--size", default=RENDER_SIZE, help="WIDTHxHEIGHT")
    p.add_argument("--perturb", type=float, default=36.0, help="per-pixel sample rotation, degrees")
    p.add_argument("--ao-length", type=float, default=0.05, help="AO ray length, fraction of the scene diagonal")
    p.add_argument("--exposure", type=float, default=1.0,
                   help="multiplies the linear radiance before tone mapping (finite, > 0; default 1)")
    for option, name in PARAM_OPTIONS.items():
        p.add_argument(option, default=None, metavar="KEY=VALUE,...",
                       help=f"{name} backend parameters (alias kept from before --backend-params; "
                            f"`rtwalk info --backend {name}` lists them)")


def add_denoise_arg(p: argparse.ArgumentParser, default: str = "on") -> None:
    """--denoise on|off: filter the picture shown or saved (viewer.denoise); measurements stay raw."""
    p.add_argument("--denoise", choices=["on", "off"], default=default,
                   help="denoise the picture shown or saved, guided by the G-buffer's albedo and normal: "
                        "Open Image Denoise (pyoidn) for stills, replays and screenshots, an a-trous filter "
                        f"on the device for moving frames (default {default}; errors are measured raw)")


def add_progressive_args(p: argparse.ArgumentParser, help_flag: str, default: bool = False) -> None:
    """--progressive / --no-progressive and --frame-target-ms (viewer.progressive)."""
    from viewer.progressive import DEFAULT_TARGET_MS

    p.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=default, help=help_flag)
    p.add_argument("--frame-target-ms", type=float, default=DEFAULT_TARGET_MS,
                   help="progressive mode: frame time to keep while the camera moves (measured, so it holds "
                        "under load), by lowering the render scale down to 1/16 (default 60: 16.7 fps)")


def check_backend(name: str) -> str:
    """The backend name if registered, else one line naming the choices (before any scene work)."""
    from viewer.backends import backend_class

    backend_class(name)  # raises RtwalkError for an unknown name
    return name


def backend_options_from(args) -> dict[str, str]:
    """Per-backend parameter text, {backend name: "key=value,..."}; checked here (unknown backend,
    unknown key, bad value) so bad input fails before any scene is loaded. `--backend-params`
    belongs to `--backend`; the registry's PARAM_OPTIONS are older spellings of one backend's."""
    from viewer.backends import DEFAULT_BACKEND, PARAM_OPTIONS, check_params

    backend = getattr(args, "backend", None)
    if backend is not None:
        check_backend(backend)
    options: dict[str, str] = {}
    for option, name in PARAM_OPTIONS.items():
        text = getattr(args, option.lstrip("-").replace("-", "_"), None)
        if text:
            check_params(name, text, option)
            options[name] = text
    text = getattr(args, "backend_params", None)
    if text:
        target = backend or DEFAULT_BACKEND
        check_params(target, text, "--backend-params")
        prev = options.get(target)
        options[target] = f"{prev},{text}" if prev else text  # --backend-params wins
    return options


def settings_from(args):
    from viewer.effects import parse_effects

    s = parse_effects(args.effects)
    check_positive(args.exposure, "--exposure")
    if not 0 <= args.perturb <= 180:
        raise RtwalkError("--perturb must be within 0..180 degrees")
    if not 0 < args.ao_length <= 10:
        raise RtwalkError("--ao-length must be within (0, 10] (fraction of the scene diagonal)")
    s.perturb_deg, s.ao_length, s.exposure = args.perturb, args.ao_length, args.exposure
    return s


def warn_no_mirrors(settings, scene) -> str | None:
    """Reflections asked for on a scene without mirror materials would render exactly as without
    them: say so on stderr (a warning, not an error) and how to make materials mirrors."""
    if not getattr(settings, "reflections", False) or any(m.mirror for m in scene.materials):
        return None
    msg = (f"rtwalk: warning: reflections are on but scene '{scene.name}' has no mirror materials, so nothing "
           "reflects; make materials mirrors with --mirror PATTERN (fnmatch on material names, repeatable; "
           "`rtwalk info SCENE` lists them)")
    print(msg, file=sys.stderr, flush=True)
    return msg


def warn_other_scene(recording, scene: str) -> str | None:
    """A recording replayed in another scene than its own (`render room --recording city-near.json`)
    shows what its cameras happen to see there, often an empty frame: one warning line on stderr."""
    from viewer.procedural import BUILTIN_SCENES
    from viewer.recording import resolve_scene_spec
    from viewer.scene_io import resolve_scene_path

    def key(spec: str) -> str:
        base = spec.partition(":")[0]
        if base in BUILTIN_SCENES:
            return base
        try:
            return str(resolve_scene_path(spec).resolve())
        except RtwalkError:
            return spec  # a missing file: the loader reports it

    own = resolve_scene_spec(recording).spec
    if key(own) == key(scene):
        return None
    msg = (f"rtwalk: warning: the recording was made for scene '{Path(own).name}', not '{Path(scene).name}'; its "
           "cameras may not frame this scene (leave SCENE out to replay the recording's own)")
    print(msg, file=sys.stderr, flush=True)
    return msg


def scene_from_args(args, recording=None):
    """Scene named on the command line, else the recording's scene, else the default city."""
    from viewer.scene_io import check_seed
    from viewer.session import prepare_scene

    spec, size, seed = args.scene, args.scene_size, args.seed
    check_seed(seed)
    if spec is None and recording is not None:
        from viewer.recording import resolve_scene_spec

        rs = resolve_scene_spec(recording)
        spec = rs.spec
        size = size if size is not None else rs.size
        seed = rs.seed if rs.seed is not None else seed
    if args.scene_size is not None:  # a scene file has no size: it was ignored without a word
        from viewer.procedural import BUILTIN_SCENES

        if (spec or "city").partition(":")[0] not in BUILTIN_SCENES:
            raise RtwalkError(f"--scene-size applies to the built-in scenes ({', '.join(BUILTIN_SCENES)}), "
                              f"not to the scene file {spec}")
    if recording is not None and args.scene is not None:
        warn_other_scene(recording, args.scene)
    cameras = None
    if recording is not None:  # default lights for what the recording looks at, not only its first view
        from viewer.session import recording_cameras

        cameras = recording_cameras(recording)
    return prepare_scene(spec, scene_size=size, seed=seed, mirror_patterns=args.mirror, quiet=args.quiet,
                         bvh_builder=getattr(args, "bvh_builder", None), light_cameras=cameras)


# ---------------------------------------------------------------------------------------------
# checks that need no scene: run before anything is loaded


IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".webp", ".tga")


def check_positive(value: float | None, flag: str) -> None:
    """A finite number > 0 (None: not given)."""
    if value is not None and not (math.isfinite(value) and value > 0):
        raise RtwalkError(f"{flag} must be a finite number > 0 (got {value})")


def check_at_least(value: int | None, low: int, flag: str) -> None:
    if value is not None and value < low:
        raise RtwalkError(f"{flag} must be >= {low} (got {value})")


def _writable_dir(folder: Path, flag: str, given: str) -> None:
    """Prove a file can be written in `folder` without creating it: a failed or refused run must
    leave no empty folder behind (the writers create it when they write). The write test runs in
    the folder, or where it is missing, in its nearest existing ancestor."""
    where = "there" if Path(given) == folder else f"in {folder}"
    probe = folder.absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise RtwalkError(f"{flag} {given}: cannot write {where} ({probe} is not a folder)")
    try:
        with tempfile.NamedTemporaryFile(dir=probe, prefix=".rtwalk-write-check-"):
            pass
    except OSError as exc:
        raise RtwalkError(f"{flag} {given}: cannot write {where} ({exc.strerror or type(exc).__name__})") from None


def check_report_free(paths: list[Path], force: bool, flag: str = "--out") -> None:
    """Refuse to overwrite a report a finished (or interrupted) run left, unless --force: one line
    naming the first such file, before any work starts."""
    if force:
        return
    taken = [p for p in paths if p.exists()]
    if taken:
        more = f" (and {len(taken) - 1} more)" if len(taken) > 1 else ""
        raise RtwalkError(f"{taken[0]} exists{more}: pass --force to overwrite it, or choose another {flag}")


def add_force_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="overwrite reports already in the output folder (default: refuse)")


def check_image_output(path: str, flag: str = "-o/--output") -> Path:
    """An image file path with a supported extension whose folder can be written (the writer
    creates the folder)."""
    from PIL import Image

    out = Path(path).expanduser()
    if out.is_dir() or path.endswith(os.sep):
        raise RtwalkError(f"{flag} {path}: is a folder, expected an image file name (e.g. out/render.png)")
    Image.init()
    saveable = {e for e, fmt in Image.registered_extensions().items() if fmt in Image.SAVE}
    ext = out.suffix.lower()
    if ext not in IMAGE_EXTENSIONS or ext not in saveable:
        raise RtwalkError(f"{flag} {path}: unsupported image type '{ext or '(none)'}' "
                          f"(choose from {', '.join(e for e in IMAGE_EXTENSIONS if e in saveable)})")
    if out.exists() and not os.access(out, os.W_OK):
        raise RtwalkError(f"{flag} {path}: file is not writable")
    _writable_dir(out.parent, flag, path)
    return out


def check_output_dir(path: str | None, flag: str) -> Path | None:
    """A folder that exists or can be created, and can be written (None: not given)."""
    if path is None:
        return None
    out = Path(path).expanduser()
    if out.exists() and not out.is_dir():
        raise RtwalkError(f"{flag} {path}: exists and is not a folder")
    _writable_dir(out, flag, path)
    return out


def check_device(backend: str) -> None:
    """The backend's device can be opened (an OpenCL device for "cl" backends), before loading."""
    from viewer.backends import backend_info

    if backend_info(backend).device == "cl":
        from viewer.cl import cl_available

        reason = cl_available()
        if reason is not None:
            raise RtwalkError(f"--backend {backend} needs an OpenCL device: {reason}")


@dataclass
class RenderRequest:
    """What every rendering command (render, bench, view, demo) checks before loading a scene:
    the backend and its parameter text, the image size and the effect settings."""

    backend: str
    backend_options: dict[str, str]
    size: tuple[int, int]
    settings: object  # viewer.effects.EffectSettings


def request_from(args, device: bool = True) -> RenderRequest:
    """The fail-fast sequence shared by the commands: backend known and its parameters valid,
    size and effects parsed, and (device=True) the backend's device there; one RtwalkError line
    otherwise, before any scene work."""
    backend_options = backend_options_from(args)
    size = parse_size(args.size)
    settings = settings_from(args)
    if device:
        check_device(args.backend)
    return RenderRequest(args.backend, backend_options, size, settings)


def parse_sizes(text: str, scene: str = "city", flag: str = "--sizes") -> list[int]:
    """'1000000,5000000' -> sizes of a built-in scene, each in its range and fitting in memory."""
    from viewer.scene_io import check_builtin_size

    sizes = []
    for item in text.split(","):
        item = item.strip().replace("_", "")
        if not item.isdigit():
            raise RtwalkError(f"bad {flag} '{text}': expected a comma list of triangle counts, e.g. 1000000,5000000")
        sizes.append(check_builtin_size(scene, int(item), flag))
    return sizes

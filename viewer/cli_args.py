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
import tempfile
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

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (6, 7) or not np.all(np.isfinite(vals)):
        raise RtwalkError(f"bad --camera '{text}': expected eye_x,eye_y,eye_z,target_x,target_y,target_z[,fov_deg]")
    if np.allclose(vals[:3], vals[3:6]):
        raise RtwalkError(f"bad --camera '{text}': eye and target coincide")
    return Camera.look_at(vals[:3], vals[3:6], fov_y=vals[6] if len(vals) == 7 else 60.0)


def add_scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", default=None,
                   help="scene file (OBJ/PLY/GLB/STL/OFF) or built-in name (city, room, room-anim); default: city")
    p.add_argument("--scene-size", type=int, default=None, help="triangles for procedural scenes (city)")
    p.add_argument("--seed", type=int, default=1, help="seed for procedural scenes")
    p.add_argument("--mirror", action="append", default=[], metavar="PATTERN",
                   help="material name pattern made a mirror (repeatable, fnmatch, case-insensitive)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def add_effect_args(p: argparse.ArgumentParser, default: str) -> None:
    from viewer.backends import backend_names

    p.add_argument("--effects", default=default,
                   help="comma list of primary,shadows,soft,ao,diffuse,reflections (NAME:N = N samples), "
                        "'all' or 'none'")
    p.add_argument("--backend", default="glsl", help=f"tracing backend: {', '.join(backend_names())}")
    p.add_argument("--backend-params", default=None, metavar="KEY=VALUE,...",
                   help="parameters of the chosen --backend (also RTWALK_<BACKEND> in the environment), "
                        "e.g. --backend chcrt --backend-params visible_threshold=20,t_q=0.5")
    p.add_argument("--size", default="640x360", help="WIDTHxHEIGHT")
    p.add_argument("--perturb", type=float, default=36.0, help="per-pixel sample rotation, degrees")
    p.add_argument("--ao-length", type=float, default=0.05, help="AO ray length, fraction of the scene diagonal")
    p.add_argument("--exposure", type=float, default=1.0,
                   help="multiplies the linear radiance before tone mapping (finite, > 0; default 1)")
    p.add_argument("--chcrt", default=None, metavar="KEY=VALUE,...",
                   help="chcrt backend parameters (alias kept from before --backend-params), e.g. "
                        "'visible_threshold=20,t_q=0.5' (aggressive threshold in pixels, split rule, "
                        "min_tile_fraction, max_subtree_height, max_batch, max_multi, ...)")


def add_denoise_arg(p: argparse.ArgumentParser, default: str = "on") -> None:
    """--denoise on|off: filter the picture shown or saved (viewer.denoise); measurements stay raw."""
    p.add_argument("--denoise", choices=["on", "off"], default=default,
                   help="denoise the picture shown or saved, guided by the G-buffer's albedo and normal: "
                        "Open Image Denoise (pyoidn) for stills, replays and screenshots, an a-trous filter "
                        f"on the device for moving frames (default {default}; errors are measured raw)")


def add_progressive_args(p: argparse.ArgumentParser, help_flag: str, default: bool = False) -> None:
    """--progressive / --no-progressive and --frame-target-ms (viewer.progressive)."""
    p.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=default, help=help_flag)
    p.add_argument("--frame-target-ms", type=float, default=100.0,
                   help="progressive mode: frame time to keep while the camera moves, by lowering the render "
                        "scale (default 100)")


def check_backend(name: str) -> str:
    """The backend name if registered, else one line naming the choices (before any scene work)."""
    from viewer.backends import backend_class

    backend_class(name)  # raises RtwalkError for an unknown name
    return name


def backend_options_from(args) -> dict[str, str]:
    """Per-backend parameter text, {backend name: "key=value,..."}; checked here (unknown backend,
    unknown key, bad value) so bad input fails before any scene is loaded. `--backend-params`
    belongs to `--backend`; `--chcrt` is the older spelling of chcrt's parameters."""
    from viewer.backends import check_params

    backend = getattr(args, "backend", None)
    if backend is not None:
        check_backend(backend)
    options: dict[str, str] = {}
    text = getattr(args, "chcrt", None)
    if text:
        check_params("chcrt", text, "--chcrt")
        options["chcrt"] = text
    text = getattr(args, "backend_params", None)
    if text:
        check_params(backend or "glsl", text, "--backend-params")
        prev = options.get(backend or "glsl")
        options[backend or "glsl"] = f"{prev},{text}" if prev else text  # --backend-params wins
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


def scene_from_args(args, recording=None):
    """Scene named on the command line, else the recording's scene, else the default city."""
    from viewer.session import prepare_scene

    spec, size, seed = args.scene, args.scene_size, args.seed
    if spec is None and recording is not None:
        from viewer.recording import resolve_scene_spec

        rs = resolve_scene_spec(recording)
        spec = rs.spec
        size = size if size is not None else rs.size
        seed = rs.seed if rs.seed is not None else seed
    cameras = None
    if recording is not None:  # default lights for what the recording looks at, not only its first view
        from viewer.session import recording_cameras

        cameras = recording_cameras(recording)
    return prepare_scene(spec, scene_size=size, seed=seed, mirror_patterns=args.mirror, quiet=args.quiet,
                         light_cameras=cameras)


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
    """Create `folder` (and parents) and prove a file can be written there."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".rtwalk-write-check-"):
            pass
    except OSError as exc:
        where = "there" if Path(given) == folder else f"in {folder}"
        raise RtwalkError(f"{flag} {given}: cannot write {where} ({exc.strerror or type(exc).__name__})") from None


def check_image_output(path: str, flag: str = "-o/--output") -> Path:
    """An image file path with a supported extension whose folder can be written (created here)."""
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

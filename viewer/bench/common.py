"""What every benchmark shares: progress lines, the shared-scenes folder, count options.

Each benchmark module (see viewer/bench/__init__.py's BENCHMARKS) has `HELP` (one line),
`add_arguments(parser)` and `run(args) -> int`; these helpers keep them from re-writing the same
bits.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS, SHARED_SCENES

__all__ = ["SHARED_SCENES", "log", "parse_counts", "add_count_option", "study_scene"]


def log(args: argparse.Namespace, msg: str, prefix: str = "") -> None:
    """A progress line on stderr unless --quiet (stdout keeps the tables)."""
    if not getattr(args, "quiet", False):
        print(f"{prefix}: {msg}" if prefix else msg, file=sys.stderr, flush=True)


def parse_counts(text: str, option: str, lo: int = 1, hi: int = 200_000_000) -> list[int]:
    """'1M,10M,250000' -> [1000000, 10000000, 250000] (k/M suffixes); each in lo..hi."""
    out = []
    for part in [p.strip() for p in str(text).split(",") if p.strip()]:
        mult = {"k": 1_000, "m": 1_000_000}.get(part[-1].lower(), 1)
        try:
            v = int(float(part[:-1] if mult > 1 else part) * mult)
        except ValueError:
            raise RtwalkError(f"bad {option} '{text}': expected counts like 1M,10M") from None
        if not lo <= v <= hi:
            raise RtwalkError(f"bad {option} '{text}': each count must be in {lo:,}..{hi:,}")
        out.append(v)
    if not out:
        raise RtwalkError(f"bad {option} '{text}': no count given")
    return out


def add_count_option(p: argparse.ArgumentParser, name: str, default: str, what: str) -> None:
    """A count list option (`--triangles`, `--elements`) with `--sizes` kept as a hidden alias, so
    `--sizes` means image sizes everywhere it is documented."""
    dest = name.lstrip("-").replace("-", "_")
    p.add_argument(name, default=default, help=f"comma list of {what}, k/M suffixes allowed (default %(default)s)")
    p.add_argument("--sizes", dest=dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def study_scene(entry: tuple[str, str | None], scene_dir: str | Path, builtin_size: int | None = None):
    """(prepared scene, camera) of a study scene: `entry` = (file relative to `scene_dir`, or a
    built-in scene name; a recording in recordings/ or None). The camera is the recording's middle
    frame, else the scene's default camera. A missing file is one line (RtwalkError)."""
    from viewer.procedural import BUILTIN_SCENES
    from viewer.recording import load_recording
    from viewer.session import prepare_scene

    rel, rec = entry
    if rel in BUILTIN_SCENES:
        prep = prepare_scene(rel, scene_size=builtin_size, quiet=True) if builtin_size else \
            prepare_scene(rel, quiet=True)
    else:
        path = Path(scene_dir) / rel
        if not path.exists():
            raise RtwalkError(f"scene file {path} not found (--scene-dir)")
        prep = prepare_scene(str(path), quiet=True)
    cam = prep.scene.default_camera
    if rec and (RECORDINGS / rec).exists():
        r = load_recording(RECORDINGS / rec)
        cam = r.camera_for_frame(r.frame_count() // 2)
    return prep, cam

"""`rtwalk bench-light`: the share of directly lit pixels along the shipped recordings.

What `--view shadows` shows: per pixel, the fraction of point lights whose shadow ray is
unoccluded (black where no light reaches). A pixel counts as directly lit when that value is > 0;
background pixels (no surface) count as unlit. Rendered with the default tracing backend at a
small size, every Nth frame of each recording, with the scene and default lights exactly as
`rtwalk view --recording NAME` prepares them (lights chosen over the recording's cameras).
"""

from __future__ import annotations

import argparse
import sys

from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS


def recording_names() -> list[str]:
    return [p.stem for p in sorted(RECORDINGS.glob("*.json"))]


def lit_fractions(prepared, rec, ctx, size: tuple[int, int], every: int = 60,
                  backend: str | None = None) -> list[tuple[int, float]]:
    """(frame, share of pixels directly lit) for frames 0, every, 2*every, ... of `rec`."""
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer

    renderer = Renderer(ctx, prepared.scene, prepared.bvh, size, backend, parse_effects("shadows"))
    renderer.view = "shadows"
    out = []
    try:
        for n in range(0, rec.frame_count(), every):
            renderer.set_scene_time(rec.scene_time_for_frame(n))
            renderer.render(rec.camera_for_frame(n))
            img = renderer.read_image()
            out.append((n, float((img[..., 0] > 0).mean())))
    finally:
        renderer.release()
    return out


WRITES_REPORTS = False  # a table on stdout: no --force (it had one that did nothing)
HELP = "share of directly lit pixels (--view shadows) along the shipped recordings, every 60th frame"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recordings", default="all",
                   help=f"comma list of shipped recordings or 'all' ({', '.join(recording_names())})")
    p.add_argument("--size", default="160x90", help="WIDTHxHEIGHT of the measured frames")
    p.add_argument("--every", type=int, default=60, help="measure every Nth frame (default 60)")


def run(args) -> int:
    from viewer.cli_args import check_at_least, parse_choices, parse_size
    from viewer.gl.context import create_headless_context
    from viewer.paths import resolve_recording
    from viewer.recording import load_recording
    from viewer.session import prepare_scene_for_recording

    names = parse_choices(args.recordings, recording_names(), "--recordings")
    size = parse_size(args.size)
    check_at_least(args.every, 1, "--every")
    ctx = create_headless_context()
    print(f"{'recording':<16} {'lights':>6}  lit share of pixels at frames 0, {args.every}, ... "
          f"({size[0]}x{size[1]}, --view shadows)")
    worst = 1.0
    for name in names:
        rec = load_recording(resolve_recording(name))
        try:
            prepared = prepare_scene_for_recording(rec, quiet=True)
        except RtwalkError as exc:  # a study scene not present here: say so, go on
            print(f"{name:<16} skipped: {str(exc).splitlines()[0]}")
            continue
        rows = lit_fractions(prepared, rec, ctx, size, args.every)
        worst = min([worst] + [f for _, f in rows])
        cells = "  ".join(f"{n}:{f:.2f}" for n, f in rows)
        print(f"{name:<16} {len(prepared.scene.point_lights):>6}  {cells}", flush=True)
    print(f"lowest lit share: {worst:.2f}", file=sys.stderr)
    return 0

"""Where the repository's data lives: the one home of the folders scenes and recordings are looked up in.

The scenes shared between checkouts sit beside the repository (../shared/scenes, or
$RTWALK_SHARED/scenes); the recordings ship in recordings/. Scene loading, recordings, the CLI and the
benchmarks all resolve names here.
"""

from __future__ import annotations

import os
from pathlib import Path

from viewer.errors import RtwalkError

REPO_ROOT = Path(__file__).resolve().parents[1]
# RTWALK_SHARED: the shared folder elsewhere (a git worktree beside others, a CI cache)
SHARED_SCENES = Path(os.environ.get("RTWALK_SHARED") or REPO_ROOT.parent / "shared").expanduser() / "scenes"
RECORDINGS = REPO_ROOT / "recordings"


def resolve_recording(text: str) -> Path:
    """A recording by path, or by name in recordings/ (`city-near` or `city-near.json`)."""
    text = text.strip()
    given = Path(text).expanduser()
    for cand in (given, RECORDINGS / text, RECORDINGS / f"{text}.json"):
        if cand.is_file():
            return cand.resolve()
    names = ", ".join(p.stem for p in sorted(RECORDINGS.glob("*.json")))
    raise RtwalkError(f"unknown recording '{text}': no such file (shipped: {names})")

"""What every benchmark shares: progress lines, the shared-scenes folder, count options.

Each benchmark module (see viewer/bench/__init__.py's BENCHMARKS) has `HELP` (one line),
`add_arguments(parser)` and `run(args) -> int`; these helpers keep them from re-writing the same
bits.
"""

from __future__ import annotations

import argparse
import sys

from viewer.errors import RtwalkError
from viewer.paths import SHARED_SCENES

__all__ = ["SHARED_SCENES", "log", "parse_counts", "add_count_option"]


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

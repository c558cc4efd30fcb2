"""Benchmarks: a backend-neutral harness and the studies built on it, registered like backends.

BENCHMARKS maps a subcommand to a module with `HELP` (one line), `add_arguments(parser)` and
`run(args) -> int`; viewer/cli.py builds its subcommands from this table, so a new benchmark is a
module plus one line here. Shared pieces:
- harness: replay of a recording, consecutive frames, warm-up and reset, interleaved configurations
- common: progress lines, the shared-scenes folder, count options (`--triangles`, `--elements`)
- estimate: the up-front time estimate (a per-ray cost model per backend)
- report / plots: JSON + Markdown writing and the one plotting helper every report uses
- gl_micro: synthetic per-draw / per-query GL costs (the overhead study)

Import each name from its module; this package re-exports nothing.
"""

from __future__ import annotations

import importlib
from types import ModuleType

BENCHMARKS: dict[str, str] = {
    "bench": "viewer.bench.replay",
    "bench-bvh": "viewer.bench.bvh_build",
    "bench-bvh-trace": "viewer.bench.bvh_trace",
    "bench-grids": "viewer.bench.grids_far",
    "bench-chcrt": "viewer.bench.chcrt",
    "bench-pgrid": "viewer.bench.pgrid",
    "bench-voxelwalk": "viewer.bench.voxelwalk",
    "bench-trace": "viewer.bench.trace_vs_embree",
    "bench-cl": "viewer.bench.cl_primitives",
    "bench-voxels": "viewer.bench.voxels",
    "bench-denoise": "viewer.bench.denoise",
    "bench-light": "viewer.bench.lit",
    "bench-gbuffer": "viewer.bench.gbuffer",
}


def bench_module(command: str) -> ModuleType:
    """The module of a benchmark subcommand (HELP, add_arguments, run)."""
    return importlib.import_module(BENCHMARKS[command])

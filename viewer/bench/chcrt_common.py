"""Small helpers the CHC+RT studies share (chcrt.py, chcrt_coherence.py, chcrt_ooc.py import
them from here, so no study module imports another)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from viewer.bench.harness import RunResult, RunSpec
from viewer.bench.report import write_study

_CHC_PHASES: tuple[str, ...] = ()


def join_params(*texts: str | None) -> str:
    """chcrt parameter texts joined in order (a later key wins when parsed)."""
    return ",".join(t.strip().strip(",") for t in texts if t and t.strip().strip(","))


def table2_rows(b, study: str, configs: tuple[tuple[str, str, str | None], ...], config_wins: bool = False
                ) -> Iterator[tuple[Path, tuple[int, int], str, list[RunResult]]]:
    """Table 2's rows (recording x size x effect of the options `b.o`), each running `configs`
    ((label, backend, parameters)) interleaved frame by frame, with progress: yields (recording,
    size, effect, one RunResult per config). A chcrt config's parameters join --chcrt's: the
    config's win where `config_wins` (what the study compares), else --chcrt's (the user's)."""
    o = b.o
    b.progress(study, len(o.recordings) * len(o.sizes) * len(o.effects) * len(configs) * o.frames)
    try:
        for path in o.recordings:
            for size in o.sizes:
                for effect in o.effects:
                    specs = [RunSpec(label, effect, backend, params if backend != "chcrt" else
                                     join_params(o.chcrt, params) if config_wins else join_params(params, o.chcrt))
                             for label, backend, params in configs]
                    yield path, size, effect, b.run_many(path, size, specs)
    finally:
        b.done()


def save_png(path: Path, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(img).save(path)


def finish_study(o, study: str, report: dict, md: str) -> dict:
    """Write a study's JSON, Markdown (and the plot its caller drew) into the options' --out."""
    return write_study(o.out, study, report, md)


def chc_phases() -> tuple[str, ...]:
    """The chcrt backend's declared phase names (read once from the registry)."""
    global _CHC_PHASES
    if not _CHC_PHASES:
        from viewer.backends import backend_info

        _CHC_PHASES = tuple(backend_info("chcrt").phases)
    return _CHC_PHASES

"""Small helpers the CHC+RT studies share (chcrt.py, chcrt_coherence.py, chcrt_ooc.py import
them from here, so no study module imports another)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from viewer.bench.report import write_study

_CHC_PHASES: tuple[str, ...] = ()


def join_params(*texts: str | None) -> str:
    """chcrt parameter texts joined in order (a later key wins when parsed)."""
    return ",".join(t.strip().strip(",") for t in texts if t and t.strip().strip(","))


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

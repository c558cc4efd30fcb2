"""Report writing shared by every benchmark: JSON (all raw numbers) and Markdown tables."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def fmt(v: float | None, nd: int = 1) -> str:
    """A table cell: '-' for missing or non-finite values."""
    if v is None or not np.isfinite(v):
        return "-"
    return f"{v:,.{nd}f}"


def ratio(a: float, b: float) -> float:
    return a / b if b and np.isfinite(a) and np.isfinite(b) and b > 0 else float("nan")


def size_text(size: tuple[int, int]) -> str:
    return f"{size[0]}x{size[1]}"


def md_table(headers: list[str], rows: list[list[str]], align: str = "") -> str:
    """A Markdown table; `align` has one letter per column, "l" or "r" (right-aligned numbers)."""
    rule = ["---:" if a == "r" else "---" for a in align.ljust(len(headers), "l")]
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(rule) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def notes_md(notes: list[str]) -> list[str]:
    return (["", "Notes:"] + [f"- {n}" for n in notes]) if notes else []


def _jsonable(obj):
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path: Path, data: dict | list) -> None:
    """Written whole or not at all: a temporary file beside it, then renamed over it. Ctrl-C and
    SIGTERM raise KeyboardInterrupt wherever the run is (viewer.interrupt); one during a plain
    write left a cut JSON, a finished report lost or a partial one unreadable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1, default=_jsonable, allow_nan=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_study(out: Path, study: str, report: dict, md: str) -> dict:
    """`<study>.json` and `<study>.md` in `out` (the study draws `<study>.png` itself); the JSON says
    `"complete": true` unless the report says otherwise (an interrupted run: viewer.bench.partial)."""
    if isinstance(report, dict) and "complete" not in report:
        report = {"complete": True, **report}
    write_json(out / f"{study}.json", report)
    (out / f"{study}.md").write_text(md + "\n")
    return {"study": study, "json": out / f"{study}.json", "md": out / f"{study}.md",
            "png": out / f"{study}.png", "markdown": md}

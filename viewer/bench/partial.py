"""Interrupted benchmarks keep what they finished: one helper instead of a copy per module.

A multi-study or multi-row benchmark runs inside `keep_partial(what)`. It tells the helper about
its work as it goes: `finished(path)` for a report already written (a finished study),
`keep(writer)` for the rows so far (the writer writes the same report the end of the run writes,
given `complete`), `started(name)` for the study in hand. On Ctrl-C or SIGTERM (viewer.interrupt)
the finished reports are re-marked `"complete": false`, the writer writes the rows so far, and the
KeyboardInterrupt carries the one line cli._run prints (exit 130):
`interrupted ...: partial report PATH ("complete": false)`. With `defer=True` the first signal only
sets a flag that `check()` turns into that interrupt between configurations (a signal inside a
destructor would otherwise be dropped and the run go on; a second signal raises at once).
A plot or Markdown failure after the JSON is written never loses the JSON (`write_plots`).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from viewer.bench.report import write_json
from viewer.interrupt import Interrupt, deferred_interrupt


@dataclass
class PartialRun:
    """What a run has finished so far (see the module docstring)."""

    what: str
    files: list[Path] = field(default_factory=list)
    writer: Callable[[bool], object] | None = None
    current: str | None = None
    flag: Interrupt = field(default_factory=Interrupt)

    def finished(self, path: Path | str) -> None:
        self.files.append(Path(path))
        self.current = None

    def keep(self, writer: Callable[[bool], object]) -> None:
        """`writer(complete)` writes the report so far and returns its JSON path or paths (None:
        nothing yet)."""
        self.writer = writer

    def started(self, name: str) -> None:
        self.current = name

    def check(self) -> None:
        """Between configurations: the first signal of a deferred block stops here."""
        if self.flag.requested:
            raise KeyboardInterrupt

    def save_partial(self) -> list[Path]:
        """Write the rows so far, then re-mark every report of this run `"complete": false` (a
        writer may reuse the end-of-run study code, which says true); the JSON paths."""
        if self.writer is not None:
            try:
                got = self.writer(False)
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # noqa: BLE001 - the studies finished before must still be marked
                print(f"rtwalk: note: the rows in hand were not written ({type(exc).__name__}: {exc})",
                      file=sys.stderr)
                got = None
            for p in [got] if isinstance(got, (str, Path)) else (got or []):
                self.files.append(Path(p))
        paths = []
        for p in dict.fromkeys(self.files):
            try:
                data = json.loads(p.read_text())
            except (OSError, ValueError):
                continue
            if isinstance(data, dict):
                write_json(p, mark_complete(data, False))
            paths.append(p)
        return paths

    def line(self, paths: list[Path]) -> str:
        left = f" (study {self.current} left out)" if self.current else ""
        if not paths:
            return f"interrupted: {self.what}: nothing finished{left}, nothing written"
        names = ", ".join(str(p) for p in paths)
        return f"interrupted{left}: {self.what}: partial report {names} (\"complete\": false)"


def mark_complete(report: dict, complete: bool = True) -> dict:
    """`report` with `"complete"` first at its top level (the reader sees it before the rows)."""
    return {"complete": complete, **{k: v for k, v in report.items() if k != "complete"}}


def write_plots(*steps: Callable[[], object]) -> None:
    """Plots/Markdown after the JSON: a failure is one note line, never a lost report."""
    for step in steps:
        try:
            step()
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # noqa: BLE001 - any plotting error must not lose the JSON
            print(f"rtwalk: note: plot not written ({type(exc).__name__}: {exc})", file=sys.stderr)


@contextmanager
def keep_partial(what: str, defer: bool = False) -> Iterator[PartialRun]:
    """Run a benchmark's loop; an interrupt writes what it finished (see the module docstring)."""
    run = PartialRun(what)
    try:
        if defer:
            with deferred_interrupt() as flag:
                run.flag = flag
                yield run  # a signal after the last configuration: the run finished, complete
        else:
            yield run
    except KeyboardInterrupt:
        raise KeyboardInterrupt(run.line(run.save_partial())) from None

"""GPU timer queries per named phase, reused frame to frame (no per-frame allocation)."""

from __future__ import annotations

import time
from contextlib import contextmanager

import moderngl


class GpuProfiler:
    """Times phases with GL_TIME_ELAPSED queries; results are read once per frame.

    Phases with the same name in one frame are summed (e.g. 20 AO passes -> one 'trace:ao').
    Phases timed while `label` is set are also summed per label (`by_label`): the renderer sets
    it to the ray type around each backend call, so any backend's phases count as tracing time.
    """

    def __init__(self, ctx: moderngl.Context, enabled: bool = True):
        self.ctx = ctx
        self.enabled = enabled
        self._pool: list[moderngl.Query] = []
        self._used: list[tuple[str, moderngl.Query, str | None]] = []
        self._cpu: dict[str, float] = {}
        self.label: str | None = None  # set by the renderer around backend.trace (ray type)
        self.by_label: dict[str, float] = {}

    def begin_frame(self) -> None:
        self._used.clear()
        self._cpu.clear()

    @contextmanager
    def phase(self, name: str):
        t0 = time.perf_counter()
        if not self.enabled:
            yield
        else:
            idx = len(self._used)
            if idx >= len(self._pool):
                self._pool.append(self.ctx.query(time=True))
            q = self._pool[idx]
            self._used.append((name, q, self.label))
            with q:
                yield
        self._cpu[name] = self._cpu.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def end_frame(self) -> dict[str, float]:
        """GPU milliseconds per phase (waits for the queries)."""
        out: dict[str, float] = {}
        self.by_label = {}
        for name, q, label in self._used:
            ns = q.elapsed
            if ns >= 0xFFFFFFFF:  # result not available (llvmpipe on the first use): unknown, not huge
                ns = 0
            out[name] = out.get(name, 0.0) + ns / 1e6
            if label is not None:
                self.by_label[label] = self.by_label.get(label, 0.0) + ns / 1e6
        return out

    def cpu_ms(self) -> dict[str, float]:
        """CPU-side milliseconds per phase (Python + driver submission)."""
        return dict(self._cpu)

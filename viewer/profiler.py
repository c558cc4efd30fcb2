"""GPU timer queries per named phase, reused frame to frame (no per-frame allocation)."""

from __future__ import annotations

import time
from contextlib import contextmanager

import moderngl


class GpuProfiler:
    """Times phases with GL_TIME_ELAPSED queries; results are read once per frame.

    Phases with the same name in one frame are summed (e.g. 20 AO passes -> one 'trace:ao').
    """

    def __init__(self, ctx: moderngl.Context, enabled: bool = True):
        self.ctx = ctx
        self.enabled = enabled
        self._pool: list[moderngl.Query] = []
        self._used: list[tuple[str, moderngl.Query]] = []
        self._cpu: dict[str, float] = {}

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
            self._used.append((name, q))
            with q:
                yield
        self._cpu[name] = self._cpu.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def end_frame(self) -> dict[str, float]:
        """GPU milliseconds per phase (waits for the queries)."""
        out: dict[str, float] = {}
        for name, q in self._used:
            ns = q.elapsed
            if ns >= 0xFFFFFFFF:  # result not available (llvmpipe on the first use): unknown, not huge
                ns = 0
            out[name] = out.get(name, 0.0) + ns / 1e6
        return out

    def cpu_ms(self) -> dict[str, float]:
        """CPU-side milliseconds per phase (Python + driver submission)."""
        return dict(self._cpu)

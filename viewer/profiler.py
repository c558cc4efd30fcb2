"""Per-phase GPU times, reused frame to frame (no per-frame allocation).

Two ways to time a phase:
- "timer": GL_TIME_ELAPSED queries, read once per frame (asynchronous; right on real GPUs).
- "sync": glFinish before and after the phase, wall time in between. Used on Mesa llvmpipe,
  whose GL_TIME_ELAPSED is wrong for draws over many 64x64 bins: a one-draw phase reads about
  one bin per thread (`python3 -m viewer.timer_check`: a 512x512 full-screen draw read 11 ms
  against 308 ms of wall time, 256x256 0.14 of it, a 64x64 one right). Also,
  moderngl reads the result as 32 bits, so phases over 4.29 s saturate.
RTWALK_PHASE_TIMING=timer|sync overrides the automatic choice.

OpenCL work is timed by `cl_phase(name, queue)`: the CL queue is finished at the end and the wall
time recorded (in "sync" mode GL and the queue are finished first, as for GL phases), so CL phases
sit in the same tables, plots and panel as GL phases and count towards `by_label`. `record(name,
ms)` adds a phase measured elsewhere (e.g. from CL event profiling).
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager

import moderngl

from viewer import iostats
from viewer.gl import io as glio

TIMING_METHODS = ("timer", "sync")
_SATURATED_NS = 0xFFFFFFFF  # moderngl's 32-bit read: the result is >= 4.29 s, or not available


def choose_timing(ctx: moderngl.Context) -> str:
    """The phase timing method for this context: RTWALK_PHASE_TIMING, else sync on llvmpipe."""
    env = os.environ.get("RTWALK_PHASE_TIMING", "").strip().lower()
    if env in TIMING_METHODS:
        return env
    renderer = str(ctx.info.get("GL_RENDERER", "")).lower()
    return "sync" if ("llvmpipe" in renderer or "softpipe" in renderer) else "timer"


def clfinish(queue) -> None:
    """queue.finish() as one counted host sync (viewer.cl.io.finish without importing viewer.cl)."""
    with iostats.timed_sync():
        queue.finish()


class GpuProfiler:
    """Times named phases; same-name phases of one frame are summed (20 AO passes -> 'trace:ao').

    Phases timed while `label` is set are also summed per label (`by_label`): the renderer sets
    it to the ray type around each backend call, so any backend's phases count as tracing time.
    `saturated` counts timer results that could not be read (>= 4.29 s or unavailable); those
    phases are charged their CPU time instead, which includes waiting for the GPU.
    """

    def __init__(self, ctx: moderngl.Context, enabled: bool = True, method: str | None = None):
        self.ctx = ctx
        self.enabled = enabled
        self.method = method or choose_timing(ctx)
        if self.method not in TIMING_METHODS:
            raise ValueError(f"phase timing must be one of {', '.join(TIMING_METHODS)}, not {self.method!r}")
        self._pool: list[moderngl.Query] = []
        self._used: list[tuple[str, moderngl.Query | float, str | None, float]] = []
        self._cpu: dict[str, float] = {}
        self.label: str | None = None  # set by the renderer around backend.trace (ray type)
        self.by_label: dict[str, float] = {}
        self.saturated = 0
        self._queries = 0  # timer queries used this frame
        self._timer_open = False  # a GL_TIME_ELAPSED query is active (phases nest; queries cannot)
        # per phase this frame: CL launches and host syncs issued inside it (viewer.iostats deltas;
        # the studies report them beside the phase's milliseconds)
        self.io_by_phase: dict[str, dict[str, int]] = {}
        # CL phases timed by queue markers, read after one finish at end_frame (no host sync per
        # phase): set by the renderer around a device-resident frame's passes
        self.cl_deferred = False

    def begin_frame(self) -> None:
        self.io_by_phase = {}
        self._queries = 0
        self._used.clear()
        self._cpu.clear()
        self.saturated = 0

    @contextmanager
    def _io(self, name: str):
        """Adds the launches and host syncs issued inside the block to io_by_phase[name]."""
        launches0, syncs0 = iostats.launches_and_syncs()
        try:
            yield
        finally:
            launches1, syncs1 = iostats.launches_and_syncs()
            d = self.io_by_phase.setdefault(name, {"cl_launches": 0, "host_syncs": 0})
            d["cl_launches"] += launches1 - launches0
            d["host_syncs"] += syncs1 - syncs0

    @contextmanager
    def phase(self, name: str):
        with self._io(name):
            with self._phase(name):
                yield

    @contextmanager
    def cl_phase(self, name: str, queue):
        """Time OpenCL work enqueued on `queue` (see _cl_phase), counting its launches and syncs."""
        with self._io(name):
            with self._cl_phase(name, queue):
                yield

    @contextmanager
    def _phase(self, name: str):
        if not self.enabled:
            t0 = time.perf_counter()
            yield
        elif self.method == "sync":
            glio.finish(self.ctx)  # work issued before the phase is not charged to it
            t0 = time.perf_counter()
            yield
            glio.finish(self.ctx)
            self._used.append((name, (time.perf_counter() - t0) * 1e3, self.label, 0.0))
        elif self._timer_open:
            # GL allows one active GL_TIME_ELAPSED query (a nested glBeginQuery is
            # GL_INVALID_OPERATION, and reading that query then fails on NVIDIA): an inner phase is
            # charged its CPU time and stays inside the outer phase's GPU time
            t0 = time.perf_counter()
            yield
            self._used.append((name, (time.perf_counter() - t0) * 1e3, self.label, 0.0))
        else:
            t0 = time.perf_counter()
            idx = self._queries  # CL and recorded phases take no query
            self._queries += 1
            if idx >= len(self._pool):
                self._pool.append(self.ctx.query(time=True))
            q = self._pool[idx]
            iostats.gl_query()
            self._timer_open = True
            try:
                with q:
                    yield
            finally:
                self._timer_open = False
            self._used.append((name, q, self.label, (time.perf_counter() - t0) * 1e3))
        self._cpu[name] = self._cpu.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    @contextmanager
    def _cl_phase(self, name: str, queue):
        """Time OpenCL work enqueued on `queue` (a pyopencl.CommandQueue) as phase `name`.

        The queue is finished at the end, so the phase holds the kernels' run time even though
        enqueueing returns at once. In "sync" mode, GL work and CL work issued before the phase
        are finished first (not charged to it); in "timer" mode the queue is still drained first."""
        if self.enabled and self.cl_deferred:
            from viewer.cl import io as clio

            t0 = time.perf_counter()
            m0 = clio.marker(queue)
            yield
            cpu = (time.perf_counter() - t0) * 1e3
            self._used.append((name, (m0, clio.marker(queue), queue), self.label, cpu))
            self._cpu[name] = self._cpu.get(name, 0.0) + cpu
            return
        if self.enabled:
            if self.method == "sync":
                glio.finish(self.ctx)
            clfinish(queue)
        t0 = time.perf_counter()
        yield
        if self.enabled:
            clfinish(queue)
            ms = (time.perf_counter() - t0) * 1e3
            self._used.append((name, ms, self.label, 0.0))
        self._cpu[name] = self._cpu.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def record(self, name: str, ms: float, cpu_ms: float | None = None) -> None:
        """Add `ms` to phase `name` for this frame (summed like timed phases, and into by_label
        under the current label); `cpu_ms` also goes into cpu_ms() when given."""
        if self.enabled:
            self._used.append((name, float(ms), self.label, 0.0))
        if cpu_ms is not None:
            self._cpu[name] = self._cpu.get(name, 0.0) + float(cpu_ms)

    def end_frame(self) -> dict[str, float]:
        """GPU milliseconds per phase (waits for the queries)."""
        out: dict[str, float] = {}
        self.by_label = {}
        if any(not isinstance(q, (float, tuple)) for _, q, _, _ in self._used):
            iostats.sync()  # the first result read waits for the frame's GL work
        queues = {id(q[2]): q[2] for _, q, _, _ in self._used if isinstance(q, tuple)}
        for queue in queues.values():  # deferred CL phases: one wait, then the markers' times
            clfinish(queue)
        for name, q, label, cpu_ms in self._used:
            if isinstance(q, float):
                ms = q
            elif isinstance(q, tuple):
                ms = self._marker_ms(q[0], q[1], cpu_ms)
            else:
                ns = q.elapsed
                if ns >= _SATURATED_NS:
                    self.saturated += 1
                    ms = cpu_ms
                else:
                    ms = ns / 1e6
            out[name] = out.get(name, 0.0) + ms
            if label is not None:
                self.by_label[label] = self.by_label.get(label, 0.0) + ms
        return out

    def _marker_ms(self, first, last, cpu_ms: float) -> float:
        """Milliseconds between two CL markers' ends. A driver may keep no timestamps for markers
        (CL_PROFILING_INFO_NOT_AVAILABLE before OpenCL 3.0, or zeros): then the phase is charged its
        CPU time and counted in `saturated`, as an unreadable timer query is."""
        try:
            t0, t1 = int(first.profile.end), int(last.profile.end)
        except Exception:  # pyopencl.RuntimeError: profiling info not available
            t0 = t1 = 0
        if t0 <= 0 or t1 <= 0:
            self.saturated += 1
            return cpu_ms
        return max(0.0, (t1 - t0) / 1e6)

    def cpu_ms(self) -> dict[str, float]:
        """CPU-side milliseconds per phase (Python + driver submission)."""
        return dict(self._cpu)

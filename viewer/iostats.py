"""Per-frame counts of what crosses between host and device, and of what the host submits.

These counts are the same on every device (llvmpipe and PoCL here, NVIDIA GL/CL elsewhere), so
CI can check a GPU-shaped frame where no GPU is: bytes to and from the device, host
synchronisations (a finish, a blocking read or map, a query result waited on), OpenCL kernel
launches, GL draws (a draw or dispatch call) and GL queries begun.

Every place that does one of these calls the matching function here; the renderer brackets a
frame with `begin_frame()` / `end_frame()` and stores the result as `FrameReport.io` (bench JSON:
`frames[i].io`). The counters are process-global (one GL context and one CL queue per process)
and cost an integer add each.

API:
  to_device(nbytes)   host -> device bytes (texture/buffer upload, CL write or write-map)
  to_host(nbytes)     device -> host bytes (texture/buffer read, CL read or read-map)
  sync(n=1)           the host waited for the device (finish, blocking copy/map, query result)
  cl_launch(n=1)      OpenCL kernel enqueues (an NDRange or a task)
  gl_draw(n=1)        GL draw / dispatch calls (one multi-draw-indirect is one)
  gl_query(n=1)       GL queries begun (occlusion, timer)
  begin_frame()       zero the counts; end_frame() -> IoCounts of the frame (also `last`)
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields, replace


@dataclass
class IoCounts:
    """What one frame moved and submitted (see the module docstring for what each field counts)."""

    bytes_to_device: int = 0
    bytes_to_host: int = 0
    host_syncs: int = 0
    cl_launches: int = 0
    gl_draws: int = 0
    gl_queries: int = 0
    python_ms: float = 0.0  # wall time of the frame minus the time spent in counted host syncs

    def as_dict(self) -> dict:
        return asdict(self)

    def __add__(self, other: IoCounts) -> IoCounts:
        return IoCounts(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})


_counts = IoCounts()
_frame_t0 = time.perf_counter()
_sync_s = 0.0
last = IoCounts()


def to_device(nbytes: int) -> None:
    _counts.bytes_to_device += int(nbytes)


def to_host(nbytes: int) -> None:
    _counts.bytes_to_host += int(nbytes)


def sync(n: int = 1) -> None:
    _counts.host_syncs += int(n)


def cl_launch(n: int = 1) -> None:
    _counts.cl_launches += int(n)


def gl_draw(n: int = 1) -> None:
    _counts.gl_draws += int(n)


def gl_query(n: int = 1) -> None:
    _counts.gl_queries += int(n)


class timed_sync:
    """`with iostats.timed_sync(): queue.finish()` counts one host sync and keeps its wait out of
    python_ms (the host's own time per frame)."""

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, *exc) -> None:
        global _sync_s
        _sync_s += time.perf_counter() - self.t0
        sync()


def current() -> IoCounts:
    """The counts so far in this frame (a copy; every field is a number, so a shallow one: the
    profiler takes one before and after every phase, and asdict's deep copy cost 0.05 ms each)."""
    return replace(_counts)


def launches_and_syncs() -> tuple[int, int]:
    """(cl_launches, host_syncs) so far in this frame: what the profiler takes before and after
    every phase (a chcrt frame has a dozen phases a pass), without copying the counts."""
    return _counts.cl_launches, _counts.host_syncs


def begin_frame() -> None:
    global _counts, _frame_t0, _sync_s
    _counts = IoCounts()
    _frame_t0 = time.perf_counter()
    _sync_s = 0.0


def end_frame() -> IoCounts:
    """The frame's counts; python_ms = frame wall time minus the waits counted by timed_sync."""
    global last
    out = current()
    out.python_ms = max(0.0, (time.perf_counter() - _frame_t0 - _sync_s) * 1e3)
    last = out
    return out

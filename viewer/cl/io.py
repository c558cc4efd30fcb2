"""Counted OpenCL launches and transfers: the one place rtwalk calls pyopencl's Kernel,
enqueue_copy and enqueue_map_buffer (tests/test_iostats.py fails on any other caller in viewer/),
so every launch, byte and host wait lands in viewer.iostats.

  kernel(prog, name) -> Kernel    a pyopencl.Kernel whose call `k(queue, gsize, lsize, *args)`
                                  counts one launch (other attributes pass through)
  kernels(prog, names) -> dict    {name: kernel(prog, name)}
  launch(k, queue, gsize, lsize, *args)   the same for a kernel held elsewhere
  copy(queue, dest, src, **kw)    enqueue_copy: NumPy -> Buffer counts to_device, Buffer -> NumPy
                                  to_host (bytes of the smaller side, or byte_count), Buffer ->
                                  Buffer nothing; a blocking host copy (the default) also a sync
  map_buffer(queue, buf, flags, offset, shape, dtype, is_blocking=True)   enqueue_map_buffer:
                                  a READ map counts to_host, a write map to_device, blocking a sync
  upload(ctx, array, flags, what, use_host) -> Buffer   a new buffer initialised from `array`
                                  (COPY_HOST_PTR, or USE_HOST_PTR: the array's own memory):
                                  counts to_device
  finish(queue)                   queue.finish() as one timed host sync

A non-blocking host copy's pyopencl event waits for the copy when it is dropped (it guards the
host array), which would make every "asynchronous" write a hidden, uncounted host sync. copy()
therefore keeps those events (and so their host arrays) per queue until the queue next waits
for the host (a blocking copy or map, or finish()), when they are complete and free to drop.

A staged GL <-> CL hop (a GL texture read straight into a mapped CL buffer, or written from one)
crosses once and is counted once, by the map (viewer/cl/transfer.py).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from viewer import iostats


class Kernel:
    """A pyopencl.Kernel that counts its launches."""

    __slots__ = ("kernel", "name", "_max_group")

    def __init__(self, kernel: Any, name: str):
        self.kernel = kernel
        self.name = name
        self._max_group: int | None = None

    def __call__(self, queue: Any, gsize: Any, lsize: Any, *args: Any, **kw: Any) -> Any:
        check_ndrange(self.name, gsize, lsize)
        if lsize is not None:
            self._check_group(queue, math.prod(int(x) for x in lsize))
        iostats.cl_launch()
        return self.kernel(queue, gsize, lsize, *args, **kw)

    def _check_group(self, queue: Any, items: int) -> None:
        """RtwalkError (one line) when the device cannot run this kernel with `items` work-items
        per group (CL_KERNEL_WORK_GROUP_SIZE: a GPU lowers it for kernels that use many registers;
        PoCL allows 4096), instead of pyopencl's INVALID_WORK_GROUP_SIZE at the launch."""
        if self._max_group is None:
            cl = _cl()
            self._max_group = int(self.kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE,
                                                                  queue.device))
        if items > self._max_group:
            from viewer.errors import RtwalkError

            raise RtwalkError(f"OpenCL kernel {self.name}: {items} work-items per group, the device allows "
                              f"{self._max_group} for it (CL_KERNEL_WORK_GROUP_SIZE); choose a smaller chunk")

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.kernel, attr)


def check_ndrange(name: str, gsize: Any, lsize: Any) -> None:
    """A global size that is a multiple of the local size in every dimension: OpenCL C 1.2 kernels
    (what NVIDIA's driver compiles) have uniform work-groups only, CL_INVALID_WORK_GROUP_SIZE
    otherwise, while PoCL (non-uniform work-groups) runs the remainder. A programming error: raised
    on every device, so the CPU tests catch it."""
    if lsize is None:
        return
    g, loc = tuple(int(x) for x in gsize), tuple(int(x) for x in lsize)
    if len(g) != len(loc) or any(b <= 0 or a % b for a, b in zip(g, loc, strict=False)):
        raise ValueError(f"OpenCL kernel {name}: global size {g} is not a multiple of the local size {loc}")


def _cl():
    from viewer.cl.context import cl_context

    return cl_context().cl


def kernel(prog: Any, name: str) -> Kernel:
    return Kernel(_cl().Kernel(prog, name), name)


def kernels(prog: Any, names) -> dict[str, Kernel]:
    return {n: kernel(prog, n) for n in names}


def launch(k: Any, queue: Any, gsize: Any, lsize: Any, *args: Any, **kw: Any) -> Any:
    if isinstance(k, Kernel):
        return k(queue, gsize, lsize, *args, **kw)
    check_ndrange(getattr(k, "function_name", "?"), gsize, lsize)
    iostats.cl_launch()
    return k(queue, gsize, lsize, *args, **kw)


def _is_host(x: Any) -> bool:
    return isinstance(x, (np.ndarray, bytes, bytearray, memoryview))


def _nbytes(x: Any) -> int:
    if isinstance(x, np.ndarray):
        return int(x.nbytes)
    if isinstance(x, memoryview):
        return int(x.nbytes)
    if isinstance(x, (bytes, bytearray)):
        return len(x)
    return int(getattr(x, "size", 0))


_in_flight: dict[int, list[Any]] = {}  # id(queue) -> events of non-blocking host copies not yet waited for
MAX_IN_FLIGHT = 4096  # past this many, the queue is finished (one counted sync) to bound them


def _completed(queue: Any) -> None:
    """The queue has just waited for the host: every earlier command is done, so the kept events
    (an in-order queue) are complete and dropping them waits for nothing."""
    _in_flight.pop(id(queue), None)


def copy(queue: Any, dest: Any, src: Any, **kw: Any) -> Any:
    """pyopencl.enqueue_copy, counted (see the module docstring)."""
    cl = _cl()
    host_dst, host_src = _is_host(dest), _is_host(src)
    if host_dst != host_src:
        n = kw.get("byte_count") or (_nbytes(dest) if host_dst else _nbytes(src))
        (iostats.to_host if host_dst else iostats.to_device)(n)
        if kw.get("is_blocking", True):
            with iostats.timed_sync():
                event = cl.enqueue_copy(queue, dest, src, **kw)
            _completed(queue)
            return event
        event = cl.enqueue_copy(queue, dest, src, **kw)
        kept = _in_flight.setdefault(id(queue), [])
        kept.append(event)
        if len(kept) > MAX_IN_FLIGHT:
            finish(queue)
        return event
    return cl.enqueue_copy(queue, dest, src, **kw)


def map_buffer(queue: Any, buf: Any, flags: Any, offset: int, shape: Any, dtype: Any,
               is_blocking: bool = True) -> tuple[np.ndarray, Any]:
    """pyopencl.enqueue_map_buffer, counted: READ maps to_host, write maps to_device."""
    cl = _cl()
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    (iostats.to_host if flags & cl.map_flags.READ else iostats.to_device)(nbytes)
    if is_blocking:
        with iostats.timed_sync():
            mapped = cl.enqueue_map_buffer(queue, buf, flags, offset, shape, dtype, is_blocking=True)
        _completed(queue)
        return mapped
    return cl.enqueue_map_buffer(queue, buf, flags, offset, shape, dtype, is_blocking=False)


def upload(ctx: Any, array: np.ndarray, flags: Any = None, what: str = "buffer", use_host: bool = False) -> Any:
    """A new CL buffer holding `array` (COPY_HOST_PTR; default READ_ONLY), counted to_device, after
    the device's allocation limits are checked (viewer.cl.limits: one line, never a raw error).
    use_host: the buffer uses the array's memory (USE_HOST_PTR, no copy on a CPU device); the
    caller keeps the array alive and unchanged until the device is done with the buffer."""
    from viewer.cl.limits import new_buffer

    a = np.ascontiguousarray(array)
    return new_buffer(ctx, ctx.cl.mem_flags.READ_ONLY if flags is None else flags, a.nbytes, what, hostbuf=a,
                      use_host=use_host)


def read_rows(queue: Any, buf: Any, rows, row_shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """Rows `rows` of a buffer of fixed-size rows (e.g. float4 rays): one small copy each and one
    wait; only those bytes cross (a backend that needs a few rays on the host)."""
    dt = np.dtype(dtype)
    rb = int(np.prod(row_shape)) * dt.itemsize
    out = np.empty((len(rows), *row_shape), dt)
    for k, r in enumerate(rows):
        copy(queue, out[k], buf, src_offset=int(r) * rb, is_blocking=False)
    finish(queue)
    return out


def read_strided(queue: Any, buf: Any, step: int, count: int, row_shape: tuple[int, ...], dtype: Any,
                 is_blocking: bool = True) -> np.ndarray:
    """Rows 0, step, 2 * step, ... (`count` of them) in one rectangular copy: a strided sample
    of a buffer of fixed-size rows without reading the rest (is_blocking=False: valid after a
    later wait on the queue, e.g. the next blocking read)."""
    dt = np.dtype(dtype)
    rb = int(np.prod(row_shape)) * dt.itemsize
    out = np.empty((int(count), *row_shape), dt)
    if count:
        copy(queue, out, buf, buffer_origin=(0, 0), host_origin=(0, 0), region=(rb, int(count)),
             buffer_pitches=(int(step) * rb,), host_pitches=(rb,), is_blocking=is_blocking)
    return out


def marker(queue: Any) -> Any:
    """An event that completes when the queue's earlier commands have (deferred phase timing)."""
    return _cl().enqueue_marker(queue)


def finish(queue: Any) -> None:
    """queue.finish() counted as one host sync (its wait kept out of python_ms)."""
    with iostats.timed_sync():
        queue.finish()
    _completed(queue)

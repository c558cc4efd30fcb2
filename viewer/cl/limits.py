"""Device memory limits, checked before a large OpenCL allocation (never a raw pyopencl error).

An OpenCL device refuses a buffer above CL_DEVICE_MAX_MEM_ALLOC_SIZE (INVALID_BUFFER_SIZE at
creation) and fails later, at first use, when all buffers together outgrow its global memory
(MEM_OBJECT_ALLOCATION_FAILURE). PoCL on the CPU sizes both from the memory free when the
process starts (POCL_MEMORY_LIMIT=<GiB> caps it), so the same build can fit on one run and not
on the next. Builders therefore ask here first:

  check_alloc(nbytes, what, ctx)  one buffer: RtwalkError with one line naming it, the MiB it
                                  needs and the MiB the device allows, when it cannot fit
  budget(ctx)                     bytes one acceleration structure build may use in all (a share
                                  of global memory: other backends and the ray stages live beside
                                  it); builders coarsen or stop to stay within it
  new_buffer(ctx, flags, nbytes, what, hostbuf, use_host)  cl.Buffer after check_alloc (a
                                  hostbuf's bytes count as host -> device traffic, viewer.iostats;
                                  use_host: USE_HOST_PTR, the host array's memory itself)

RTWALK_CL_MAX_ALLOC_MIB and RTWALK_CL_GLOBAL_MIB lower the device's figures (never raise them):
tests simulate a small device with them instead of allocating gigabytes. RTWALK_CL_LOCAL_KIB
lowers the local memory per work-group (`local_mem`): RTWALK_CL_LOCAL_KIB=48 runs the kernels
sized for NVIDIA's 48 KiB here (PoCL offers megabytes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from viewer import iostats
from viewer.errors import RtwalkError

MAX_ALLOC_ENV = "RTWALK_CL_MAX_ALLOC_MIB"
GLOBAL_ENV = "RTWALK_CL_GLOBAL_MIB"
LOCAL_ENV = "RTWALK_CL_LOCAL_KIB"
BUDGET_SHARE = 0.25  # of global memory, for one structure build (several backends may coexist)
MIB = 2**20


@dataclass(frozen=True)
class DeviceLimits:
    """Bytes: the largest single buffer and all of the device's global memory."""

    max_alloc: int
    global_mem: int

    @property
    def budget(self) -> int:
        """Bytes one structure build may use in all."""
        return int(self.global_mem * BUDGET_SHARE)


def _env_bytes(name: str, unit: int = MIB, unit_name: str = "MiB") -> int | None:
    text = os.environ.get(name, "").strip()
    if not text:
        return None
    try:
        v = float(text)
    except ValueError:
        raise RtwalkError(f"{name}={text!r}: not a number of {unit_name}") from None
    if not v > 0:
        raise RtwalkError(f"{name}={text!r}: must be > 0 {unit_name}")
    return int(v * unit)


def _env_mib(name: str) -> int | None:
    return _env_bytes(name)


def device_limits(ctx: Any = None) -> DeviceLimits:
    """The limits of ctx's device (default: the shared context), lowered by the env overrides."""
    if ctx is None:
        from viewer.cl.context import cl_context

        ctx = cl_context()
    dev = ctx.device
    max_alloc, global_mem = int(dev.max_mem_alloc_size), int(dev.global_mem_size)
    env_alloc, env_global = _env_mib(MAX_ALLOC_ENV), _env_mib(GLOBAL_ENV)
    if env_alloc is not None:
        max_alloc = min(max_alloc, env_alloc)
    if env_global is not None:
        global_mem = min(global_mem, env_global)
    return DeviceLimits(min(max_alloc, global_mem), global_mem)


def local_mem(ctx: Any) -> int:
    """Bytes of local memory a work-group may use (CL_DEVICE_LOCAL_MEM_SIZE: NVIDIA 48 KiB),
    lowered by RTWALK_CL_LOCAL_KIB."""
    size = int(ctx.device.local_mem_size)
    env = _env_bytes(LOCAL_ENV, 1024, "KiB")
    return size if env is None else min(size, env)


def budget(ctx: Any = None) -> int:
    """Bytes one acceleration structure build may use in all (see DeviceLimits.budget)."""
    return device_limits(ctx).budget


def pair_cap(ctx: Any, bytes_per_pair: int) -> int:
    """Most (key, value) pairs a sort-based build may list: its per-pair buffers within the
    budget and each 4-byte-per-pair buffer within one allocation."""
    lim = device_limits(ctx)
    return int(min(lim.budget // max(1, bytes_per_pair), lim.max_alloc // 4))


def mib(nbytes: float) -> str:
    return f"{nbytes / MIB:,.1f}"


def check_alloc(nbytes: int, what: str, ctx: Any = None, limits: DeviceLimits | None = None) -> None:
    """RtwalkError (one line) when one buffer of nbytes cannot exist on the device."""
    lim = limits or device_limits(ctx)
    if nbytes > lim.max_alloc:
        raise RtwalkError(f"{what} needs {mib(nbytes)} MiB in one buffer, the OpenCL device allows "
                          f"{mib(lim.max_alloc)} MiB per buffer ({mib(lim.global_mem)} MiB in all)")
    if nbytes > lim.global_mem:
        raise RtwalkError(f"{what} needs {mib(nbytes)} MiB, the OpenCL device has {mib(lim.global_mem)} MiB")


def check_total(nbytes: int, what: str, ctx: Any = None, limits: DeviceLimits | None = None) -> None:
    """RtwalkError (one line) when a structure's buffers together exceed the build budget."""
    lim = limits or device_limits(ctx)
    if nbytes > lim.budget:
        raise RtwalkError(f"{what} needs {mib(nbytes)} MiB of device memory, at most {mib(lim.budget)} MiB "
                          f"may go to one structure ({BUDGET_SHARE:.0%} of the OpenCL device's "
                          f"{mib(lim.global_mem)} MiB)")


def new_buffer(ctx: Any, flags: Any, nbytes: int, what: str, hostbuf: Any = None, use_host: bool = False) -> Any:
    """A pyopencl Buffer of nbytes (or holding hostbuf) after check_alloc; an allocation the
    device still refuses becomes one RtwalkError line too. use_host: the buffer uses hostbuf's
    memory (USE_HOST_PTR: no copy on a device that shares the host's memory, such as PoCL; hostbuf
    must outlive the buffer and not change while the device reads it). A device with its own
    memory (a discrete GPU) gets a copy instead: its kernels would otherwise read across the bus."""
    nbytes = int(hostbuf.nbytes if hostbuf is not None else nbytes)
    check_alloc(nbytes, what, ctx)
    cl = ctx.cl
    try:
        if hostbuf is not None:
            iostats.to_device(nbytes)  # the host array crosses once, at creation
            shared = use_host and bool(ctx.device.host_unified_memory)
            how = cl.mem_flags.USE_HOST_PTR if shared else cl.mem_flags.COPY_HOST_PTR
            return cl.Buffer(ctx.context, flags | how, hostbuf=hostbuf)
        return cl.Buffer(ctx.context, flags, max(16, nbytes))
    except cl.Error as e:
        raise RtwalkError(f"{what}: the OpenCL device cannot allocate {mib(nbytes)} MiB "
                          f"({str(e).splitlines()[0]})") from None

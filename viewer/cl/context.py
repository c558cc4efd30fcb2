"""The OpenCL context and in-order queue every CL backend and primitive shares.

The device comes from RTWALK_CL_DEVICE (an index into all devices of all platforms, in platform
order, or a case-insensitive substring of "platform-name device-name"), else the first GPU, else
the first device (a machine with NVIDIA's driver and PoCL lists both, in an order the ICD loader
picks: the GPU must not lose to the CPU by the order of files in /etc/OpenCL/vendors).
pyopencl is imported only here and only on first use, so GL backends work without it; a machine
without an OpenCL platform gets one RtwalkError line naming the package to install.
PoCL compiles kernels per work-group size at first enqueue and keeps the result in
POCL_CACHE_DIR: `ensure_pocl_cache_dir()` points it at a writable folder before PoCL loads.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from viewer.errors import RtwalkError

DEVICE_ENV = "RTWALK_CL_DEVICE"
NO_DEVICE = "no OpenCL device (install pocl-opencl-icd)"

_context: ClContext | None = None


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def ensure_pocl_cache_dir() -> str:
    """Set POCL_CACHE_DIR to a writable folder unless the user set one; returns the folder.

    Default ~/.cache/rtwalk/pocl ($XDG_CACHE_HOME honoured), else a per-user temporary folder
    (PoCL's own default fails silently when $HOME is read-only and recompiles every run)."""
    current = os.environ.get("POCL_CACHE_DIR")
    if current:
        return current
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    for cand in (base / "rtwalk" / "pocl", Path(tempfile.gettempdir()) / f"rtwalk-pocl-{os.getuid()}"):
        if _writable_dir(cand):
            os.environ["POCL_CACHE_DIR"] = str(cand)
            return str(cand)
    return ""


@dataclass
class ClContext:
    """One device, its context and an in-order queue with profiling enabled (events carry times)."""

    cl: Any  # the pyopencl module
    context: Any  # pyopencl.Context
    queue: Any  # pyopencl.CommandQueue
    device: Any  # pyopencl.Device

    @property
    def name(self) -> str:
        return f"{self.device.platform.name.strip()} / {self.device.name.strip()}"

    @property
    def compute_units(self) -> int:
        return int(self.device.max_compute_units)

    @property
    def is_cpu(self) -> bool:
        return bool(self.device.type & self.cl.device_type.CPU)

    @property
    def sub_buffer_align(self) -> int:
        """Bytes a sub-buffer's origin must be a multiple of (CL_DEVICE_MEM_BASE_ADDR_ALIGN is in
        bits: PoCL here 1024, NVIDIA 4096), at least 128; a misaligned origin is
        CL_MISALIGNED_SUB_BUFFER_OFFSET."""
        return max(128, int(self.device.mem_base_addr_align) // 8)

    def align_up(self, nbytes: int) -> int:
        """`nbytes` rounded up to a valid sub-buffer origin."""
        a = self.sub_buffer_align
        return -(-int(nbytes) // a) * a

    def finish(self) -> None:
        self.queue.finish()


def _import_cl():
    ensure_pocl_cache_dir()
    try:
        import pyopencl as cl
    except ImportError as e:
        raise RtwalkError(f"{NO_DEVICE}; pyopencl is not importable ({e})") from None
    return cl


def list_devices() -> list[Any]:
    """All OpenCL devices of all platforms, in platform order ([] when there is no platform)."""
    cl = _import_cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # CL_PLATFORM_NOT_FOUND_KHR when no ICD is installed
        return []
    devices: list[Any] = []
    for p in platforms:
        try:
            devices.extend(p.get_devices())
        except cl.Error:  # a platform without devices
            continue
    return devices


CL_DEVICE_TYPE_GPU = 1 << 2


def choose_device(devices: list[Any], spec: str | None) -> Any:
    """The device RTWALK_CL_DEVICE names (index or name substring), else the first GPU, else the
    first."""
    if not devices:
        raise RtwalkError(NO_DEVICE)
    spec = (spec or "").strip()
    if not spec:
        gpus = [d for d in devices if int(getattr(d, "type", 0)) & CL_DEVICE_TYPE_GPU]
        return (gpus or devices)[0]
    names = [f"{d.platform.name.strip()} {d.name.strip()}" for d in devices]
    if spec.isdigit():
        i = int(spec)
        if i >= len(devices):
            raise RtwalkError(f"{DEVICE_ENV}={spec}: only {len(devices)} OpenCL device(s): " + "; ".join(names))
        return devices[i]
    for d, n in zip(devices, names, strict=True):
        if spec.lower() in n.lower():
            return d
    raise RtwalkError(f"{DEVICE_ENV}={spec!r} matches no OpenCL device: " + "; ".join(names))


def cl_context() -> ClContext:
    """The shared context (created on first call). Raises RtwalkError without an OpenCL device."""
    global _context
    if _context is None:
        cl = _import_cl()
        device = choose_device(list_devices(), os.environ.get(DEVICE_ENV))
        try:
            ctx = cl.Context([device])
            queue = cl.CommandQueue(ctx, device, properties=cl.command_queue_properties.PROFILING_ENABLE)
        except cl.Error as e:
            raise RtwalkError(f"cannot open OpenCL device {device.name.strip()!r}: {str(e).splitlines()[0]}") from None
        _context = ClContext(cl, ctx, queue, device)
    return _context


def cl_available() -> str | None:
    """None when an OpenCL device can be opened, else the reason (for pytest skips)."""
    try:
        cl_context()
    except RtwalkError as e:
        return str(e)
    return None

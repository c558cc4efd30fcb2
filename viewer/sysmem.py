"""Memory this process may still use, for refusing a scene size before building it.

The smallest of: the system's MemAvailable, the cgroup limit less its current use (containers),
and the address-space limit (`ulimit -v`) less this process's current virtual size. None where
none of them can be read (the caller then does not refuse).
"""

from __future__ import annotations

import resource
from pathlib import Path


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_headroom() -> int | None:
    limit = _read_int("/sys/fs/cgroup/memory.max")  # "max" (no limit) reads as None
    if limit is None:
        limit = _read_int("/sys/fs/cgroup/memory/memory.limit_in_bytes")  # cgroup v1
        if limit is not None and limit >= 1 << 60:
            limit = None
    if limit is None:
        return None
    used = _read_int("/sys/fs/cgroup/memory.current") or _read_int("/sys/fs/cgroup/memory/memory.usage_in_bytes") or 0
    return max(limit - used, 0)


def _vm_size() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _address_space_headroom() -> int | None:
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    return max(soft - _vm_size(), 0)


def available_bytes() -> int | None:
    """Bytes this process can still allocate (the tightest known limit), or None if unknown."""
    values = [v for v in (_meminfo_available(), _cgroup_headroom(), _address_space_headroom()) if v is not None]
    return min(values) if values else None


def gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB"

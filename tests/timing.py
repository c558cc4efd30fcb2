"""Sizing timed work to the device: tests that compare a measured time with another must first
make the work long enough to measure, whatever the device (an H100 runs in 0.3 ms what llvmpipe
runs in 300 ms). Speed targets live in benchmarks, never here."""

from __future__ import annotations

from collections.abc import Callable

FLOOR_MS = 20.0  # long enough that launch overhead and timer resolution are a few percent


def grow_until_measurable(run: Callable[[int], float], start: int, limit: int,
                          floor_ms: float = FLOOR_MS) -> tuple[int, float]:
    """The smallest work size reached from `start` (x2 or more per step, up to `limit`) at which
    run(size) -> wall ms takes at least `floor_ms`; returns (size, ms). Raises if even `limit` is
    too light, so a test never asserts on an unmeasurable time."""
    size = start
    while True:
        ms = run(size)
        if ms >= floor_ms:
            return size, ms
        if size >= limit:
            raise AssertionError(f"work size {size} takes only {ms:.3f} ms (< {floor_ms} ms) at its limit")
        factor = 2 if ms <= 0 else max(2, min(64, int(1.5 * floor_ms / ms)))
        size = min(limit, size * factor)

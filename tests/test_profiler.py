"""Phase timing: the profiler's numbers against wall-clock time measured around the same work."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.timing import FLOOR_MS, grow_until_measurable
from viewer.profiler import GpuProfiler, choose_timing
from viewer.timer_check import HEAVY_FS, HEAVY_VS


def _heavy_draw(ctx, size: int = 256, n: int = 400):
    prog = ctx.program(vertex_shader=HEAVY_VS, fragment_shader=HEAVY_FS)
    prog["n"] = n
    vbo = ctx.buffer(np.array([-1, -1, 3, -1, -1, 3], "f4").tobytes())
    vao = ctx.vertex_array(prog, vbo, "p")
    fbo = ctx.framebuffer(color_attachments=[ctx.texture((size, size), 4, dtype="f4")])
    return vao, fbo


MAX_LOOP = 60_000  # llvmpipe ends a shader loop after 65,535 back-edges: grow the target beyond


def _sized_heavy_draw(ctx):
    """_heavy_draw grown until one draw takes >= FLOOR_MS here (0.31 ms at 256 x 256, n = 400 on an
    H100): the loop count first, then the target size (256 x 256 is 16 bins; more stays multi-bin)."""
    made: dict = {}

    def run(work: int) -> float:
        n = min(work, MAX_LOOP)
        size = 256 * max(1, int(round((work / n) ** 0.5)))
        if made:
            made["vao"].release()
            made["fbo"].release()
        made["vao"], made["fbo"] = _heavy_draw(ctx, size, n)
        made["fbo"].use()
        made["vao"].render()  # compile the shader variant outside the measurement
        ctx.finish()
        t0 = time.perf_counter()
        made["vao"].render()
        ctx.finish()
        return (time.perf_counter() - t0) * 1e3

    grow_until_measurable(run, 400, MAX_LOOP * 256)
    return made["vao"], made["fbo"]


def test_phase_time_covers_a_multi_bin_draw(gl_ctx):
    """A full-screen draw over many 64x64 bins must be charged (almost) all of its wall time.

    llvmpipe's GL_TIME_ELAPSED charges about one bin per thread; the profiler must not."""
    vao, fbo = _sized_heavy_draw(gl_ctx)
    fbo.use()
    prof = GpuProfiler(gl_ctx)
    for _ in range(2):
        prof.begin_frame()
        gl_ctx.finish()
        t0 = time.perf_counter()
        with prof.phase("draw"):
            vao.render()
        gl_ctx.finish()
        wall_ms = (time.perf_counter() - t0) * 1e3
        ms = prof.end_frame()["draw"]
    assert wall_ms > 0.5 * FLOOR_MS, "the draw is too light to tell the methods apart"
    assert 0.6 * wall_ms <= ms <= wall_ms * 1.05 + 1.0, (prof.method, ms, wall_ms)


def test_llvmpipe_uses_sync_timing(gl_ctx, monkeypatch):
    monkeypatch.delenv("RTWALK_PHASE_TIMING", raising=False)
    if "llvmpipe" in str(gl_ctx.info.get("GL_RENDERER", "")).lower():
        assert choose_timing(gl_ctx) == "sync"
    monkeypatch.setenv("RTWALK_PHASE_TIMING", "timer")
    assert choose_timing(gl_ctx) == "timer"
    with pytest.raises(ValueError):
        GpuProfiler(gl_ctx, method="stopwatch")


class _SaturatedQuery:
    """A timer query whose 32-bit result saturated (a phase over 4.29 s)."""

    elapsed = 0xFFFFFFFF

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_saturated_timer_is_charged_cpu_time_not_zero(gl_ctx):
    prof = GpuProfiler(gl_ctx, method="timer")
    prof._pool.append(_SaturatedQuery())
    prof.begin_frame()
    with prof.phase("long"):
        time.sleep(0.02)
    ms = prof.end_frame()["long"]
    assert prof.saturated == 1
    assert ms >= 15.0


def test_grow_until_measurable_reaches_the_floor_or_fails():
    """The work-sizing helper of the timed tests: a fast device (0.1 us per unit) gets enough work
    for FLOOR_MS; work that stays too light at its limit fails instead of asserting on noise."""
    from tests.timing import FLOOR_MS, grow_until_measurable

    sizes = []

    def fast(n: int) -> float:
        sizes.append(n)
        return n * 1e-4

    n, ms = grow_until_measurable(fast, 400, 10**9)
    assert ms >= FLOOR_MS and n * 1e-4 == ms and sizes == sorted(sizes) and len(sizes) < 8
    with pytest.raises(AssertionError, match="only"):
        grow_until_measurable(fast, 400, 10_000)


class _RecordingQuery:
    """A timer query that records whether it was begun while another one was active."""

    active = 0
    nested = 0
    elapsed = 2_000_000  # 2 ms

    def __enter__(self):
        _RecordingQuery.nested += _RecordingQuery.active
        _RecordingQuery.active += 1
        return self

    def __exit__(self, *exc):
        _RecordingQuery.active -= 1
        return False


def test_nested_phases_never_nest_timer_queries(gl_ctx):
    """GL allows one active GL_TIME_ELAPSED query (NVIDIA: a nested begin is GL_INVALID_OPERATION):
    an inner phase is charged its CPU time, the outer one its query's GPU time."""
    prof = GpuProfiler(gl_ctx, method="timer")
    prof._pool.extend([_RecordingQuery(), _RecordingQuery()])
    prof.begin_frame()
    with prof.phase("outer"):
        with prof.phase("inner"):
            time.sleep(0.01)
    with prof.phase("after"):
        pass
    ms = prof.end_frame()
    assert _RecordingQuery.nested == 0
    assert ms["outer"] == ms["after"] == 2.0 and ms["inner"] >= 8.0


class _Marker:
    def __init__(self, end: int | None):
        self._end = end

    @property
    def profile(self):
        if self._end is None:
            raise RuntimeError("clGetEventProfilingInfo failed: PROFILING_INFO_NOT_AVAILABLE")
        return type("P", (), {"end": self._end})()


class _Queue:
    def finish(self) -> None:
        pass


@pytest.mark.parametrize("ends,expect", [((1_000_000, 4_000_000), 3.0), ((None, None), 7.0), ((0, 0), 7.0)])
def test_cl_marker_phase_without_timestamps_is_charged_cpu_time(gl_ctx, ends, expect):
    """A driver that keeps no timestamps for markers (an error, or zeros) costs the phase its CPU
    time, counted as unreadable, instead of an exception at the end of every device frame."""
    prof = GpuProfiler(gl_ctx, method="timer")
    prof.begin_frame()
    prof._used.append(("cl:trace", (_Marker(ends[0]), _Marker(ends[1]), _Queue()), None, 7.0))
    assert prof.end_frame()["cl:trace"] == pytest.approx(expect)
    assert prof.saturated == (0 if expect == 3.0 else 1)

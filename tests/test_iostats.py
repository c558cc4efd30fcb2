"""Per-frame I/O counters (viewer.iostats): every CL launch and transfer goes through the counted
choke points (viewer/cl/io.py, viewer/gl/io.py), and a steady frame moves a bounded, pass-count
independent number of bytes."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import opencl_missing
from viewer import iostats

ROOT = Path(__file__).resolve().parents[1] / "viewer"
# calls that bypass the counts: pyopencl's Kernel, enqueue_copy, enqueue_map_buffer, and buffers
# initialised from host memory (COPY_HOST_PTR with hostbuf=)
_BYPASS = re.compile(r"\.(Kernel|enqueue_copy|enqueue_map_buffer)\(|hostbuf=")


def test_no_uncounted_opencl_calls_outside_viewer_cl():
    """Code outside viewer/cl (chcrt has no CL) must use viewer.cl.io: kernel/copy/map_buffer/upload."""
    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("cl/") or "chcrt" in rel:
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if _BYPASS.search(code):
                bad.append(f"viewer/{rel}:{i}: {line.strip()}")
    assert not bad, "uncounted OpenCL calls (use viewer.cl.io):\n" + "\n".join(bad)


def test_cl_io_counts_bytes_direction_and_syncs():
    if opencl_missing():
        pytest.skip(opencl_missing())
    from viewer.cl import cl_context, host_buffer, mapped
    from viewer.cl import io as clio

    ctx = cl_context()
    a = np.arange(1000, dtype=np.float32)
    iostats.begin_frame()
    buf = clio.upload(ctx, a)
    out = np.empty_like(a)
    clio.copy(ctx.queue, out, buf)
    hb = host_buffer(ctx, a.nbytes)
    with mapped(ctx, hb, (1000,), np.float32, write=True) as m:
        m[:] = a
    with mapped(ctx, hb, (1000,), np.float32) as m:
        back = m.copy()
    clio.finish(ctx.queue)
    io = iostats.end_frame()
    assert np.array_equal(out, a) and np.array_equal(back, a)
    assert io.bytes_to_device == 2 * a.nbytes
    assert io.bytes_to_host == 2 * a.nbytes
    assert io.host_syncs == 4  # blocking read, two blocking maps, finish
    buf.release()
    hb.release()


# -- steady frames --------------------------------------------------------------------------------
SIZE = (160, 90)
# a frame may read a few rays besides its per-pixel traffic (a backend placing a structure from a
# strided sample of a pass's rays: fewer than 2 * 4096 rays of 32 bytes; city has one point light),
# plus the frame's parameters and ray counts
FIXED_BYTES = 2 * 4096 * 32 + 4096


def _steady_io(backend: str, effects: str):
    """The counts of the second frame of a two-frame replay of city-near (the first also builds,
    uploads and compiles)."""
    from tests.conftest import prepared_scene
    from viewer.effects import parse_effects
    from viewer.gl.context import shared_context
    from viewer.paths import RECORDINGS
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    r = Renderer(shared_context(), prep.scene, prep.bvh, SIZE, backend, parse_effects(effects))
    try:
        r.render(rec.camera_for_frame(10))
        rep = r.render(rec.camera_for_frame(11))
        return rep.io, r.frame_path
    finally:
        r.release()


def _backends(device: str) -> list:
    from tests.conftest import backend_params
    from viewer.backends import backend_info

    out = []
    for p in backend_params(reference=True):
        name = p.values[0]
        try:
            dev = backend_info(name).device
        except Exception:  # noqa: BLE001 (an unimportable backend: its own tests report it)
            continue
        if dev == device:
            out.append(p)
    return out


@pytest.mark.parametrize("backend", _backends("cl"))
def test_cl_backend_steady_frame_bytes_are_bounded_and_pass_independent(backend, gl_ctx):
    """Device-resident frames: per steady frame at most the G-buffer ids in (4 B/px) and the used
    accumulators out (16 B/px each: shadows and ao here), and ao:8 moves exactly the bytes of ao:4."""
    if opencl_missing():
        pytest.skip(opencl_missing())
    io4, path = _steady_io(backend, "primary,shadows,ao:4")
    io8, _ = _steady_io(backend, "primary,shadows,ao:8")
    assert path == "device"
    px = SIZE[0] * SIZE[1]
    k = 2  # accumulated effects: shadows, ao
    total4 = io4.bytes_to_device + io4.bytes_to_host
    assert total4 <= (4 + 16 * k) * px + FIXED_BYTES, io4
    assert io4.bytes_to_device >= 4 * px and io4.bytes_to_host >= 16 * k * px, io4  # ids in, accumulators out
    assert (io8.bytes_to_device, io8.bytes_to_host) == (io4.bytes_to_device, io4.bytes_to_host), (io4, io8)
    assert io8.cl_launches > io4.cl_launches  # the 4 extra passes ran (raygen, trace, accumulate)
    if backend == "clbvh":  # no host wait per pass: the syncs are per frame
        assert io8.host_syncs == io4.host_syncs, (io4, io8)


@pytest.mark.parametrize("backend", _backends("gl"))
def test_gl_backend_bytes_do_not_grow_with_passes(backend, gl_ctx):
    """GL backends trace on the GL device: ao:8 sends what ao:4 sends; what comes back grows only by
    a traversal's 8-byte counter read per extra draw (glsl decides on the host whether to draw again)."""
    io4, _ = _steady_io(backend, "primary,shadows,ao:4")
    io8, _ = _steady_io(backend, "primary,shadows,ao:8")
    assert io8.bytes_to_device == io4.bytes_to_device, (io4, io8)
    assert 0 <= io8.bytes_to_host - io4.bytes_to_host <= 8 * (io8.gl_draws - io4.gl_draws), (io4, io8)
    assert io4.bytes_to_device + io4.bytes_to_host < SIZE[0] * SIZE[1]  # no per-pixel traffic at all


def test_panel_and_bench_summary_show_the_counters():
    import io as pyio

    from viewer.bench.replay import print_summary, summarize
    from viewer.iostats import IoCounts
    from viewer.ui.panel import io_lines

    c = IoCounts(bytes_to_device=4 * 100, bytes_to_host=32 * 100, host_syncs=7, cl_launches=9, gl_draws=2)
    lines = io_lines(c, (10, 10))
    assert "4.0 B/px" in lines[0] and "32.0 B/px" in lines[1] and "host syncs 7" in lines[2]
    # on a CPU rasterizer the frame's "host" time also holds its rendering: the line says so
    assert lines[-1].startswith("host time ") and "CPU" not in lines[-1]
    assert "CPU rendering" in io_lines(c, (10, 10), "llvmpipe (LLVM 15.0.6, 256 bits)")[-1]
    assert "CPU rendering" not in io_lines(c, (10, 10), "NVIDIA H100 80GB HBM3/PCIe/SSE2")[-1]
    rows = [{"gpu_ms": {"a": t}, "wall_ms": 2.0, "rays": {"primary": 1}, "mrays_per_s": {"all": 0.0, "primary": 0.0},
             "trace_ms": t, "trace_ms_by_ray": {"primary": t},
             "io": IoCounts(bytes_to_device=b).as_dict()} for b, t in ((999, 90.0), (400, 7.0), (600, 3.0), (500, 5.0))]
    s = summarize(rows)
    assert s["io_mean"]["bytes_to_device"] == 500  # steady frames: the first is left out
    # steady times: the median of the frames after the first (a cold frame would skew a mean)
    assert s["steady_frames"] == 3 and s["steady_trace_ms_median"] == 5.0, s
    assert s["steady_trace_ms_by_ray_median"] == {"primary": 5.0} and s["steady_frame_gpu_ms_median"] == 5.0
    assert s["frame_gpu_ms_mean"] == 26.25
    out = pyio.StringIO()
    print_summary({"summary": s, "size": [10, 10], "scene_name": "x", "triangles": 1, "backend": "b",
                   "device": {"renderer": "r"}}, out)
    assert "I/O per steady frame: to device 0.00 MB (5.0 B/px)" in out.getvalue()
    assert "steady (median of the 3 frames after the first): GPU 5.0 ms, trace 5.0 ms (primary 5.0)" in out.getvalue()
    # per phase: the mean over every frame (the cold one's 90 ms in it) beside the steady median
    assert s["steady_gpu_ms_median"] == {"a": 5.0}
    assert any(line.split() == ["a", "26.25", "5.00"] for line in out.getvalue().splitlines()), out.getvalue()

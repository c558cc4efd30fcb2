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

"""The OpenCL layer: device choice, missing-device error, #include expansion, program cache,
POCL_CACHE_DIR default, GL<->CL ray/hit transfer, and CL phases in the profiler."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.timing import FLOOR_MS, grow_until_measurable
from viewer.cl import context as clctx
from viewer.cl import programs
from viewer.errors import RtwalkError


def _need_cl():
    reason = clctx.cl_available()
    if reason is not None:
        pytest.skip(f"no OpenCL device: {reason}")
    return clctx.cl_context()


def _fake(platform: str, name: str, dtype: int = 2):
    return SimpleNamespace(name=name, platform=SimpleNamespace(name=platform), type=dtype)


def test_choose_device_by_index_and_substring():
    """Unset: the first GPU (CL_DEVICE_TYPE_GPU = 4), whatever order the ICD loader lists the
    platforms in; else the first device."""
    devs = [_fake("Portable Computing Language", "pthread-cpu"), _fake("NVIDIA CUDA", "RTX 4090", 4)]
    assert clctx.choose_device(devs, None) is devs[1]
    assert clctx.choose_device(devs, "") is devs[1]
    assert clctx.choose_device(devs[:1], None) is devs[0]
    assert clctx.choose_device(devs, "0") is devs[0]
    assert clctx.choose_device(devs, "1") is devs[1]
    assert clctx.choose_device(devs, "rtx") is devs[1]
    assert clctx.choose_device(devs, "portable") is devs[0]
    for bad in ("2", "amd"):
        with pytest.raises(RtwalkError, match=clctx.DEVICE_ENV):
            clctx.choose_device(devs, bad)


def test_no_device_is_one_line_error(monkeypatch):
    monkeypatch.setattr(clctx, "_context", None)
    monkeypatch.setattr(clctx, "list_devices", lambda: [])
    with pytest.raises(RtwalkError) as e:
        clctx.cl_context()
    assert str(e.value) == "no OpenCL device (install pocl-opencl-icd)"
    assert clctx.cl_available() == str(e.value)


def test_pocl_cache_dir_default_and_user_value(monkeypatch, tmp_path):
    monkeypatch.setenv("POCL_CACHE_DIR", str(tmp_path / "mine"))
    assert clctx.ensure_pocl_cache_dir() == str(tmp_path / "mine")
    monkeypatch.delenv("POCL_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    got = clctx.ensure_pocl_cache_dir()
    assert got == str(tmp_path / "xdg" / "rtwalk" / "pocl") and Path(got).is_dir()
    monkeypatch.delenv("POCL_CACHE_DIR")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    monkeypatch.setenv("XDG_CACHE_HOME", str(ro / "sub"))
    try:
        got = clctx.ensure_pocl_cache_dir()
    finally:
        ro.chmod(0o700)
    if got.startswith(str(ro)):  # running as root: permissions do not stop us
        assert Path(got).is_dir()
    else:
        assert "rtwalk-pocl-" in got and Path(got).is_dir()


def test_include_expansion(tmp_path):
    (tmp_path / "a.cl").write_text('#include "b.cl"\n#include "common.cl"\nint a(void) { return b() + 1; }\n')
    (tmp_path / "b.cl").write_text('#include "common.cl"\ninline int b(void) { return 41; }\n')
    src = programs.expand(tmp_path / "a.cl")
    assert "#include" not in src.replace("(include with #include", "")
    assert src.count("rt_block_range(uint n") == 1  # common.cl included once
    assert src.index("inline int b(void)") < src.index("int a(void)")
    (tmp_path / "c.cl").write_text('#include "missing.cl"\n')
    with pytest.raises(RtwalkError, match="missing.cl"):
        programs.expand(tmp_path / "c.cl")
    with pytest.raises(RtwalkError, match="nope.cl"):
        programs.expand("nope.cl")


def test_program_cache_and_build_error(tmp_path):
    ctx = _need_cl()
    f = tmp_path / "k.cl"
    f.write_text('#include "common.cl"\n__kernel void k(__global int *o) { o[get_global_id(0)] = VALUE; }\n')
    p1 = programs.build(f, {"VALUE": 3}, ctx)
    assert programs.build(f, {"VALUE": 3}, ctx) is p1
    p2 = programs.build(f, {"VALUE": 4}, ctx)
    assert p2 is not p1
    out = np.zeros(8, np.int32)
    buf = ctx.cl.Buffer(ctx.context, ctx.cl.mem_flags.READ_WRITE, out.nbytes)
    ctx.cl.Kernel(p2, "k")(ctx.queue, (8,), None, buf)
    ctx.cl.enqueue_copy(ctx.queue, out, buf)
    assert (out == 4).all()
    f.write_text("__kernel void k(__global int *o) { o[0] = undefined_name; }\n")
    with pytest.raises(RtwalkError, match="k.cl"):
        programs.build(f, None, ctx)
    assert programs.warm_up([("common.cl", None)], ctx) >= 0.0


_COPY = """
#include "common.cl"
__kernel void copy(__global const float4 *o, __global const float4 *d, __global float *t, __global int *tri) {
    uint i = get_global_id(0);
    float4 a = o[i], b = d[i];
    t[i] = rt_ray_active(a, b) ? a.x + b.y * 10.0f + a.w * 100.0f + b.w * 1000.0f : INFINITY;
    tri[i] = rt_ray_active(a, b) ? (int)i : RT_MISS_ID;
}
"""


def test_ray_and_hit_transfer_through_gl_textures(gl_ctx, tmp_path):
    """Rays written into the GL textures reach the CL kernel in the documented layout, and the
    kernel's hits reach the GL hit textures (checked against NumPy on the same data)."""
    from viewer.cl.transfer import HitStage, RayStage
    from viewer.rays import HitBuffer, RayBatch

    ctx = _need_cl()
    size = (37, 23)
    n = size[0] * size[1]
    rng = np.random.default_rng(1)
    o = rng.integers(-8, 8, size=(n, 4)).astype(np.float32)  # small integers: exact arithmetic
    d = rng.integers(-8, 8, size=(n, 4)).astype(np.float32)
    o[::5, 3] = 0.0
    d[::5, 3] = -1.0  # inactive: tmax < tmin
    d[3, 0] = np.nan
    rays, hits = RayBatch(gl_ctx, size), HitBuffer(gl_ctx, size)
    rays.origin.write(o.tobytes())
    rays.direction.write(d.tobytes())
    rs, hs = RayStage(size, ctx), HitStage(size, ctx)
    rs.upload(rays)
    f = tmp_path / "copy.cl"
    f.write_text(_COPY)
    ctx.cl.Kernel(programs.build(f, None, ctx), "copy")(ctx.queue, (n,), None, rs.origin, rs.dir, hs.t, hs.tri)
    hs.download(hits)
    t, tri = hits.read()
    active = np.isfinite(o).all(1) & np.isfinite(d[:, :3]).all(1) & (o[:, 3] < d[:, 3])
    want_t = np.where(active, o[:, 0] + d[:, 1] * 10 + o[:, 3] * 100 + d[:, 3] * 1000, np.inf).astype(np.float32)
    np.testing.assert_array_equal(t, want_t)
    np.testing.assert_array_equal(tri, np.where(active, np.arange(n), -1))
    assert not active[3] and n // 4 < active.sum() < n
    t2, tri2 = hs.read()
    np.testing.assert_array_equal(t2, t)
    rs.release()
    hs.release()
    rays.release()
    hits.release()


_SPIN = """
__kernel void spin(__global float *o, int n) {
    float x = (float)get_global_id(0);
    for (int i = 0; i < n; ++i) x = x * 0.999999f + 1.0f;
    o[get_global_id(0)] = x;
}
"""


@pytest.mark.parametrize("method", ["sync", "timer"])
def test_cl_phase_covers_kernel_time_and_counts_per_label(gl_ctx, tmp_path, method):
    from viewer.profiler import GpuProfiler

    ctx = _need_cl()
    f = tmp_path / "spin.cl"
    f.write_text(_SPIN)
    k = ctx.cl.Kernel(programs.build(f, None, ctx), "spin")
    buf = ctx.cl.Buffer(ctx.context, ctx.cl.mem_flags.READ_WRITE, 4 * 256)
    k(ctx.queue, (256,), (64,), buf, np.int32(10))
    ctx.finish()

    def run(n: int) -> float:
        t0 = time.perf_counter()
        k(ctx.queue, (256,), (64,), buf, np.int32(n))
        ctx.finish()
        return (time.perf_counter() - t0) * 1e3

    # iterations for a kernel of >= FLOOR_MS on this device (0.5 ms at 200,000 on an H100)
    n, _ = grow_until_measurable(run, 20_000, 2**31 - 1)
    prof = GpuProfiler(gl_ctx, method=method)
    gl_ctx.finish()  # GL work an earlier test of this worker left queued is not this wall time's
    ctx.finish()
    prof.begin_frame()
    t0 = time.perf_counter()
    prof.label = "ao"
    with prof.cl_phase("cl:spin", ctx.queue):
        k(ctx.queue, (256,), (64,), buf, np.int32(n))  # returns before the kernel ends
    prof.record("cl:extra", 2.5)
    prof.label = None
    with prof.phase("gl"):
        pass
    wall = (time.perf_counter() - t0) * 1e3
    ms = prof.end_frame()
    assert wall > 0.5 * FLOOR_MS, "the kernel is too light to tell enqueue time from run time"
    assert 0.8 * wall <= ms["cl:spin"] <= wall * 1.05 + 1.0, (ms, wall)
    assert ms["cl:extra"] == 2.5
    assert prof.by_label["ao"] == pytest.approx(ms["cl:spin"] + 2.5)
    assert "gl" in ms and "gl" not in prof.by_label


def test_importing_the_layer_does_not_load_opencl():
    """GL backends must work on machines without OpenCL: pyopencl loads on first cl_context()."""
    import subprocess
    import sys

    code = ("import sys, viewer.cl, viewer.cl.primitives, viewer.bench.cl_primitives, viewer.profiler; "
            "assert 'pyopencl' not in sys.modules; import os; assert os.environ.get('POCL_CACHE_DIR')")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])


def test_launch_sizes_are_checked_for_gpus(tmp_path):
    """A global size that is not a multiple of the local size is refused on every device (OpenCL C
    1.2 on NVIDIA has uniform work-groups only; PoCL would run it), and a local size above the
    kernel's CL_KERNEL_WORK_GROUP_SIZE is one RtwalkError line, not INVALID_WORK_GROUP_SIZE."""
    from viewer.cl import io as clio

    clio.check_ndrange("k", (128, 4), (64, 2))
    clio.check_ndrange("k", (100,), None)
    for g, loc in (((100,), (64,)), ((128,), (64, 1)), ((128,), (0,))):
        with pytest.raises(ValueError, match="not a multiple"):
            clio.check_ndrange("k", g, loc)
    ctx = _need_cl()
    f = tmp_path / "one.cl"
    f.write_text("__kernel void k(__global int *a) { a[get_global_id(0)] = 1; }\n")
    prog = programs.build(f, None, ctx)
    k = clio.kernel(prog, "k")
    buf = ctx.cl.Buffer(ctx.context, ctx.cl.mem_flags.READ_WRITE, 4 * 64)
    k(ctx.queue, (64,), (64,), buf)
    k._max_group = 32  # as a GPU reports for a kernel heavy on registers
    with pytest.raises(RtwalkError, match=r"k: 64 work-items per group, the device allows 32"):
        k(ctx.queue, (64,), (64,), buf)
    ctx.finish()
    buf.release()

"""The OpenCL layer: one shared context/queue, kernel programs, GL<->CL ray/hit transfer, primitives.

pyopencl is imported lazily (first `cl_context()`), so importing this package costs nothing and
GL backends work on machines without OpenCL. Importing it sets POCL_CACHE_DIR to a writable
folder (~/.cache/rtwalk/pocl, else a temporary one) unless the user set it.

API (all names importable from viewer.cl):

Context (viewer/cl/context.py)
  cl_context() -> ClContext           shared; device = RTWALK_CL_DEVICE (index into all devices
                                      of all platforms, or a substring of "platform device"), else
                                      the first. No device: RtwalkError("no OpenCL device (install
                                      pocl-opencl-icd)"); the CLI prints it as one line, exit 2.
  ClContext.cl / .context / .queue / .device   pyopencl module, Context, in-order CommandQueue
                                      (PROFILING_ENABLE), Device; .name, .compute_units, .is_cpu,
                                      .finish()
  cl_available() -> str | None        None if usable, else the reason (pytest.skip(reason))
  list_devices(), choose_device(devices, spec), ensure_pocl_cache_dir()

Programs (viewer/cl/programs.py)
  build(path, defines=None, ctx=None, search=()) -> pyopencl.Program
      path: a file name looked up in `search` then viewer/cl/kernels, or a Path (a backend passes
      Path(__file__).parent / "trace.cl"). `#include "x.cl"` is expanded from the including
      file's folder, then `search`, then viewer/cl/kernels. defines: {"WG": 64, "FLAG": None}.
      Cached per (expanded source, defines, device); build errors raise RtwalkError.
      Keep kernels: `k = viewer.cl.io.kernel(prog, "name")` once, then `k(queue, gsize, lsize, *args)`.

Counted launches and transfers (viewer/cl/io.py): kernel/kernels, copy, map_buffer, upload,
  read_rows/read_strided, finish, marker -- the only callers of pyopencl's Kernel, enqueue_copy
  and enqueue_map_buffer (viewer.iostats counts; tests/test_iostats.py enforces it).

Device-resident frame (viewer/cl/frame.py, kernels/frame.cl): DeviceFrame (ids in once, surface /
  raygen / accumulate kernels, accumulators out once), frame_path(backend) picks it for CL
  backends with trace_device; interop_available() is the hook for a zero-copy path.
  warm_up([(path, defines), ...]) -> ms   build + create kernels before the first frame.
  expand(path, search=()) -> str      the expanded source.

Transfer (viewer/cl/transfer.py), layouts (n = width*height, row-major, row 0 = bottom):
  RayStage(size)      .origin float4[n] (x, y, z, tmin), .dir float4[n] (dx, dy, dz, tmax);
                      .upload(ray_batch) reads both RGBA32F textures straight into mapped
                      CL_MEM_ALLOC_HOST_PTR buffers; .upload_arrays(o4, d4) for tests.
  HitStage(size)      .t float[n] (+inf miss), .tri int[n] (-1 miss);
                      .download(hit_buffer) maps them and writes the R32F / R32I textures;
                      .read() -> (t, tri) NumPy copies.
  PassStages(ctx, extras=0)  .get(size) -> (RayStage, HitStage, *extra int32 per-pixel buffers), made
                      again only when the size changes; .release(). What every CL backend stages.
  host_buffer(ctx, nbytes, access), mapped(ctx, buf, shape, dtype, write=False) context manager.

Profiling (viewer/profiler.py)
  with profiler.cl_phase("clbvh:trace", ctx.queue): ...   finishes the CL queue at the end (and,
      in sync mode, GL and the queue before) and records wall time as a phase like GL phases:
      same tables, plots, panel, and summed into by_label under the ray type being traced.
  profiler.record(name, ms)   a phase measured elsewhere (e.g. from CL event profiling).

Primitives (viewer/cl/primitives.py): see its docstring (radix sort, scan, compaction,
segments/chunks, min/max reduce) on pyopencl Buffers, with NumPy wrappers.
"""

from __future__ import annotations

from viewer.cl.context import (
    DEVICE_ENV,
    NO_DEVICE,
    ClContext,
    choose_device,
    cl_available,
    cl_context,
    ensure_pocl_cache_dir,
    list_devices,
)
from viewer.cl.programs import KERNELS_DIR, build, expand, warm_up
from viewer.cl.transfer import HitStage, PassStages, RayStage, host_buffer, mapped

ensure_pocl_cache_dir()

__all__ = [
    "DEVICE_ENV", "NO_DEVICE", "ClContext", "choose_device", "cl_available", "cl_context", "ensure_pocl_cache_dir",
    "list_devices", "KERNELS_DIR", "build", "expand", "warm_up", "HitStage", "PassStages", "RayStage",
    "host_buffer", "mapped",
]

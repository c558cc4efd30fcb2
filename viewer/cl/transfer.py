"""Rays and hits between the GL textures (viewer.rays) and CL buffers, staged through mapped memory.

PoCL has no cl_khr_gl_sharing, so data crosses through host memory once: the CL buffers are
allocated with CL_MEM_ALLOC_HOST_PTR, mapped, and moderngl reads the GL texture straight into the
mapped pointer (`Texture.read_into`) or writes the texture straight from it (`Texture.write`).
Mapping costs about 0.1 ms where a 29 MB copy costs 3.5 ms (measured on this machine).

Buffer layouts (one ray per pixel, row-major, row 0 = bottom, n = width * height):
  origin : float4[n]  (x, y, z, tmin)   -- RayBatch.origin texture, RGBA32F
  dir    : float4[n]  (dx, dy, dz, tmax) -- RayBatch.direction texture, RGBA32F; tmax <= tmin
                                            or non-finite values mark an inactive ray
  t      : float[n]   hit distance in units of |dir|, +inf on a miss -- HitBuffer.t, R32F
  tri    : int[n]     leaf-order triangle slot, -1 on a miss          -- HitBuffer.id, R32I
The buffers are unmapped while kernels run (map -> GL copy -> unmap), as OpenCL requires.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

import viewer.cl.io as clio
from viewer.cl.context import ClContext, cl_context
from viewer.cl.limits import check_alloc

if TYPE_CHECKING:
    from viewer.rays import HitBuffer, RayBatch


def host_buffer(ctx: ClContext, nbytes: int, access: str = "rw") -> Any:
    """A CL buffer in host-allocated memory (cheap to map); `access` is "r", "w" or "rw" from
    the kernels' point of view."""
    mf = ctx.cl.mem_flags
    flags = {"r": mf.READ_ONLY, "w": mf.WRITE_ONLY, "rw": mf.READ_WRITE}[access]
    check_alloc(int(nbytes), "ray/hit stage", ctx)
    return ctx.cl.Buffer(ctx.context, flags | mf.ALLOC_HOST_PTR, max(int(nbytes), 4))


class _Mapped:
    """`with _Mapped(ctx, buf, shape, dtype, write=True) as a:` a is the buffer's memory as NumPy."""

    def __init__(self, ctx: ClContext, buf: Any, shape: tuple[int, ...], dtype: Any, write: bool):
        self.ctx, self.buf, self.shape, self.dtype = ctx, buf, shape, np.dtype(dtype)
        mflags = ctx.cl.map_flags
        self.flags = mflags.WRITE_INVALIDATE_REGION if write else mflags.READ

    def __enter__(self) -> np.ndarray:
        self.array, _ = clio.map_buffer(self.ctx.queue, self.buf, self.flags, 0, self.shape,
                                                       self.dtype, is_blocking=True)
        return self.array

    def __exit__(self, *exc) -> None:
        self.array.base.release(self.ctx.queue)
        del self.array


def mapped(ctx: ClContext, buf: Any, shape: tuple[int, ...], dtype: Any, write: bool = False) -> _Mapped:
    """Map a CL buffer as a NumPy array for the `with` block (write=True: contents discarded)."""
    return _Mapped(ctx, buf, shape, dtype, write)


class RayStage:
    """CL copies of a RayBatch: `origin` and `dir` float4 buffers (layout above). `access` from the
    kernels' side: "r" for staged rays, "rw" where a kernel makes them (the device-resident frame)."""

    def __init__(self, size: tuple[int, int], ctx: ClContext | None = None, access: str = "r"):
        self.ctx = ctx or cl_context()
        self.size = (int(size[0]), int(size[1]))
        self.n = self.size[0] * self.size[1]
        self.origin = host_buffer(self.ctx, self.n * 16, access)
        self.dir = host_buffer(self.ctx, self.n * 16, access)

    def upload(self, rays: RayBatch) -> None:
        """Read the ray textures into the CL buffers (blocks until GL has produced them)."""
        assert tuple(rays.size) == self.size, (rays.size, self.size)
        for tex, buf in ((rays.origin, self.origin), (rays.direction, self.dir)):
            with mapped(self.ctx, buf, (self.n, 4), np.float32, write=True) as a:
                tex.read_into(a)

    def upload_arrays(self, origin: np.ndarray, direction: np.ndarray) -> None:
        """Fill the buffers from (n, 4) float32 arrays (tests, CPU-made rays)."""
        for src, buf in ((origin, self.origin), (direction, self.dir)):
            with mapped(self.ctx, buf, (self.n, 4), np.float32, write=True) as a:
                a[...] = np.asarray(src, np.float32).reshape(self.n, 4)

    def active_count(self) -> int:
        """Rays with tmin < tmax (a vectorised read of the mapped buffers: for counters, not hot paths)."""
        with mapped(self.ctx, self.origin, (self.n, 4), np.float32) as o, \
                mapped(self.ctx, self.dir, (self.n, 4), np.float32) as d:
            return int(np.count_nonzero(d[:, 3] > o[:, 3]))

    def read(self):
        """The rays as viewer.rays.RayArrays (verification: capture mode, tests)."""
        from viewer.rays import RayArrays

        with mapped(self.ctx, self.origin, (self.n, 4), np.float32) as o, \
                mapped(self.ctx, self.dir, (self.n, 4), np.float32) as d:
            return RayArrays(np.ascontiguousarray(o[:, :3]), np.ascontiguousarray(d[:, :3]),
                             np.ascontiguousarray(o[:, 3]), np.ascontiguousarray(d[:, 3]))

    def release(self) -> None:
        self.origin.release()
        self.dir.release()


class HitStage:
    """CL result buffers for a HitBuffer: `t` float and `tri` int per ray (layout above). `access`:
    "w" for staged hits, "rw" where a kernel reads them too (the device-resident frame)."""

    def __init__(self, size: tuple[int, int], ctx: ClContext | None = None, access: str = "w"):
        self.ctx = ctx or cl_context()
        self.size = (int(size[0]), int(size[1]))
        self.n = self.size[0] * self.size[1]
        self.t = host_buffer(self.ctx, self.n * 4, access)
        self.tri = host_buffer(self.ctx, self.n * 4, access)

    def download(self, hits: HitBuffer) -> None:
        """Write the CL results into the hit textures (waits for the queue's kernels)."""
        assert tuple(hits.size) == self.size, (hits.size, self.size)
        for buf, tex, dt in ((self.t, hits.t, np.float32), (self.tri, hits.id, np.int32)):
            with mapped(self.ctx, buf, (self.n,), dt) as a:
                tex.write(a)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of (t, tri) as NumPy arrays (tests)."""
        with mapped(self.ctx, self.t, (self.n,), np.float32) as t, mapped(self.ctx, self.tri, (self.n,), np.int32) as i:
            return t.copy(), i.copy()

    def release(self) -> None:
        self.t.release()
        self.tri.release()


class PassStages:
    """A CL backend's staging at the ray-batch size: a RayStage, a HitStage and `extras` int32
    per-pixel buffers (e.g. per-ray counters, a PixelBuffers), made again only when the size
    changes (every backend needs the same, so it lives here)."""

    def __init__(self, ctx: ClContext, extras: int = 0, extra_access: str = "w"):
        self.ctx = ctx
        self.extra = PixelBuffers(ctx, extras, extra_access)
        self.size: tuple[int, int] | None = None
        self.stages: tuple = ()

    def get(self, size: tuple[int, int]) -> tuple:
        """(RayStage, HitStage, *extra buffers) for a ray batch of `size`."""
        size = (int(size[0]), int(size[1]))
        if size != self.size:
            for part in self.stages:
                part.release()
            self.stages = (RayStage(size, self.ctx), HitStage(size, self.ctx))
            self.size = size
        return (*self.stages, *self.extra.get(size))

    def release(self) -> None:
        for part in self.stages:
            part.release()
        self.extra.release()
        self.stages, self.size = (), None


class PixelBuffers:
    """`count` int32 per-pixel CL buffers at a ray-batch size, made again only when the size changes:
    a backend's extra per-ray outputs in a device-resident frame (no RayStage / HitStage needed:
    the frame owns those)."""

    def __init__(self, ctx: ClContext, count: int, access: str = "w"):
        self.ctx, self.count, self.access = ctx, int(count), access
        self.size: tuple[int, int] | None = None
        self.parts: tuple = ()

    def get(self, size: tuple[int, int]) -> tuple:
        size = (int(size[0]), int(size[1]))
        if size != self.size:
            self.release()
            self.parts = tuple(host_buffer(self.ctx, 4 * size[0] * size[1], self.access) for _ in range(self.count))
            self.size = size
        return self.parts

    def release(self) -> None:
        for part in self.parts:
            part.release()
        self.parts, self.size = (), None

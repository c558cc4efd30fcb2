"""Counted GL reads, writes, draws and finishes (viewer.iostats): generic code moves data between
the host and GL objects through these so every frame's bytes, waits and draws are counted.

  read(obj, **kw) -> bytes      texture / buffer / framebuffer read: to_host + one sync, after
                                host_barrier (shader writes -> this read)
  ReadBack(ctx, nbytes)         a buffer the host reads in place of one the shaders write: a
                                device copy, then read() of the copy
  write(obj, data, **kw)        texture / buffer write from host memory: to_device
  draw(vao, *args, **kw)        vao.render(...): one gl_draw
  finish(ctx)                   ctx.finish() as one timed host sync
  check_errors(ctx, where)      with RTWALK_GL_CHECK=1: one line when glGetError reports an error
A GL texture read straight into a mapped CL buffer (or written from one) is a staged GL <-> CL
hop, counted once by the CL map (viewer/cl/io.py), not here.
"""

from __future__ import annotations

import os
from typing import Any

import moderngl
import numpy as np

from viewer import iostats

# glMemoryBarrier bits that make shader writes (SSBO / image stores and atomics) visible to the
# host's reads and writes of buffers, textures and framebuffers (glGetBufferSubData, glGetTexImage,
# glReadPixels, glBufferSubData). Without them a counter read right after the draw that increments
# it returns the old value, on llvmpipe too (it does not flush the draw for a buffer the draw wrote
# only through an SSBO: tests/test_gl.py measures 0); a glFinish in between (sync phase timing)
# hides that, timer-query timing did not (chcrt's pair counts were stale there before this).
HOST_ACCESS_BARRIERS = (moderngl.BUFFER_UPDATE_BARRIER_BIT | moderngl.TEXTURE_UPDATE_BARRIER_BIT
                        | moderngl.FRAMEBUFFER_BARRIER_BIT | moderngl.PIXEL_BUFFER_BARRIER_BIT)


def host_barrier(ctx: Any) -> None:
    """Make earlier shader writes visible to the next host read or write of a GL object (the read
    blocks anyway, so the barrier adds no wait of its own)."""
    ctx.memory_barrier(HOST_ACCESS_BARRIERS)


def read(obj: Any, **kw: Any) -> bytes:
    host_barrier(obj.ctx)
    with iostats.timed_sync():
        data = obj.read(**kw)
    iostats.to_host(len(data))
    return data


class ReadBack:
    """A small buffer the host reads instead of the buffer the shaders write (counters): the read
    copies `size` bytes into it on the device first. A driver places a buffer by how it is used:
    on an NVIDIA H200, while the host read the ray generation's counters directly after every
    frame, that frame's ray generation took 29.9 ms on the GPU at 1280x720 with camera rays only
    (0.53 ms through this copy; glsl's frame 51.4 -> 23.2 ms), as if its atomics went to host
    memory, and a device copy out of the counters made the host wait."""

    def __init__(self, ctx: Any, nbytes: int):
        self.ctx = ctx
        self.buf = ctx.buffer(reserve=max(int(nbytes), 4))

    def read(self, src: Any, size: int, offset: int = 0) -> bytes:
        """`size` bytes of `src` from `offset`, after every shader write to it (one copy, one sync)."""
        if size > self.buf.size:
            self.buf.release()
            self.buf = self.ctx.buffer(reserve=size)
        host_barrier(self.ctx)  # shader writes -> the copy (BUFFER_UPDATE covers glCopyBufferSubData)
        self.ctx.copy_buffer(self.buf, src, size, read_offset=offset)
        iostats.gl_draw()
        return read(self.buf, size=size)

    def release(self) -> None:
        self.buf.release()


def write(obj: Any, data: Any, **kw: Any) -> None:
    n = data.nbytes if isinstance(data, (np.ndarray, memoryview)) else len(data)
    iostats.to_device(n)
    obj.write(data, **kw)


def draw(vao: Any, *args: Any, **kw: Any) -> None:
    iostats.gl_draw()
    vao.render(*args, **kw)


GL_CHECK_ENV = "RTWALK_GL_CHECK"


def check_errors(ctx: Any, where: str) -> None:
    """With RTWALK_GL_CHECK=1, RtwalkError (one line) when GL recorded an error (glGetError) since
    the last look: a driver that refuses what Mesa accepted (a nested query, a bad barrier bit, an
    incomplete texture) says so here instead of drawing nothing. Off by default: a look per frame
    is cheap, but an error left by another library must not stop rtwalk."""
    if os.environ.get(GL_CHECK_ENV, "").strip() in ("", "0"):
        return
    err = ctx.error
    if err != "GL_NO_ERROR":
        from viewer.errors import RtwalkError

        raise RtwalkError(f"OpenGL error during {where}: {err} ({GL_CHECK_ENV}=1)")


def finish(ctx: Any) -> None:
    with iostats.timed_sync():
        ctx.finish()

"""Named device buffers reused across builds: a builder asks for `name` with at least `nbytes` and
gets the same buffer back until it needs a bigger one (the per-frame grids rebuild every pass and
must not allocate every time)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # no OpenCL import at module load: the accel modules import this
    from viewer.cl.context import ClContext


class BufferPool:
    """READ_WRITE buffers by name, grown on demand (never shrunk), all freed by release()."""

    def __init__(self, ctx: ClContext):
        self.ctx = ctx
        self.bufs: dict[str, Any] = {}

    def get(self, name: str, nbytes: int) -> Any:
        buf = self.bufs.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = self.ctx.cl.Buffer(self.ctx.context, self.ctx.cl.mem_flags.READ_WRITE, max(16, int(nbytes)))
            self.bufs[name] = buf
        return buf

    def __getitem__(self, name: str) -> Any:
        return self.bufs[name]

    def release(self) -> None:
        for buf in self.bufs.values():
            buf.release()
        self.bufs.clear()

"""Named device buffers reused across builds: a builder asks for `name` with at least `nbytes` and
gets the same buffer back until it needs a bigger one (the per-frame grids rebuild every pass and
must not allocate every time)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from viewer.cl.limits import new_buffer

if TYPE_CHECKING:  # no OpenCL import at module load: the accel modules import this
    from viewer.cl.context import ClContext


class BufferPool:
    """READ_WRITE buffers by name, grown on demand (never shrunk), all freed by release()."""

    def __init__(self, ctx: ClContext, what: str = "buffer pool"):
        self.ctx = ctx
        self.what = what  # names the structure in a limits error ("uniform grid blocks")
        self.bufs: dict[str, Any] = {}

    def get(self, name: str, nbytes: int) -> Any:
        buf = self.bufs.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
                del self.bufs[name]
            buf = new_buffer(self.ctx, self.ctx.cl.mem_flags.READ_WRITE, int(nbytes), f"{self.what} {name}")
            self.bufs[name] = buf
        return buf

    def take(self, name: str) -> Any:
        """Hand the buffer over to the caller (who now owns it); the next get() makes a new one."""
        return self.bufs.pop(name)

    @property
    def nbytes(self) -> int:
        """Bytes held by the pool's buffers."""
        return int(sum(b.size for b in self.bufs.values()))

    def __getitem__(self, name: str) -> Any:
        return self.bufs[name]

    def release(self) -> None:
        for buf in self.bufs.values():
            buf.release()
        self.bufs.clear()

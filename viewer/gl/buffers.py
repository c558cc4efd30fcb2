"""Stream buffers: SSBOs of records rewritten every draw."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.gl import io as glio


class StreamBuffer:
    """An SSBO of records, re-specified (orphaned) before every upload so draws still queued keep
    their data and the upload never waits for them. Grows to the next power of two when needed."""

    def __init__(self, ctx: moderngl.Context, itemsize: int, binding: int, capacity: int = 4096):
        self.ctx = ctx
        self.itemsize = itemsize
        self.binding = binding
        self.capacity = capacity
        self.buf = ctx.buffer(reserve=self.capacity * itemsize, dynamic=True)

    def upload(self, records: np.ndarray | bytes) -> None:
        """Replace the contents with `records` and bind the buffer to its binding point."""
        data = records if isinstance(records, bytes) else records.tobytes()
        n = max(len(data) // self.itemsize, 1)
        if n > self.capacity:
            self.buf.release()
            self.capacity = 1 << (n - 1).bit_length()
            self.buf = self.ctx.buffer(reserve=self.capacity * self.itemsize, dynamic=True)
        else:
            self.buf.orphan(self.capacity * self.itemsize)
        if data:
            glio.write(self.buf, data)
        self.buf.bind_to_storage_buffer(self.binding)

    def release(self) -> None:
        self.buf.release()

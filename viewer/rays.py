"""Rays and hits as they pass between the passes and a backend, and the pass they belong to.

A `RayBatch` is two RGBA32F textures, one ray per pixel: origin+tmin and direction+tmax
(tmax < 0 marks "no ray"). A `HitBuffer` is R32F distance (+inf on a miss) and R32I triangle id
in BVH leaf order (-1 on a miss). GL backends draw straight into the hit buffer; OpenCL and CPU
backends stage them (`RayBatch.read()`, `HitBuffer.write()`, or viewer.cl's mapped transfers).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import moderngl
import numpy as np

from viewer.effects import RayType
from viewer.gl import io as glio
from viewer.gl.textures import float_texture, int_texture, read_texture


@dataclass(frozen=True)
class DeviceCount:
    """A uint32 on the device: `offset` bytes into `buffer`."""

    buffer: moderngl.Buffer
    offset: int


@dataclass(frozen=True)
class PassInfo:
    """One sample pass of one effect. `light` indexes scene.point_lights for SHADOW passes and
    scene.rect_lights for SOFT passes (0 otherwise); `weight` is the pass's accumulation weight.
    `ray_count`: where the ray generation counted this pass's active rays (tmax > tmin) on the
    device, when it did (a backend that needs the count copies it instead of counting again);
    None for rays that came from elsewhere."""

    ray_type: RayType
    sample: int = 0
    light: int = 0
    weight: float = 1.0
    report: bool = True  # False: nobody reports this pass's statistics (the traced G-buffer's rays)
    ray_count: DeviceCount | None = field(default=None, compare=False)

    @property
    def any_hit(self) -> bool:
        return self.ray_type.any_hit

    @property
    def key(self) -> tuple[int, int, int]:
        """Identity of the pass across frames (temporal state is kept per key)."""
        return int(self.ray_type), int(self.sample), int(self.light)


@dataclass
class RayArrays:
    """Rays read back to the CPU, row-major over pixels (row 0 = bottom). float32."""

    origins: np.ndarray  # (R, 3)
    directions: np.ndarray  # (R, 3), unit length
    tmin: np.ndarray  # (R,)
    tmax: np.ndarray  # (R,), < 0 for pixels without a ray

    @property
    def active(self) -> np.ndarray:
        return self.tmax > self.tmin


class RayBatch:
    """Ray textures for one pass; owned by the renderer, reused every pass."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]):
        self.size = size
        self.origin = float_texture(ctx, size, 4)
        self.direction = float_texture(ctx, size, 4)
        self.fbo = ctx.framebuffer(color_attachments=[self.origin, self.direction])

    def read(self) -> RayArrays:
        o = read_texture(self.origin).reshape(-1, 4)
        d = read_texture(self.direction).reshape(-1, 4)
        return RayArrays(np.ascontiguousarray(o[:, :3]), np.ascontiguousarray(d[:, :3]),
                         np.ascontiguousarray(o[:, 3]), np.ascontiguousarray(d[:, 3]))

    def release(self) -> None:
        self.fbo.release()
        self.origin.release()
        self.direction.release()


class HitBuffer:
    """Nearest-hit distance and triangle id per pixel."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]):
        self.size = size
        self.t = float_texture(ctx, size, 1)
        self.id = int_texture(ctx, size)
        self.fbo = ctx.framebuffer(color_attachments=[self.t, self.id])

    def write(self, t: np.ndarray, tri: np.ndarray) -> None:
        glio.write(self.t, np.ascontiguousarray(t, np.float32).tobytes())
        glio.write(self.id, np.ascontiguousarray(tri, np.int32).tobytes())

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return read_texture(self.t).reshape(-1).copy(), read_texture(self.id).reshape(-1).copy()

    def release(self) -> None:
        self.fbo.release()
        self.t.release()
        self.id.release()

"""The interface every tracing backend implements.

A backend receives a `RayBatch` (two RGBA32F textures, one ray per pixel: origin+tmin and
direction+tmax, tmax < 0 marks "no ray") and fills a `HitBuffer` (R32F distance, +inf on a miss;
R32I triangle id in leaf order, -1 on a miss). GL backends draw straight into the hit buffer;
CPU/OpenCL backends call `RayBatch.read()` and `HitBuffer.write()`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Protocol

import moderngl
import numpy as np

from viewer.effects import RayType
from viewer.gpu import ProgramCache, float_texture, int_texture, read_texture
from viewer.profiler import GpuProfiler


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
        self.t.write(np.ascontiguousarray(t, np.float32).tobytes())
        self.id.write(np.ascontiguousarray(tri, np.int32).tobytes())

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return read_texture(self.t).reshape(-1).copy(), read_texture(self.id).reshape(-1).copy()

    def release(self) -> None:
        self.fbo.release()
        self.t.release()
        self.id.release()


@dataclass
class TraceResult:
    """What a backend reports for one ray pass besides the hits."""

    stats: dict[str, float] = field(default_factory=dict)  # counters, e.g. {"draws": 1}
    overlays: dict[str, moderngl.Texture] = field(default_factory=dict)


@dataclass
class BackendContext:
    """GL objects a backend may use; given once at creation."""

    ctx: moderngl.Context
    programs: ProgramCache
    profiler: GpuProfiler
    gpu_scene: object  # viewer.gpu.GpuScene
    scene: object  # viewer.scene.Scene (leaf order)
    bvh: object  # viewer.bvh.BVH


WORK_SLOTS = ("invocations", "nodes", "box_tests", "tri_tests",
              "query_fragments", "query_nodes", "query_box_tests", "query_tri_tests")
BIND_WORK = 9


class WorkCounters:
    """Shader work per trace (diagnostics, RTWALK_COUNT_WORK=1): ray-shader invocations, BVH nodes
    fetched, ray/box and ray/triangle tests, and the same for occlusion-query fragments. This is
    what a CPU rasterizer pays for, so it explains speed on llvmpipe independently of timing
    noise. Off by default: the counting itself costs time."""

    def __init__(self, ctx: moderngl.Context, enabled: bool | None = None):
        self.enabled = os.environ.get("RTWALK_COUNT_WORK", "") == "1" if enabled is None else enabled
        self.buf = ctx.buffer(reserve=4 * 16) if self.enabled else None

    @property
    def defines(self) -> dict[str, object]:
        return {"COUNT_WORK": 1} if self.enabled else {}

    def begin(self) -> None:
        if self.buf is not None:
            self.buf.write(bytes(4 * 16))
            self.buf.bind_to_storage_buffer(BIND_WORK)

    def end(self) -> dict[str, float]:
        if self.buf is None:
            return {}
        self.buf.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)  # SSBO writes -> glGetBufferSubData
        v = np.frombuffer(self.buf.read(), np.uint32)
        return {f"work_{name}": float(v[i]) for i, name in enumerate(WORK_SLOTS)}

    def release(self) -> None:
        if self.buf is not None:
            self.buf.release()


class Backend(Protocol):
    name: str
    description: str

    def trace(self, rays: RayBatch, ray_type: RayType, sample: int, hits: HitBuffer) -> TraceResult:
        """Trace every active ray of `rays` into `hits`. Phases are timed with the profiler."""
        ...

    def begin_frame(self, frame_index: int) -> None:
        """Called before the first pass of a frame (temporal state lives in the backend)."""
        ...

    def release(self) -> None: ...

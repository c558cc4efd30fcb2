"""GL-side pieces of the backend contract (see interface.py for what a backend declares).

A backend receives a `RayBatch` (two RGBA32F textures, one ray per pixel: origin+tmin and
direction+tmax, tmax < 0 marks "no ray") and fills a `HitBuffer` (R32F distance, +inf on a miss;
R32I triangle id in leaf order, -1 on a miss). GL backends draw straight into the hit buffer;
CPU/OpenCL backends call `RayBatch.read()` and `HitBuffer.write()`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import moderngl
import numpy as np

from viewer.gl import io as glio
from viewer.gl.bindings import BIND_WORK
from viewer.gl.programs import ProgramCache
from viewer.profiler import GpuProfiler


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
    gpu_scene: object  # viewer.gl.scene.GpuScene
    scene: object  # viewer.scene.Scene (leaf order)
    bvh: object  # viewer.accel.bvh.BVH


class StatelessBackend:
    """Defaults of the Backend protocol for a backend that keeps nothing between frames and has no
    screen tiles: begin_frame and reset do nothing, tile_level is -1 (no overlay outlines), no
    overlays. A backend with temporal state (chcrt) implements them itself."""

    overlays_enabled: bool = False

    def begin_frame(self, frame_index: int) -> None:
        """Nothing carries over between frames."""

    def reset(self) -> None:
        """No temporal state to forget."""

    def tile_level(self, size: tuple[int, int]) -> int:
        return -1


WORK_SLOTS = ("invocations", "nodes", "box_tests", "tri_tests",
              "query_fragments", "query_nodes", "query_box_tests", "query_tri_tests",
              "subtrees_entered")  # chcrt: scheduled subtrees whose box a ray entered


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
            glio.write(self.buf, bytes(4 * 16))
            self.buf.bind_to_storage_buffer(BIND_WORK)

    def end(self) -> dict[str, float]:
        if self.buf is None:
            return {}
        self.buf.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)  # SSBO writes -> glGetBufferSubData
        v = np.frombuffer(glio.read(self.buf), np.uint32)
        return {f"work_{name}": float(v[i]) for i, name in enumerate(WORK_SLOTS)}

    def release(self) -> None:
        if self.buf is not None:
            self.buf.release()

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
from viewer.gl.bindings import BIND_IMG_WORK_NODES, BIND_IMG_WORK_TRIS, BIND_WORK
from viewer.gl.programs import ProgramCache
from viewer.gl.textures import clear_int_texture
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
# SIMD lane groups of neighbouring pixels, (width, height): llvmpipe with 256-bit vectors shades 8
# fragments at once (a 4x2 half of its 4x4 blocks), an NVIDIA warp 32 (eight 2x2 quads, about 8x4)
LANE_GROUPS = {"simd8": (4, 2), "simd32": (8, 4)}


def lane_group_work(per_pixel: np.ndarray, group: tuple[int, int]) -> float:
    """The work a SIMD machine pays when a group of `group` = (width, height) neighbouring pixels
    runs in lockstep: the sum over the groups of lanes x the group's largest value (every lane waits
    for the busiest; groups at the edges are padded with idle lanes). per_pixel: (H, W) array.
    Divided by the per-pixel sum it is the lanes' wasted share: 1 = every lane equally busy."""
    gw, gh = group
    h, w = per_pixel.shape
    padded = np.zeros((-(-h // gh) * gh, -(-w // gw) * gw))
    padded[:h, :w] = per_pixel
    groups = padded.reshape(padded.shape[0] // gh, gh, padded.shape[1] // gw, gw)
    return float(groups.max(axis=(1, 3)).sum() * gw * gh)


class WorkCounters:
    """Shader work per trace (diagnostics, RTWALK_COUNT_WORK=1): ray-shader invocations, BVH nodes
    fetched, ray/box and ray/triangle tests, and the same for occlusion-query fragments. This is
    what a CPU rasterizer pays for, so it explains speed on llvmpipe independently of timing
    noise. The intersection shaders also add their nodes and triangle tests per pixel, from which
    `work_simdN_nodes` / `work_simdN_tri_tests` count what lane groups pay (LANE_GROUPS,
    lane_group_work): a traversal whose rays' work varies more between neighbours loses more of
    its savings to idle lanes. Off by default: the counting itself costs time."""

    def __init__(self, ctx: moderngl.Context, enabled: bool | None = None):
        self.ctx = ctx
        self.enabled = os.environ.get("RTWALK_COUNT_WORK", "") == "1" if enabled is None else enabled
        self.buf = ctx.buffer(reserve=4 * 16) if self.enabled else None
        self.pixels: list[moderngl.Texture] = []  # R32I per pixel: nodes, triangle tests

    @property
    def defines(self) -> dict[str, object]:
        return {"COUNT_WORK": 1} if self.enabled else {}

    def begin(self, size: tuple[int, int]) -> None:
        """Zero the counters of a trace of `size` (the ray batch's) and bind them."""
        if self.buf is None:
            return
        glio.write(self.buf, bytes(4 * 16))
        self.buf.bind_to_storage_buffer(BIND_WORK)
        if not self.pixels or self.pixels[0].size != tuple(size):
            for tex in self.pixels:
                tex.release()
            self.pixels = [self.ctx.texture(tuple(size), 1, dtype="i4") for _ in range(2)]
        for tex, unit in zip(self.pixels, (BIND_IMG_WORK_NODES, BIND_IMG_WORK_TRIS), strict=True):
            clear_int_texture(tex, 0)
            tex.bind_to_image(unit, read=True, write=True)

    def end(self) -> dict[str, float]:
        if self.buf is None:
            return {}
        self.buf.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)  # SSBO writes -> glGetBufferSubData
        v = np.frombuffer(glio.read(self.buf), np.uint32)
        out = {f"work_{name}": float(v[i]) for i, name in enumerate(WORK_SLOTS)}
        # (a pixel traced by several draws adds them up, so for such a trace the groups' figures
        # are lower bounds: each draw's group waits for its own busiest lane)
        for tex, name in zip(self.pixels, ("nodes", "tri_tests"), strict=False):  # none before begin()
            w, h = tex.size
            per_pixel = np.frombuffer(glio.read(tex), np.int32).reshape(h, w)
            out[f"work_pixel_{name}"] = float(per_pixel.sum(dtype=np.int64))
            for label, group in LANE_GROUPS.items():
                out[f"work_{label}_{name}"] = lane_group_work(per_pixel, group)
        return out

    def release(self) -> None:
        if self.buf is not None:
            self.buf.release()
        for tex in self.pixels:
            tex.release()
        self.pixels = []

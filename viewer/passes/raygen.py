"""Ray generation: one ray per pixel per pass into a RayBatch, counting active rays on the GPU."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.effects import RayType, halton2
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_COUNTERS
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.textures import clear_uint_buffer
from viewer.passes.gbuffer import GBufferPass
from viewer.passes.uniforms import apply
from viewer.rays import DeviceCount, RayBatch


class RayGenPass:
    """Counts each pass's active rays on the device, in its own uint32 slot (the pass's index since
    reset_count; passes beyond MAX_PASS_SLOTS - RAY_TYPES share one slot per ray type, the last
    RAY_TYPES): read_counts sums them per ray type after the frame, and a backend may copy a pass's
    own count (PassInfo.ray_count) instead of counting the rays again."""

    MAX_PASS_SLOTS = 1024
    RAY_TYPES = 8  # read_counts' length, and the shared slots

    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 defines: dict[str, object] | None = None):
        """`defines`: the scene's fetch path (GpuScene.trace_defines)."""
        self.ctx = ctx
        self.program_cache = programs
        self.defines = dict(defines or {})
        self._by_type: dict[RayType, moderngl.Program] = {}  # made on first use, one per ray type
        self.frame_uniforms: dict = {}  # camera and lights of the frame (set_frame_uniforms)
        self.quad = quad
        self.counters = ctx.buffer(reserve=4 * self.MAX_PASS_SLOTS)
        clear_uint_buffer(self.counters, self.MAX_PASS_SLOTS)
        self.readback = glio.ReadBack(ctx, 4 * self.MAX_PASS_SLOTS)  # the host reads the counts here
        self.slot_types: list[RayType] = []  # the ray type of every pass since reset_count

    def program(self, ray_type: RayType) -> moderngl.Program:
        """The ray generation of `ray_type` (raygen.frag with RAY_TYPE: one program per type)."""
        prog = self._by_type.get(ray_type)
        if prog is None:
            prog = self.program_cache.get("fullscreen.vert", "raygen.frag", {**self.defines, "RAY_TYPE": int(ray_type)})
            prog["gId"] = 0
            self._by_type[ray_type] = prog
        return prog

    def set_frame_uniforms(self, values: dict) -> None:
        """The frame's camera and light uniforms, set on each program as it generates rays."""
        self.frame_uniforms = values

    def generate(self, rays: RayBatch, gbuffer: GBufferPass, ray_type: RayType, sample: int,
                 light_index: int, ray_length: float, perturb_rad: float) -> DeviceCount | None:
        """The pass's rays into `rays`; returns where their count is (None: in a slot shared with
        other passes of its type)."""
        shared = self.MAX_PASS_SLOTS - self.RAY_TYPES
        own = len(self.slot_types) < shared
        slot = len(self.slot_types) if own else shared + int(ray_type)
        self.slot_types.append(ray_type)
        p = self.program(ray_type)
        p["countSlot"] = slot
        apply(p, self.frame_uniforms)
        p["lightIndex"] = int(light_index)
        p["sampleUV"] = halton2(sample)
        p["perturbAngle"] = float(perturb_rad)
        p["rayLength"] = float(ray_length)
        p["stream"] = int(ray_type) * 7919 + sample * 104729 + light_index * 15485863
        gbuffer.tri_id.use(0)
        self.counters.bind_to_storage_buffer(BIND_COUNTERS)
        rays.fbo.use()
        self.ctx.disable(self.ctx.BLEND | self.ctx.DEPTH_TEST)
        self.quad.render(p)
        return DeviceCount(self.counters, 4 * slot) if own else None

    def _slots_used(self) -> int:
        """Slots the passes since reset_count wrote: their own, or every slot once they overflowed."""
        n = len(self.slot_types)
        return n if n <= self.MAX_PASS_SLOTS - self.RAY_TYPES else self.MAX_PASS_SLOTS

    def reset_count(self) -> None:
        """Zero the slots of the passes since the last reset (on the device)."""
        clear_uint_buffer(self.counters, self._slots_used())
        self.slot_types = []

    def release(self) -> None:
        self.counters.release()
        self.readback.release()

    def read_counts(self) -> np.ndarray:
        """int64 (RAY_TYPES,): active rays per ray type over the passes since reset_count (one read
        of their slots)."""
        out = np.zeros(self.RAY_TYPES, np.int64)
        used = self._slots_used()
        if used == 0:
            return out
        counts = np.frombuffer(self.readback.read(self.counters, 4 * used), np.uint32).astype(np.int64)
        shared = self.MAX_PASS_SLOTS - self.RAY_TYPES
        for k, ray_type in enumerate(self.slot_types[:shared]):
            out[int(ray_type)] += counts[k]
        if used == self.MAX_PASS_SLOTS:
            out += counts[shared:]
        return out

"""The resumable full BVH traversal shared by the GL backends (trace_glsl_body.glsl).

Long traversals are finished, never cut short: llvmpipe silently ends shader loops after 65,535
loop back-edges per invocation, so each ray visits at most `max_visits` BVH nodes per draw; an
unfinished ray saves its traversal state and further draws continue the unfinished rays until an
atomic counter says none is left (stats: resumed_rays, continuation_draws). The glsl backend traces
every ray with it; chcrt finishes the rays its own shader gave up on. A module of its own so that no
backend imports another. Its shaders (trace_glsl_body.glsl, run by trace_glsl.frag or trace_glsl.comp) live
in the glsl backend's folder.

Only Mesa's CPU rasterizers have that limit (`loop_limit`). Elsewhere (an NVIDIA GPU) a ray may
visit every node in one draw (`max_visits` = the tree's nodes), so no ray is ever unfinished and the
counter is never read: a pass then costs no host wait. RTWALK_LOOP_LIMIT=N|none overrides the choice
(tests run the unlimited path on llvmpipe with short traversals).

Two stages run the same traversal, with the same bits (`STAGES`): a full-screen fragment draw
(trace_glsl.frag, hits through the framebuffer) or a compute dispatch (trace_glsl.comp, hits into an
SSBO, then one full-screen draw, trace_resolve.frag, writes them into the HitBuffer). A GPU may run
compute shaders on many more of its processors than fragment shaders: an NVIDIA H100 or H200 has
its graphics pipeline on a few of them (docs/device-limits.md). The backends choose it
(viewer.gl.stages.resolve_stage: `auto` follows the device).
"""

from __future__ import annotations

import os
from pathlib import Path

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.base import BackendContext, WorkCounters
from viewer.errors import RtwalkError
from viewer.gl import io as glio
from viewer.gl import limits
from viewer.gl.bindings import BIND_IMG_RESUME, BIND_RESUME_COUNTERS, BIND_RESUME_STATE, BIND_TRACE_HITS
from viewer.gl.programs import FullscreenQuad, compute_shader
from viewer.gl.stages import STAGES
from viewer.gl.textures import int_texture
from viewer.rays import HitBuffer, PassInfo, RayBatch

SHADER_DIR = Path(__file__).resolve().parent / "glsl"  # trace_glsl_* live in the glsl backend's folder
LOOP_LIMIT = 65_535  # llvmpipe: loop back-edges per shader invocation, shared by all loops
SIMD_WIDTH = 16  # fragments per llvmpipe shader invocation, assumed wide (8 with 256-bit vectors)


LOOP_LIMIT_ENV = "RTWALK_LOOP_LIMIT"
GROUP = 8  # the compute stage's work groups: GROUP x GROUP pixels (trace_glsl.comp local_size)


def loop_limit_env() -> tuple[bool, int | None]:
    """RTWALK_LOOP_LIMIT: (set, its limit: a number of at least 20,000, or None for `none`); a bad
    value is one line (RtwalkError), checked by the CLI before anything is loaded."""
    text = os.environ.get(LOOP_LIMIT_ENV, "").strip().lower()
    if not text:
        return False, None
    if text in ("none", "off", "0"):
        return True, None
    if not text.isdigit() or int(text) < 20_000:
        raise RtwalkError(f"{LOOP_LIMIT_ENV}={text!r}: give a loop limit of at least 20000, or 'none'")
    return True, int(text)


def loop_limit(ctx: moderngl.Context) -> int | None:
    """Loop back-edges a shader invocation runs before the driver silently ends its loops: LOOP_LIMIT
    on Mesa's CPU rasterizers (llvmpipe, softpipe), None (no limit) on other drivers; the environment
    variable RTWALK_LOOP_LIMIT (a number, or `none`) overrides it."""
    given, limit = loop_limit_env()
    if given:
        return limit
    renderer = str(ctx.info.get("GL_RENDERER", "")).lower()
    return LOOP_LIMIT if ("llvmpipe" in renderer or "softpipe" in renderer) else None


def max_visits(max_leaf: int, stack_size: int, other_loops: int = 0, limit: int = LOOP_LIMIT) -> int:
    """Node visits per ray and draw that keep every SIMD vector below LOOP_LIMIT back-edges.

    Per visit the vector runs one main-loop iteration and at most 2 * max_leaf triangle-loop
    iterations (two leaves); stack pops run in an inner loop whose iterations, summed over the
    vector, are at most SIMD_WIDTH * (visits + stack_size) (a lane pops no more than it pushed plus
    what it resumed with); loading and saving the stack add 2 * stack_size; `other_loops` is what
    the caller's other loops may run. A margin of 5,000 covers everything else."""
    budget = limit - 5_000 - other_loops - (SIMD_WIDTH + 2) * stack_size
    per_visit = 1 + 2 * max_leaf + SIMD_WIDTH
    return max(64, min(4096, budget // per_visit))


def visit_cost(max_leaf: int, loops: int) -> int:
    """`loops` loop back-edges of a SIMD vector in node visits as max_visits counts them (at least
    one): what a shader that runs other loops between its traversals charges to its visit budget."""
    per_visit = 1 + 2 * max_leaf + SIMD_WIDTH
    return max(1, -(-int(loops) // per_visit))


class ResumableTraversal:
    """Full BVH traversal of every ray (trace_glsl_body.glsl) that finishes long traversals in further draws.

    Also finishes rays another GL backend gave up on: its shader marks such a pixel -2 in the slot
    image (image unit BIND_IMG_RESUME) and counts it once in ResumeCounters.unfinished (SSBO
    BIND_RESUME_COUNTERS) after `bind_flags`; `run(..., resume_only=True)` then traces exactly
    those rays from the root and overwrites their hits.

    `stage`: "fragment" or "compute" (STAGES): the same hits either way."""

    def __init__(self, bc: BackendContext, work: WorkCounters | None = None, stage: str = "fragment"):
        if stage not in STAGES:
            raise RtwalkError(f"traversal stage {stage!r}: choose from {', '.join(STAGES)}")
        self.bc = bc
        self.stage = stage
        self.work = work or WorkCounters(bc.ctx, enabled=False)
        hist = getattr(bc.bvh.stats, "leaf_size_histogram", None) or {1: 1}
        self.max_leaf = max(int(k) for k in hist)
        self.stack_size = int(bc.gpu_scene.stack_size)
        bc.gpu_scene.require_nodes()  # the tree this traversal reads (made on first use)
        self.limit = loop_limit(bc.ctx)
        # without a loop limit every ray finishes in its first draw (a ray visits each node at most
        # once): the programs leave the resume code out (RESUMABLE 0, also for the backends whose
        # shaders hand rays over: resume_defines), and nothing is bound, zeroed or read for it
        self.resumable = self.limit is not None
        self.resume_defines = {"RESUMABLE": int(self.resumable)}
        self.max_visits = (max_visits(self.max_leaf, self.stack_size, limit=self.limit) if self.limit is not None
                           else len(bc.bvh.node_left) + 1)
        defines = {"STACK_SIZE": self.stack_size, "MAX_VISITS": self.max_visits, **self.resume_defines,
                   **self.work.defines, **bc.gpu_scene.trace_defines()}
        programs = bc.programs.with_path(SHADER_DIR)
        if stage == "compute":
            self.program = compute_shader(bc.ctx, "trace_glsl.comp", defines, (SHADER_DIR,))
            self.resolve = programs.get("fullscreen.vert", "trace_resolve.frag")
        else:
            self.program = programs.get("fullscreen.vert", "trace_glsl.frag", defines)
            self.resolve = None
        self.program["rayOrigin"] = 0
        self.program["rayDir"] = 1
        self.hit_words: moderngl.Buffer | None = None  # compute stage: 2 words per pixel (trace_glsl.comp)
        self.quad = FullscreenQuad(bc.ctx)
        self.counters = bc.ctx.buffer(reserve=8)
        self._zeros = bc.ctx.buffer(bytes(8))  # copied on the GPU: zeroing the counters sends nothing per pass
        self.capacity = 1024  # resume slots; grows to the number of unfinished rays
        self.state = bc.ctx.buffer(reserve=self.capacity * self._stride_bytes)
        self.slots: moderngl.Texture | None = None  # per pixel resume slot, -1 between traces

    @property
    def _stride_bytes(self) -> int:
        return 4 * (4 + 2 * self.stack_size)

    def _slot_image(self, size: tuple[int, int]) -> moderngl.Texture:
        if self.slots is None or self.slots.size != size:
            if self.slots is not None:
                self.slots.release()
            self.slots = int_texture(self.bc.ctx, size)
            glio.write(self.slots, np.full(size[0] * size[1], -1, np.int32).tobytes())
        return self.slots

    def bind_flags(self, size: tuple[int, int]) -> None:
        """Bind the slot image and zeroed counters (before the draws that may flag pixels); nothing
        where no ray is ever handed over (no loop limit: the programs have no resume code). The
        copy follows the last pass's counter read, whose barrier fenced that pass's shader writes."""
        if not self.resumable:
            return
        self._slot_image(size).bind_to_image(BIND_IMG_RESUME, read=True, write=True)
        self.bc.ctx.copy_buffer(self.counters, self._zeros)
        self.counters.bind_to_storage_buffer(BIND_RESUME_COUNTERS)

    def _read_counters(self) -> tuple[int, int]:
        # (the counters for this read; the saved states and slots for the next draws, also the next
        # pass's: every read waits for the draws anyway, so the other bits cost nothing more)
        self.bc.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT
                                   | moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        unfinished, allocated = np.frombuffer(glio.read(self.counters), np.int32)
        return int(unfinished), int(allocated)

    def _grow(self, needed: int) -> None:
        """Room for `needed` slots, keeping the saved states."""
        cap = max(2 * self.capacity, needed)
        state = self.bc.ctx.buffer(reserve=cap * self._stride_bytes)
        self.bc.ctx.copy_buffer(state, self.state)
        self.state.release()
        self.state = state
        self.capacity = cap

    def run(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer, resume_only: bool = False) -> dict[str, float]:
        """Trace (all rays, or only the flagged ones) until none is unfinished; call bind_flags first.
        Returns stats: draws, resumed_rays (rays not finished by their first draw), continuation_draws."""
        ctx = self.bc.ctx
        barriers = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT
        draws, resumed = 0, 0
        if self.limit is None and resume_only:  # no shader gave a ray up: nothing to read or draw
            return {"draws": 0, "resumed_rays": 0, "continuation_draws": 0}
        if resume_only:
            resumed, _ = self._read_counters()
            if resumed == 0:
                return {"draws": 0, "resumed_rays": 0, "continuation_draws": 0}
            ctx.memory_barrier(barriers)
            ctx.copy_buffer(self.counters, self._zeros)
        # a ray visits each node at most once: a draw that does not finish it advances it by max_visits
        # (or gives it a slot, once), so this many draws always suffice
        max_draws = 4 + 2 * (len(self.bc.bvh.node_left) // self.max_visits + 1)
        self.bc.gpu_scene.bind()
        rays.origin.use(0)
        rays.direction.use(1)
        self.program["anyHit"] = int(pinfo.any_hit)
        compute = self.resolve is not None
        if compute:
            self._bind_hit_words(hits.size)
        else:
            hits.fbo.use()
            ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        while True:
            self.state.bind_to_storage_buffer(BIND_RESUME_STATE)
            self.program["resume"] = int(draws > 0 or resume_only)
            self.program["capacity"] = self.capacity
            if compute:
                self.program["firstDispatch"] = int(draws == 0)
                w, h = hits.size
                self.program.run(-(-w // GROUP), -(-h // GROUP))
                iostats.gl_draw()
            else:
                self.quad.render(self.program)
            draws += 1
            if self.limit is None:  # every ray finished in this draw (max_visits covers the tree): no read
                break
            unfinished, allocated = self._read_counters()
            if draws == 1 and not resume_only:
                resumed = unfinished
            if unfinished == 0:
                break
            if draws >= max_draws:
                raise RtwalkError(f"{unfinished} rays still unfinished after {draws} traversal draws")
            ctx.memory_barrier(barriers)
            if allocated > self.capacity:  # some rays got no slot (-2): make room, they restart
                used = self.capacity
                self._grow(allocated)
                glio.write(self.counters, np.array([0, used], np.int32).tobytes())
            else:
                glio.write(self.counters, np.array([0, allocated], np.int32).tobytes())
        if compute:
            self._resolve(hits)
        return {"draws": draws, "resumed_rays": resumed,
                "continuation_draws": draws - (0 if resume_only else 1)}

    def _bind_hit_words(self, size: tuple[int, int]) -> None:
        """The compute stage's hit words for `size`, bound; the dispatches write them after every
        earlier access to the hits (the resolve draw's reads of the last pass included)."""
        nbytes = 8 * size[0] * size[1]
        if self.hit_words is None or self.hit_words.size < nbytes:
            limits.check_storage_block(self.bc.ctx, nbytes, f"the compute traversal's hits at {size[0]}x{size[1]}")
            if self.hit_words is not None:
                self.hit_words.release()
            self.hit_words = self.bc.ctx.buffer(reserve=nbytes)
        self.bc.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.hit_words.bind_to_storage_buffer(BIND_TRACE_HITS)
        self.program["raySize"] = tuple(int(v) for v in size)

    def _resolve(self, hits: HitBuffer) -> None:
        """The compute stage's hits into the HitBuffer (trace_resolve.frag), after the dispatches'
        writes; the draw leaves the attachments as a fragment stage's draw would."""
        ctx = self.bc.ctx
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.hit_words.bind_to_storage_buffer(BIND_TRACE_HITS)
        self.resolve["width"] = int(hits.size[0])
        hits.fbo.use()
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        self.quad.render(self.resolve)

    def release(self) -> None:
        if self.hit_words is not None:
            self.hit_words.release()
            self.hit_words = None
        for obj in (self.counters, self._zeros, self.state, self.slots):
            if obj is not None:
                obj.release()
        self.slots = None

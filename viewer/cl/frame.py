"""The device-resident frame for OpenCL backends: rays are generated, traced and accumulated on the
CL device, so per frame only the G-buffer's triangle ids cross to OpenCL (4 bytes per pixel) and
the accumulators of the effects in use cross back to GL (16 bytes per pixel each), whatever the
number of passes.

Path selection is by capability (`frame_path`): a backend whose BackendInfo.device is "cl" and
that implements `trace_device` gets this staged path; GL backends, overlay frames and CL backends
without `trace_device` keep the per-pass RayBatch path. The staged path fits llvmpipe + PoCL,
which share no memory objects (no cl_khr_gl_sharing). Hook for a zero-copy path: where the CL
device has cl_khr_external_memory_opaque_fd (+ cl_khr_external_semaphore_opaque_fd) and GL has
GL_EXT_memory_object_fd (NVIDIA), the id texture and the accumulation textures can be backed by
memory both APIs import, so `upload_ids` and `write_accumulators` become semaphore waits
(`interop_available` reports the capability; `frame_path` returns "interop" there once an
implementation exists — today it still returns "staged").

Buffers (n = width * height, row-major, row 0 = bottom):
  ids    int[n]          the G-buffer's triangle id per pixel (-1 background), read once per frame
  rays   RayStage        origin float4 (x, y, z, tmin), dir float4 (dx, dy, dz, tmax)
  hits   HitStage        t float (+inf miss), tri int (-1 miss)
  acc    float4[n] per accumulated effect (passes.accumulate.ACCUMULATED), summed over passes
  counts uint[8]         active rays per ray type (raygen), read once per frame (with the
                         accumulators' reads: request_counts / read_counts)
  tris   GPU_TRI_DTYPE (48 B per triangle), mats float4 per material: once per scene change
  params float4[FRAME_PARAMS] the frame's camera and lights (frame.cl's P_* layout)
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

import viewer.cl.io as clio
from viewer.cl.context import ClContext, cl_context
from viewer.cl.programs import build
from viewer.cl.transfer import HitStage, RayStage, mapped
from viewer.effects import RayType

PATH_ENV = "RTWALK_FRAME_PATH"
FRAME_PARAMS = 38  # float4 slots (frame.cl: P_RECT_RAD + 4)
WG = 64
MAX_COUNTERS = 8


def interop_available(ctx: ClContext | None = None, gl_extensions: set[str] | frozenset[str] = frozenset()) -> bool:
    """Whether a zero-copy GL/CL interop path could be used here (external memory on both sides)."""
    ctx = ctx or cl_context()
    ext = str(ctx.device.extensions).split()
    return ("cl_khr_external_memory_opaque_fd" in ext and "cl_khr_external_semaphore_opaque_fd" in ext
            and "GL_EXT_memory_object_fd" in gl_extensions)


def frame_path(backend: Any, overlays: bool = False) -> str:
    """"device": the CL-resident frame (this module, staged through host memory); "batch": the
    per-pass RayBatch path (GL backends, overlay frames, CL backends without trace_device).
    RTWALK_FRAME_PATH=batch forces the RayBatch path (comparisons, a fallback)."""
    if os.environ.get(PATH_ENV, "").strip().lower() == "batch":
        return "batch"
    if overlays or backend.info.device != "cl" or not callable(getattr(backend, "trace_device", None)):
        return "batch"
    return "device"


def frame_params(cam_u: dict, light_u: dict) -> np.ndarray:
    """The camera and light uniforms (passes.uniforms) packed as frame.cl's P_* float4 slots."""
    p = np.zeros((FRAME_PARAMS, 4), np.float32)
    p[0, :3], p[0, 3] = cam_u["camPos"], cam_u["tanHalfFov"]
    p[1, :3], p[1, 3] = cam_u["camRight"], cam_u["viewport"][0]
    p[2, :3], p[2, 3] = cam_u["camUp"], cam_u["viewport"][1]
    p[3, :3], p[3, 3] = cam_u["camForward"], light_u["ambient"]
    p[4, :3], p[4, 3] = light_u["skyColor"], light_u["lightRadius"]
    p[5, 0], p[5, 1] = light_u["numPointLights"], light_u["numRectLights"]
    for base, key in ((6, "pointPos"), (14, "pointIntensity"), (22, "rectCorner"), (26, "rectU"), (30, "rectV"),
                      (34, "rectRadiance")):
        vals = np.asarray(light_u[key], np.float32).reshape(-1, 3)
        p[base:base + len(vals), :3] = vals
    return p


class DeviceFrame:
    """CL buffers and kernels of the device-resident frame (see the module docstring)."""

    def __init__(self, ctx: ClContext | None = None):
        self.ctx = ctx or cl_context()
        prog = build("frame.cl", {}, self.ctx)
        self.k_raygen = clio.kernel(prog, "raygen")
        self.k_accumulate = clio.kernel(prog, "accumulate")
        self.k_surface = clio.kernel(prog, "surface")
        mf = self.ctx.cl.mem_flags
        self.params = self.ctx.cl.Buffer(self.ctx.context, mf.READ_ONLY, FRAME_PARAMS * 16)
        self.counts = self.ctx.cl.Buffer(self.ctx.context, mf.READ_WRITE, 4 * MAX_COUNTERS)
        self._params_host = np.zeros((FRAME_PARAMS, 4), np.float32)  # kept alive for the async write
        self.size: tuple[int, int] | None = None
        self.ids = self.rays = self.hits = None
        self.surf: tuple = ()
        self._surfaces_of = -1  # the G-buffer draw whose ids and surfaces `ids` and `surf` hold (-1: none)
        self.acc: dict[RayType, Any] = {}
        self.tris = self.mats = None
        self.scene_key: tuple | None = None
        self._counts_host: np.ndarray | None = None  # the counts' pending read (request_counts)
        self._counts_waited = False

    # -- per scene --------------------------------------------------------------------------
    def set_scene(self, scene: Any) -> None:
        """Triangles (leaf order) and materials into CL buffers, again only when the geometry
        changed (scene identity and geometry_version)."""
        key = (id(scene.triangles), scene.geometry_version, scene.triangle_count)
        if key == self.scene_key:
            return
        self.release_scene()
        # the packing the GL scene made too, read in place (USE_HOST_PTR: on a CPU device no copy and
        # no fresh pages, 0.5-1.9 s of a 10 M first frame; the scene's cached array outlives it)
        self.tris = clio.upload(self.ctx, scene.gpu_triangles(), use_host=True)
        self.mats = clio.upload(self.ctx, scene.albedo_table())
        self.scene_key = key

    # -- per size ---------------------------------------------------------------------------
    def resize(self, size: tuple[int, int]) -> None:
        size = (int(size[0]), int(size[1]))
        if size == self.size:
            return
        self.release_targets()
        n = size[0] * size[1]
        mf = self.ctx.cl.mem_flags
        self.ids = self.ctx.cl.Buffer(self.ctx.context, mf.READ_WRITE | mf.ALLOC_HOST_PTR, 4 * n)
        # per pixel, made once per frame on the device: normal, secondary-ray origin, G-buffer position
        self.surf = tuple(self.ctx.cl.Buffer(self.ctx.context, mf.READ_WRITE, 16 * n) for _ in range(3))
        self.rays = RayStage(size, self.ctx, "rw")  # written by raygen, read by the tracer
        self.hits = HitStage(size, self.ctx, "rw")  # written by the tracer, read by accumulate
        self.size = size

    def _acc(self, rt: RayType) -> Any:
        buf = self.acc.get(rt)
        if buf is None:
            n = self.size[0] * self.size[1]
            mf = self.ctx.cl.mem_flags
            buf = self.ctx.cl.Buffer(self.ctx.context, mf.READ_WRITE | mf.ALLOC_HOST_PTR, 16 * n)
            self.acc[rt] = buf
            self.ctx.cl.enqueue_fill_buffer(self.ctx.queue, buf, np.float32(0), 0, 16 * n)
        return buf

    # -- per frame --------------------------------------------------------------------------
    def begin(self, size: tuple[int, int], id_texture: Any, cam_u: dict, light_u: dict, keep: bool,
              gbuffer_drawn: int = -1) -> None:
        """Read the G-buffer ids into CL (one staged copy) and make the per-pixel surfaces, write the
        frame's parameters, and clear the accumulators. With `keep` (more sample passes added to the
        previous call's, same camera) the accumulators are kept, and the ids and surfaces already
        here are reused where they come from the same G-buffer draw (`gbuffer_drawn`, the renderer's
        count of draws; -1: unknown, read again) at the same size."""
        reuse = (keep and self.size == (int(size[0]), int(size[1])) and gbuffer_drawn >= 0
                 and self._surfaces_of == gbuffer_drawn)
        self.resize(size)
        n = self.size[0] * self.size[1]
        q = self.ctx.queue
        if not reuse:
            with mapped(self.ctx, self.ids, (n,), np.int32, write=True) as a:
                id_texture.read_into(a)  # a staged GL -> CL hop: counted once, by the map
        self._params_host[...] = frame_params(cam_u, light_u)
        clio.copy(q, self.params, self._params_host, is_blocking=False)
        self.ctx.cl.enqueue_fill_buffer(q, self.counts, np.uint32(0), 0, 4 * MAX_COUNTERS)
        w, h = self.size
        if not reuse:
            self.k_surface(q, self._gsize(), (WG,), self.ids, self.tris, self.params, np.int32(w), np.int32(h),
                           *self.surf)
            self._surfaces_of = gbuffer_drawn
        if not keep:
            for buf in self.acc.values():
                self.ctx.cl.enqueue_fill_buffer(q, buf, np.float32(0), 0, 16 * n)

    def _gsize(self) -> tuple[int]:
        n = self.size[0] * self.size[1]
        return (-(-n // WG) * WG,)

    def generate(self, ray_type: RayType, sample: int, light: int, ray_length: float, perturb_rad: float) -> None:
        """raygen.frag's rays of one pass into `self.rays` (and its active rays into the counts)."""
        from viewer.effects import halton2

        w, h = self.size
        stream = (int(ray_type) * 7919 + sample * 104729 + light * 15485863) & 0xFFFFFFFF
        self.k_raygen(self.ctx.queue, self._gsize(), (WG,), self.ids, self.tris, self.mats, self.surf[0],
                      self.surf[1], self.params,
                      np.int32(w), np.int32(h), np.int32(int(ray_type)), np.int32(light),
                      np.array(halton2(sample), np.float32), np.float32(perturb_rad), np.float32(ray_length),
                      np.uint32(stream), self.rays.origin, self.rays.dir, self.counts)

    def accumulate(self, ray_type: RayType, light: int, weight: float) -> None:
        """accumulate.frag: add the traced pass (self.rays, self.hits) to its effect's accumulator."""
        w, h = self.size
        self.k_accumulate(self.ctx.queue, self._gsize(), (WG,), self.ids, self.tris, self.mats, self.surf[0],
                          self.surf[2], self.params,
                          np.int32(w), np.int32(h), np.int32(int(ray_type)), np.int32(light), np.float32(weight),
                          self.rays.origin, self.rays.dir, self.hits.t, self.hits.tri, self._acc(ray_type))

    def write_accumulators(self, textures: dict, effects) -> None:
        """The accumulators of `effects` into their GL textures (a staged CL -> GL hop each): every
        accumulator mapped for reading without a wait (host-allocated buffers: no copy on a CPU
        device), then one wait for all of them (and for the ray counts' read before them), so the
        frame waits once whatever the number of effects; each hop is counted once, by its map."""
        n = self.size[0] * self.size[1]
        q = self.ctx.queue
        maps = []
        for rt in effects:
            buf = self.acc.get(rt)
            if buf is None:
                continue
            array, _ = clio.map_buffer(q, buf, self.ctx.cl.map_flags.READ, 0, (n, 4), np.float32, is_blocking=False)
            maps.append((rt, array))
        if not maps:
            return
        clio.finish(q)
        self._counts_waited = True  # earlier commands (the counts' read) are done too
        for rt, array in maps:
            textures[rt].write(array)
            array.base.release(q)

    def request_counts(self) -> None:
        """Enqueue the ray counts' read without waiting: a later blocking read or map on the
        (in-order) queue completes it, so the counts cost no host sync of their own."""
        self._counts_host = np.zeros(MAX_COUNTERS, np.uint32)
        clio.copy(self.ctx.queue, self._counts_host, self.counts, is_blocking=False)
        self._counts_waited = False

    def read_counts(self) -> np.ndarray:
        """The active rays per ray type: from `request_counts` when a blocking read has waited for
        it since (write_accumulators), else read now."""
        if getattr(self, "_counts_host", None) is None:
            self.request_counts()
        if not self._counts_waited:
            clio.finish(self.ctx.queue)
        out, self._counts_host = self._counts_host, None
        return out.astype(np.int64)

    # -- release ----------------------------------------------------------------------------
    def release_scene(self) -> None:
        for b in (self.tris, self.mats):
            if b is not None:
                b.release()
        self.tris = self.mats = None
        self.scene_key = None
        self._surfaces_of = -1  # made from the old triangles

    def release_targets(self) -> None:
        for part in (self.rays, self.hits):
            if part is not None:
                part.release()
        if self.ids is not None:
            self.ids.release()
            for b in self.surf:
                b.release()
        for buf in self.acc.values():
            buf.release()
        self.acc = {}
        self.ids = self.rays = self.hits = None
        self.surf = ()
        self._surfaces_of = -1
        self.size = None

    def release(self) -> None:
        self.release_targets()
        self.release_scene()
        self.params.release()
        self.counts.release()

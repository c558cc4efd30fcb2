"""clbvh: the OpenCL baseline. One work-item per ray traverses a 4-wide BVH from the root.

The BVH4 is collapsed from the renderer's SAH binary BVH (viewer.accel.bvh4), so triangle ids
are the same leaf-order slots as for every backend. Kernels (trace.cl beside this file, tests
from viewer/cl/kernels/geometry.cl) follow glsl's conventions: watertight triangle test with the
double fallback, conservative slab test, safe reciprocals, hits only for tmin < t < tmax; the
any-hit kernel (shadow, soft, AO) exits on the first hit.

Per pass: the ray textures are read into mapped CL buffers (phase "clbvh:upload"), the kernel
runs (phase "trace:<ray type>", as glsl's draw), the hits are written back to the hit textures
("clbvh:download"). The work-group size is fixed (WG): PoCL compiles one work-group function
per size, and the size made no difference to speed in a prototype on this machine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from viewer.accel.bvh4 import BVH4, build_bvh4
from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.interface import BackendInfo
from viewer.rays import HitBuffer, PassInfo, RayBatch

KERNEL = Path(__file__).resolve().parent / "trace.cl"
WG = 64
MAX_STACK = 256  # private stack entries the kernel may hold (3 per BVH4 level)


def pack_triangles(triangles: np.ndarray) -> np.ndarray:
    """float32 (N, 3, 4): the three vertices of each triangle as float4 (w = 0), leaf order."""
    t = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
    out = np.zeros((max(len(t), 1), 3, 4), np.float32)
    out[: len(t), :, :3] = t
    return out


class ClbvhScene:
    """The BVH4 and the leaf-ordered triangles in CL buffers, plus the built kernels."""

    def __init__(self, triangles: np.ndarray, bvh, ctx=None):
        from viewer.cl import build, cl_context

        self.ctx = ctx or cl_context()
        self.bvh4: BVH4 = build_bvh4(bvh)
        self.stack_size = self.bvh4.stack_size()
        assert self.stack_size <= MAX_STACK, f"BVH4 depth {self.bvh4.depth} needs {self.stack_size} stack entries"
        cl = self.ctx.cl
        mf = cl.mem_flags
        self.nodes = cl.Buffer(self.ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=self.bvh4.nodes)
        self.tris = cl.Buffer(self.ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=pack_triangles(triangles))
        prog = build(KERNEL, {"STACK_SIZE": self.stack_size, "WG": WG}, self.ctx)
        self.kernels = {False: cl.Kernel(prog, "trace_closest"), True: cl.Kernel(prog, "trace_any")}
        self.memory_bytes = self.bvh4.memory_bytes + self.tris.size

    def enqueue(self, ray_o, ray_d, out_t, out_id, n: int, any_hit: bool):
        """Enqueue the trace of n rays (buffers as viewer/cl/transfer.py lays them out)."""
        if n == 0:
            return None
        gsize = -(-n // WG) * WG
        return self.kernels[bool(any_hit)](self.ctx.queue, (gsize,), (WG,), self.nodes, self.tris,
                                           ray_o, ray_d, out_t, out_id, np.int32(n))

    def release(self) -> None:
        self.nodes.release()
        self.tris.release()


class ClbvhBackend:
    info = BackendInfo("clbvh", "OpenCL: one work-item per ray walks a 4-wide BVH (float4 child tests) from the root",
                       counters=("rays",), device="cl")

    def __init__(self, bc: BackendContext, params: None = None):
        from viewer.cl import cl_context

        self.bc = bc
        self.params = params
        self.overlays_enabled = False
        self.ctx = cl_context()
        self.scene = ClbvhScene(bc.scene.triangles, bc.bvh, self.ctx)
        self._stages = None  # (size, RayStage, HitStage)

    def _staged(self, size: tuple[int, int]):
        from viewer.cl import HitStage, RayStage

        size = (int(size[0]), int(size[1]))
        if self._stages is None or self._stages[0] != size:
            self._release_stages()
            self._stages = (size, RayStage(size, self.ctx), HitStage(size, self.ctx))
        return self._stages[1], self._stages[2]

    def begin_frame(self, frame_index: int) -> None:
        pass

    def reset(self) -> None:
        pass

    def tile_level(self, size: tuple[int, int]) -> int:
        return -1

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        prof = self.bc.profiler
        rs, hs = self._staged(rays.size)
        q = self.ctx.queue
        with prof.cl_phase("clbvh:upload", q):
            rs.upload(rays)
        with prof.cl_phase(f"trace:{pinfo.ray_type.label}", q):
            self.scene.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit)
        with prof.cl_phase("clbvh:download", q):
            hs.download(hits)
        return TraceResult(stats={"rays": rs.n})

    def _release_stages(self) -> None:
        if self._stages is not None:
            self._stages[1].release()
            self._stages[2].release()
            self._stages = None

    def release(self) -> None:
        self._release_stages()
        self.scene.release()

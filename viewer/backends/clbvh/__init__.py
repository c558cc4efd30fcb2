"""clbvh: the OpenCL baseline. One work-item per ray traverses a 4-wide BVH from the root.

The BVH4 is collapsed from the renderer's binary BVH (viewer.accel.bvh4, on the device with
viewer.accel.bvh4_device when it has float64: the same nodes), so triangle ids
are the same leaf-order slots as for every backend. Kernels (trace.cl beside this file, tests
from viewer/cl/kernels/geometry.cl) follow glsl's conventions: watertight triangle test with the
double fallback, conservative slab test, safe reciprocals, hits only for tmin < t < tmax; the
any-hit kernel (shadow, soft, AO) exits on the first hit.

Device-resident frames (viewer.cl.frame, the renderer's choice for CL backends): `trace_device`
traces the frame's CL ray buffers into its CL hit buffers, nothing crosses per pass; the `rays`
counter sums over the frame on the device and is read once (`end_frame`).

RayBatch frames (overlays, tools): per pass the ray textures are read into mapped CL buffers
(phase "clbvh:upload"), the kernel runs (phase "trace:<ray type>", as glsl's draw), the hits are
written back to the hit textures ("clbvh:download"). The kernel also counts the active rays, the
`rays` counter: the first
work-item of each work-group counts its group's, one global atomic per work-group, no barrier
(measured: no cost against the kernel without the count). The work-group size is fixed (WG):
PoCL compiles one work-group function per size, and the size made no difference to speed in a
prototype on this machine.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from viewer.accel.bvh4 import BVH4, NODE4_DTYPE, build_bvh4
from viewer.accel.bvh4_device import build_bvh4_device, device_supported
from viewer.backends.base import BackendContext, StatelessBackend, TraceResult
from viewer.backends.interface import BackendInfo
from viewer.cl import io as clio
from viewer.rays import HitBuffer, PassInfo, RayBatch

KERNEL = Path(__file__).resolve().parent / "trace.cl"
PACK_KERNEL = Path(__file__).resolve().parent / "pack.cl"
WG = 64
MAX_STACK = 256  # private stack entries the kernel may hold (3 per BVH4 level)
DEVICE_BVH4_MIN_NODES = 200_000  # binary nodes from which the BVH4 collapse runs on the device


#: A leaf block: up to four triangles of one leaf in SoA form (one float4 lane per triangle, NaN
#: padding), then the first triangle slot of the block and its triangle count.
LEAF_BLOCK_DTYPE = np.dtype([("v", "<f4", (9, 4)), ("first", "<i4"), ("count", "<i4"), ("pad", "<i4", 2)])
assert LEAF_BLOCK_DTYPE.itemsize == 160


def leaf_block_index(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kernel nodes with leaf refs ~first_block, first slot and triangle count of each block).

    A leaf of c triangles (slots first .. first+c-1, leaf order) becomes ceil(c / 4) consecutive
    blocks. Vectorised over leaves (integers only: the triangles are packed by pack_leaves or,
    in ClbvhScene, on the device)."""
    child, count = nodes["child"], nodes["count"]
    is_leaf = (child < 0) & (count > 0)
    first = (~child[is_leaf]).astype(np.int64)
    cnt = count[is_leaf].astype(np.int64)
    nblk = (cnt + 3) // 4
    blk_start = np.cumsum(nblk) - nblk
    out_nodes = nodes.copy()
    kchild = out_nodes["child"]
    kchild[is_leaf] = ~blk_start
    n_blocks = int(nblk.sum())
    if np.all(nblk == 1):  # the usual case (leaves of at most 4 triangles): one block per leaf
        return out_nodes, first.astype(np.int32), cnt.astype(np.int32)
    leaf_of = np.repeat(np.arange(len(first)), nblk)
    k = np.arange(n_blocks) - blk_start[leaf_of]  # block number inside its leaf
    b_first = first[leaf_of] + 4 * k
    b_count = np.minimum(cnt[leaf_of] - 4 * k, 4)
    return out_nodes, b_first.astype(np.int32), b_count.astype(np.int32)


def pack_leaves(nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kernel copies of a BVH4 on the host: (nodes with leaf refs ~first_block, LEAF_BLOCK_DTYPE
    blocks); v[3 * vertex + axis, lane] holds the coordinate of slot first + lane, NaN padding.
    The reference for pack.cl (ClbvhScene packs on the device)."""
    tris = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
    out_nodes, b_first, b_count = leaf_block_index(nodes)
    n_blocks = len(b_first)
    blocks = np.zeros(max(n_blocks, 1), LEAF_BLOCK_DTYPE)
    if n_blocks:
        lane = np.arange(4)
        valid = lane[None, :] < b_count[:, None]  # (B, 4)
        slot = np.where(valid, b_first[:, None] + lane[None, :], 0)
        v = tris[slot].reshape(n_blocks, 4, 9)  # (B, lane, vertex*3 + axis)
        v = np.where(valid[:, :, None], v, np.float32(np.nan))
        blocks["v"] = v.transpose(0, 2, 1)
        blocks["first"] = b_first
        blocks["count"] = b_count
    return out_nodes, blocks


def pack_leaves_device(ctx, nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, object]:
    """pack_leaves with the blocks written by pack.cl straight into a device buffer: the
    triangles are read in place (USE_HOST_PTR) and no host copy of the blocks is made (at 10 M
    triangles the host packing and its upload were 5 s of the first frame). One host sync."""
    from viewer.cl import build
    from viewer.cl.limits import new_buffer

    tris = np.ascontiguousarray(triangles, np.float32).reshape(-1, 9)
    out_nodes, b_first, b_count = leaf_block_index(nodes)
    n_blocks = len(b_first)
    mf = ctx.cl.mem_flags
    blocks = new_buffer(ctx, mf.READ_WRITE, max(n_blocks, 1) * LEAF_BLOCK_DTYPE.itemsize, "clbvh leaf blocks")
    if n_blocks:
        k = clio.kernel(build(PACK_KERNEL, {}, ctx), "pack_blocks")
        src = clio.upload(ctx, tris, what="clbvh triangles", use_host=True)
        bf = clio.upload(ctx, b_first, what="clbvh block slots")
        bn = clio.upload(ctx, b_count, what="clbvh block counts")
        k(ctx.queue, (-(-n_blocks // WG) * WG,), (WG,), src, np.uint32(n_blocks), bf, bn, blocks)
        clio.finish(ctx.queue)  # the triangles are read in place: done before the caller may free them
        for buf in (src, bf, bn):
            buf.release()
    return out_nodes, blocks


def pack_device_bvh4(ctx, nodes_buf, n4: int, triangles: np.ndarray) -> tuple[object, object]:
    """(kernel nodes, leaf blocks) as device buffers from a BVH4 already on the device
    (viewer.accel.bvh4_device) whose leaves hold at most 4 triangles: leaf slots counted per node,
    the project's scan numbers the blocks row-major (as leaf_block_index), `kernel_nodes` writes
    the nodes with block refs, pack_blocks the blocks. Nothing crosses but the scan's total; at
    10 M triangles the host index and the node upload were 1.5-2 s of the first frame."""
    from viewer.cl import build
    from viewer.cl.limits import new_buffer
    from viewer.cl.primitives import primitives

    prog = build(PACK_KERNEL, {}, ctx)
    k = clio.kernels(prog, ("leaf_slots", "kernel_nodes", "pack_blocks"))
    mf = ctx.cl.mem_flags
    q, u = ctx.queue, np.uint32
    g = (-(-n4 // WG) * WG,)
    slots, offset = (new_buffer(ctx, mf.READ_WRITE, 4 * n4, "clbvh leaf slots") for _ in range(2))
    k["leaf_slots"](q, g, (WG,), u(n4), nodes_buf, slots)
    n_blocks = primitives(ctx).exclusive_scan(slots, offset, n4)
    knodes = new_buffer(ctx, mf.READ_ONLY, n4 * NODE4_DTYPE.itemsize, "clbvh nodes")
    first, count = (new_buffer(ctx, mf.READ_WRITE, 4 * max(n_blocks, 1), "clbvh blocks") for _ in range(2))
    k["kernel_nodes"](q, g, (WG,), u(n4), nodes_buf, offset, knodes, first, count)
    blocks = new_buffer(ctx, mf.READ_WRITE, max(n_blocks, 1) * LEAF_BLOCK_DTYPE.itemsize, "clbvh leaf blocks")
    tris = np.ascontiguousarray(triangles, np.float32).reshape(-1, 9)
    src = clio.upload(ctx, tris, what="clbvh triangles", use_host=True)
    k["pack_blocks"](q, (-(-max(n_blocks, 1) // WG) * WG,), (WG,), src, u(n_blocks), first, count, blocks)
    clio.finish(q)  # the triangles are read in place: done before the caller may free them
    for buf in (slots, offset, first, count, src):
        buf.release()
    return knodes, blocks


class ClbvhScene:
    """The BVH4 and the leaf-ordered triangles in CL buffers, plus the built kernels."""

    def __init__(self, triangles: np.ndarray, bvh, ctx=None):
        from viewer.cl import build, cl_context

        self.ctx = ctx or cl_context()
        self._bvh4_buf = None  # the device collapse's node buffer (self.bvh4's arrays view it)
        self.bvh4: BVH4
        # big trees collapse on the device (same nodes, 2-3x faster at 10 M triangles; one host
        # read per BVH4 level); small ones, e.g. an animated scene's per-frame collapse, on the host
        if len(bvh.node_left) >= DEVICE_BVH4_MIN_NODES and device_supported(self.ctx):
            self.bvh4, self._bvh4_buf = build_bvh4_device(bvh, self.ctx)
        else:
            self.bvh4 = build_bvh4(bvh)
        self.stack_size = self.bvh4.stack_size()
        assert self.stack_size <= MAX_STACK, f"BVH4 depth {self.bvh4.depth} needs {self.stack_size} stack entries"
        cl = self.ctx.cl
        mf = cl.mem_flags
        n4 = len(self.bvh4.nodes)
        if self._bvh4_buf is not None and int(self.bvh4.nodes["count"].max()) <= 4:  # one block a leaf
            self.nodes, self.blocks = pack_device_bvh4(self.ctx, self._bvh4_buf, n4, triangles)
        else:
            knodes, self.blocks = pack_leaves_device(self.ctx, self.bvh4.nodes, triangles)
            self.nodes = clio.upload(self.ctx, knodes, what="clbvh nodes")
        prog = build(KERNEL, {"STACK_SIZE": self.stack_size, "WG": WG}, self.ctx)
        self.kernels = {False: clio.kernel(prog, "trace_closest"), True: clio.kernel(prog, "trace_any")}
        self.memory_bytes = self.nodes.size + self.blocks.size
        self.active = cl.Buffer(self.ctx.context, mf.READ_WRITE, 4)  # active rays of the last enqueue

    def enqueue(self, ray_o, ray_d, out_t, out_id, n: int, any_hit: bool, reset: bool = True):
        """Enqueue the trace of n rays (buffers as viewer/cl/transfer.py lays them out); the kernel
        counts the active ones into `self.active` (read with active_count), zeroed first unless
        `reset` is False (the count then sums over enqueues: a device-resident frame's passes)."""
        q = self.ctx.queue
        if reset:
            self.reset_count()
        if n == 0:
            return None
        gsize = -(-n // WG) * WG
        return self.kernels[bool(any_hit)](q, (gsize,), (WG,), self.nodes, self.blocks,
                                           ray_o, ray_d, out_t, out_id, np.int32(n), self.active)

    def reset_count(self) -> None:
        self.ctx.cl.enqueue_fill_buffer(self.ctx.queue, self.active, np.int32(0), 0, 4)

    def active_count(self) -> int:
        """Active rays of the last enqueue (a 4-byte blocking read: waits for the kernel)."""
        out = np.zeros(1, np.int32)
        clio.copy(self.ctx.queue, out, self.active)
        return int(out[0])

    def release(self) -> None:
        self.nodes.release()
        self.blocks.release()
        self.active.release()
        self._bvh4_buf = None  # freed with the last view of it (self.bvh4)


class ClbvhBackend(StatelessBackend):
    info = BackendInfo("clbvh", "OpenCL: one work-item per ray walks a 4-wide BVH (float4 child tests) from the root",
                       counters=("rays",), device="cl")

    def __init__(self, bc: BackendContext, params: None = None):
        from viewer.cl import PassStages, cl_context

        self.bc = bc
        self.params = params
        self.ctx = cl_context()
        self.scene = ClbvhScene(bc.scene.triangles, bc.bvh, self.ctx)
        self.stages = PassStages(self.ctx)
        self._device_frame = False  # this frame's passes came through trace_device

    def begin_frame(self, frame_index: int) -> None:
        self._device_frame = False

    def scene_changed(self, bc: BackendContext) -> None:
        """Rebuild the BVH4 (collapsed from the refitted binary BVH) and re-upload it with the
        moved triangles (phase "build:bvh4")."""
        self.bc = bc
        t0 = time.perf_counter()
        self.scene.release()
        self.scene = ClbvhScene(bc.scene.triangles, bc.bvh, self.ctx)
        ms = (time.perf_counter() - t0) * 1e3
        bc.profiler.record("build:bvh4", ms, ms)

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        prof = self.bc.profiler
        rs, hs = self.stages.get(rays.size)
        q = self.ctx.queue
        with prof.cl_phase("clbvh:upload", q):
            rs.upload(rays)
        with prof.cl_phase(f"trace:{pinfo.ray_type.label}", q):
            self.scene.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit)
        with prof.cl_phase("clbvh:download", q):
            hs.download(hits)
        return TraceResult(stats={"rays": self.scene.active_count()})  # the pass's active rays

    def trace_device(self, rays, pinfo: PassInfo, hits) -> TraceResult:
        """Trace CL ray buffers (viewer.cl.RayStage layout) into CL hit buffers (HitStage): no
        transfer, no host wait."""
        if not self._device_frame:
            self.scene.reset_count()
            self._device_frame = True
        with self.bc.profiler.cl_phase(f"trace:{pinfo.ray_type.label}", self.ctx.queue):
            self.scene.enqueue(rays.origin, rays.dir, hits.t, hits.tri, rays.n, pinfo.any_hit, reset=False)
        return TraceResult()

    def end_frame(self) -> dict[str, float]:
        """Counters of a device-resident frame: its active rays (one 4-byte read)."""
        return {"rays": float(self.scene.active_count())} if self._device_frame else {}

    def release(self) -> None:
        self.stages.release()
        self.scene.release()

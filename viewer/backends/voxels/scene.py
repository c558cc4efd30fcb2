"""A voxel structure in CL buffers plus its traversal kernel: what the `voxels` backend, the tests
and the study share. Kernels: bvh.cl, kd.cl, octree.cl beside this file (common.cl: hit rule,
short stack, step record)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viewer.accel.voxel_bvh import build_voxel_bvh
from viewer.accel.voxel_kd import build_voxel_kd
from viewer.accel.voxel_leaves import VoxelStructure
from viewer.accel.voxel_octree import build_voxel_octree
from viewer.accel.voxelize import Voxels
from viewer.cl import io as clio
from viewer.errors import RtwalkError

HERE = Path(__file__).resolve().parent
STRUCTURES = {"bvh": build_voxel_bvh, "kd": build_voxel_kd, "octree": build_voxel_octree}
WG = 64
STACK_RANGE = (1, 16)


def build_structure(kind: str, vox: Voxels) -> VoxelStructure:
    if kind not in STRUCTURES:
        raise RtwalkError(f"unknown voxel structure '{kind}' (choose from {', '.join(STRUCTURES)})")
    return STRUCTURES[kind](vox)


@dataclass
class TraceOut:
    """Host copies of one trace: t (+inf miss), tri (-1 miss), vox (leaf-order voxel index, -1),
    record int32 (n, 4) steps per ray (interior, leaf, pop, restart) when recorded; seq the step kinds
    in order when the tracer was built with seq_len > 0."""

    t: np.ndarray
    tri: np.ndarray
    vox: np.ndarray
    record: np.ndarray | None = None
    seq: np.ndarray | None = None  # uint8 (n, seq_len) step kinds in order (1-4), 0 after the last


class VoxelTracer:
    """One structure on the CL device. `record`: build the kernel that writes per-ray step counts;
    `seq_len` > 0 also the first seq_len step kinds of each ray (the lockstep model's input)."""

    def __init__(self, structure: VoxelStructure, origin, scale: float, stack: int = 8, record: bool = False,
                 ctx=None, seq_len: int = 0):
        from viewer.cl import build, cl_context

        if not STACK_RANGE[0] <= stack <= STACK_RANGE[1]:
            raise RtwalkError(f"voxel stack must be in {STACK_RANGE[0]}..{STACK_RANGE[1]} (got {stack})")
        if len(structure.leaves) == 0:
            raise RtwalkError("the voxelization has no voxels (the scene has no triangle of non-zero area)")
        self.ctx = ctx or cl_context()
        self.structure = structure
        self.stack = stack
        self.seq_len = int(seq_len) if record else 0
        self.record = record
        cl = self.ctx.cl
        mf = cl.mem_flags
        c = self.ctx.context

        def buf(a: np.ndarray):
            a = np.ascontiguousarray(a)
            if a.nbytes == 0:
                a = np.zeros(4, np.uint8)
            return clio.upload(self.ctx, a, what="voxel structure")

        self.nodes = buf(structure.nodes)
        self.leaves = buf(structure.leaves)
        self.voxel_tri = buf(structure.voxel_tri)
        hdr = np.zeros(8, np.float32)
        hdr[:3] = origin
        hdr[3] = scale
        self.hdr = buf(hdr)
        defines = {"STACK": stack, "WG": WG}
        if record:
            defines["RECORD"] = None
            defines["SEQ_LEN"] = self.seq_len
        prog = build(HERE / f"{structure.kind}.cl", defines, self.ctx)
        self.kernel = clio.kernel(prog, "trace")
        self.root_lo = np.zeros(4, np.float32)
        self.root_lo[:3] = structure.root_lo
        self.root_hi = np.zeros(4, np.float32)
        self.root_hi[:3] = structure.root_hi
        self.dummy = cl.Buffer(c, mf.READ_WRITE, 16)

    def enqueue(self, ray_o, ray_d, out_t, out_tri, out_vox, n: int, any_hit: bool, bias: float = 0.0,
                record=None, seq=None, leave: bool = False, gap: float = 0.5):
        """Trace n rays (buffers as viewer/cl/transfer.py lays them out); record: int4 per ray, seq:
        seq_len bytes per ray (recording tracers; a ray writes only its first min(steps, seq_len)
        bytes). `bias`: tmin moves this many voxel widths along the ray; `leave`: the run of voxels
        the ray starts in (each within `gap` voxel widths of the previous exit) is skipped: the
        surface a secondary ray leaves (common.cl)."""
        if n == 0:
            return None
        if self.record and record is None:
            raise ValueError("a recording tracer needs a record buffer")
        gsize = -(-n // WG) * WG
        s = self.structure
        return self.kernel(self.ctx.queue, (gsize,), (WG,), self.nodes, self.leaves, self.voxel_tri, self.hdr,
                           np.int32(s.root), np.int32(s.resolution), self.root_lo, self.root_hi, ray_o, ray_d,
                           out_t, out_tri, out_vox, record if record is not None else self.dummy,
                           seq if seq is not None else self.dummy, np.int32(n),
                           np.int32(bool(any_hit)), np.float32(bias), np.int32(bool(leave)), np.float32(gap))

    def trace_arrays(self, o4: np.ndarray, d4: np.ndarray, any_hit: bool = False, bias: float = 0.0,
                     leave: bool = False, gap: float = 0.5) -> TraceOut:
        """Host-side convenience (tests, study): float32 (n, 4) origin+tmin and direction+tmax."""
        cl = self.ctx.cl
        mf = cl.mem_flags
        c = self.ctx.context
        n = len(o4)
        o_b = clio.upload(self.ctx, np.ascontiguousarray(o4, np.float32))
        d_b = clio.upload(self.ctx, np.ascontiguousarray(d4, np.float32))
        t = np.empty(n, np.float32)
        tri = np.empty(n, np.int32)
        vox = np.empty(n, np.int32)
        rec = np.zeros((n, 4), np.int32) if self.record else None
        t_b = cl.Buffer(c, mf.WRITE_ONLY, max(t.nbytes, 4))
        tri_b = cl.Buffer(c, mf.WRITE_ONLY, max(tri.nbytes, 4))
        vox_b = cl.Buffer(c, mf.WRITE_ONLY, max(vox.nbytes, 4))
        rec_b = cl.Buffer(c, mf.WRITE_ONLY, max(rec.nbytes, 16)) if rec is not None else None
        seq = np.zeros((n, self.seq_len), np.uint8) if self.seq_len else None
        seq_b = None  # cleared: the kernel writes only the steps a ray takes, 0 after them is this copy's
        if seq is not None:
            seq_b = clio.upload(self.ctx, seq, mf.READ_WRITE) if seq.nbytes else \
                cl.Buffer(c, mf.WRITE_ONLY, 16)
        q = self.ctx.queue
        self.enqueue(o_b, d_b, t_b, tri_b, vox_b, n, any_hit, bias, rec_b, seq_b, leave, gap)
        if n:
            clio.copy(q, t, t_b)
            clio.copy(q, tri, tri_b)
            clio.copy(q, vox, vox_b)
            if rec is not None:
                clio.copy(q, rec, rec_b)
            if seq is not None:
                clio.copy(q, seq, seq_b)
        clio.finish(q)
        for b in (o_b, d_b, t_b, tri_b, vox_b, rec_b, seq_b):
            if b is not None:
                b.release()
        return TraceOut(t, tri, vox, rec, seq)

    def release(self) -> None:
        for b in (self.nodes, self.leaves, self.voxel_tri, self.hdr, self.dummy):
            b.release()

"""The BVH4 collapse (viewer.accel.bvh4) on the OpenCL device.

Why: at 10 M triangles the host collapse took 2.5-3.3 s of the first frame. Same greedy, same
node order and numbering, so the same nodes bit for bit (tests/test_clbvh.py): per BVH4 level,
`b4_open` picks each node's 2-4 children (float64 areas, first largest on ties, as the host),
the project's exclusive scan numbers the inner ones row-major, `b4_write` writes the nodes and the
next level's frontier. One host read per level (the next level's size: the launch size). The
binary tree is read in place (USE_HOST_PTR); the nodes stay in a device buffer that the returned
BVH4's arrays view (mapped, zero-copy on a CPU device).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.bvh import BVH
from viewer.accel.bvh4 import BVH4, NODE4_DTYPE
from viewer.cl import io as clio

KERNEL = Path(__file__).resolve().parent / "bvh4_device.cl"
WG = 64


def device_supported(ctx: Any) -> bool:
    """The collapse needs float64 on the device (the host compares areas in float64)."""
    return "cl_khr_fp64" in ctx.device.extensions


def build_bvh4_device(bvh: BVH, ctx: Any = None) -> tuple[BVH4, Any]:
    """(BVH4 whose nodes / source view a mapped device buffer, that nodes buffer)."""
    from viewer.cl import build, cl_context
    from viewer.cl.limits import new_buffer
    from viewer.cl.primitives import primitives

    ctx = ctx or cl_context()
    cl, q, u = ctx.cl, ctx.queue, np.uint32
    m = len(bvh.node_left)
    n_inner = int(m - (bvh.node_left < 0).sum())
    cap = max(n_inner, 1)  # each BVH4 node comes from a distinct binary inner node (or the leaf root)
    source_off = ctx.align_up(cap * NODE4_DTYPE.itemsize)  # the source ids' sub-buffer after the nodes
    nodes = new_buffer(ctx, cl.mem_flags.READ_WRITE, source_off + 4 * cap, "BVH4 nodes")
    if n_inner == 0:  # a single leaf: one node, the leaf in slot 0 (as the host collapse)
        from viewer.accel.bvh4 import build_bvh4

        b4 = build_bvh4(bvh)
        clio.copy(q, nodes, b4.nodes)
        return b4, nodes
    k = {name: clio.kernel(build(KERNEL, {"WG": WG}, ctx), name) for name in ("b4_open", "b4_write")}
    arrays = [np.ascontiguousarray(a) for a in (bvh.node_min, bvh.node_max, bvh.node_left, bvh.node_right,
                                                bvh.node_first, bvh.node_count)]
    nmin, nmax, left, right, first, count = (clio.upload(ctx, a, what="BVH4 input", use_host=True) for a in arrays)
    prims = primitives(ctx)
    mf = cl.mem_flags.READ_WRITE
    front = [new_buffer(ctx, mf, 4 * cap, "BVH4 frontier"), new_buffer(ctx, mf, 4 * cap, "BVH4 frontier")]
    ch4 = new_buffer(ctx, mf, 16 * cap, "BVH4 children")
    ninner, offset = new_buffer(ctx, mf, 4 * cap, "BVH4 counts"), new_buffer(ctx, mf, 4 * cap, "BVH4 offsets")
    source = nodes.get_sub_region(source_off, 4 * cap)
    clio.copy(q, front[0], np.zeros(1, np.int32), is_blocking=False)  # the root
    base, level, size = 0, 0, 1
    while size:
        g = (-(-size // WG) * WG,)
        cur, nxt = front[level % 2], front[1 - level % 2]
        k["b4_open"](q, g, (WG,), u(size), cur, nmin, nmax, left, right, ch4, ninner)
        total = prims.exclusive_scan(ninner, offset, size)  # one read: the next level's size
        k["b4_write"](q, g, (WG,), u(size), u(base), cur, ch4, offset, nmin, nmax, left, first, count, nodes,
                      source, nxt)
        base += size
        size = int(total)
        level += 1
    words = base * NODE4_DTYPE.itemsize // 4
    flat, _ = clio.map_buffer(q, nodes, cl.map_flags.READ | cl.map_flags.WRITE, 0, (source_off // 4 + cap,), np.int32)
    out_nodes = flat[:words].view(NODE4_DTYPE)
    out_src = flat[source_off // 4:source_off // 4 + base]
    for buf in (nmin, nmax, left, right, first, count, *front, ch4, ninner, offset):
        buf.release()
    leaves = int(((out_nodes["child"] < 0) & (out_nodes["count"] > 0)).sum())
    return BVH4(out_nodes, level - 1, out_src, leaves), nodes

"""SIMD lane utilisation of lockstep execution, from recorded per-ray traversal steps.

Chajdas & Westermann read execution coherency from GPU hardware counters (64-wide AMD). This
machine has none, so coherency is computed from what each ray did, under a stated model:

  Rays are taken in groups of W consecutive rays (ray index = pixel index, row-major; the last
  group is padded with idle lanes). The W lanes of a group advance in lockstep, one traversal
  step per iteration: iteration j executes step j of every lane that still has one. A step has a
  kind (interior-node step, leaf test, stack pop, restart from the root); a SIMD unit runs one
  code path at a time, so in an iteration each distinct kind present among the active lanes
  costs one issue slot, in which only the lanes taking that kind do useful work.

      U_W = (sum over rays of their steps) / (W * sum over groups and iterations of the number
            of distinct step kinds in that iteration)

  U_W = 1 when all W rays take the same kinds of step in the same order and finish together;
  idle lanes (finished rays, rays of another kind in that slot) lower it. `merged` is the same
  with all kinds counted as one code path (a "while-while" loop without divergence inside the
  iteration): steps / (W * sum over groups of the longest ray).

Inputs: seq uint8 (n, L), the kinds (1..4) of each ray's first L steps in order, 0 after its last
step (VoxelTracer.trace_arrays returns this layout). Only the first L steps of a ray are seen; the
caller reports how many steps were cut off. `lane_utilisation` is the NumPy definition (tests,
small inputs); `DeviceLockstep` computes the same sums with lockstep.cl on the recording's device
buffers (the study: tens of millions of rays, no host copy of the sequences).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from viewer.cl import io as clio

KINDS = {1: "interior", 2: "leaf", 3: "pop", 4: "restart"}


def lane_utilisation(seq: np.ndarray, width: int) -> dict:
    """{"steps", "slots", "utilisation", "merged_utilisation", "groups"} for lockstep groups of `width`."""
    seq = np.asarray(seq, np.uint8)
    n, L = seq.shape
    g = -(-n // width)
    pad = g * width - n
    if pad:
        seq = np.concatenate([seq, np.zeros((pad, L), np.uint8)])
    s = seq.reshape(g, width, L)
    steps = int(np.count_nonzero(s))
    slots = 0
    for k in KINDS:
        slots += int(np.any(s == k, axis=1).sum())
    longest = (s != 0).sum(axis=2).max(axis=1)  # steps are contiguous from 0
    merged_slots = int(longest.sum())
    return {"steps": steps, "slots": slots, "groups": g, "merged_slots": merged_slots,
            "utilisation": steps / (width * slots) if slots else float("nan"),
            "merged_utilisation": steps / (width * merged_slots) if merged_slots else float("nan")}


def summary(steps: int, slots: int, merged_slots: int, groups: int, width: int) -> dict:
    """The dict lane_utilisation returns, from its sums."""
    return {"steps": int(steps), "slots": int(slots), "groups": int(groups), "merged_slots": int(merged_slots),
            "utilisation": steps / (width * slots) if slots else float("nan"),
            "merged_utilisation": steps / (width * merged_slots) if merged_slots else float("nan")}


def combine(parts: list[dict], width: int) -> dict:
    """Utilisation of several chunks or passes traced apart (each a whole number of groups but the last)."""
    return summary(sum(p["steps"] for p in parts), sum(p["slots"] for p in parts),
                   sum(p["merged_slots"] for p in parts), sum(p["groups"] for p in parts), width)


class DeviceLockstep:
    """lane_utilisation on device buffers: seq (n x L step kinds, entries past a ray's length
    unread) and rec (int4 step counts per ray) as a recording VoxelTracer writes them."""

    def __init__(self, ctx, max_rays: int, max_width: int = 64):
        from viewer.cl import build

        self.ctx = ctx
        self.max_width = max_width
        self.kernel = clio.kernel(build(Path(__file__).with_name("lockstep.cl"), {"MAXW": max_width}, ctx),
                                    "lockstep")
        self.host = np.empty(3 * max(max_rays, 1), np.int32)  # width 1 at most
        self.out = ctx.cl.Buffer(ctx.context, ctx.cl.mem_flags.WRITE_ONLY, self.host.nbytes)

    def __call__(self, seq_b, rec_b, n: int, seq_len: int, width: int) -> dict:
        if not 1 <= width <= self.max_width or 3 * -(-n // width) > len(self.host):
            raise ValueError(f"lockstep: width {width} or {n} rays out of range")
        g = -(-n // width)
        if n == 0:
            return summary(0, 0, 0, 0, width)
        self.kernel(self.ctx.queue, (g,), None, seq_b, rec_b, np.int32(n), np.int32(seq_len), np.int32(width),
                    self.out)
        res = self.host[: 3 * g]
        clio.copy(self.ctx.queue, res, self.out)
        clio.finish(self.ctx.queue)
        r = res.reshape(g, 3).astype(np.int64).sum(axis=0)
        return summary(r[0], r[1], r[2], g, width)

    def release(self) -> None:
        self.out.release()

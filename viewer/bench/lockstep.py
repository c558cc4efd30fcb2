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
step (viewer/backends/voxels/common.cl writes this layout). Only the first L steps of a ray are
seen; the caller reports how many steps were cut off.
"""

from __future__ import annotations

import numpy as np

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
    return {"steps": steps, "slots": slots, "groups": g,
            "utilisation": steps / (width * slots) if slots else float("nan"),
            "merged_utilisation": steps / (width * merged_slots) if merged_slots else float("nan")}


def combine(parts: list[dict], width: int) -> dict:
    """Utilisation of several chunks traced apart (each a whole number of groups but the last)."""
    steps = sum(p["steps"] for p in parts)
    slots = sum(p["slots"] for p in parts)
    merged = sum(p["steps"] / p["merged_utilisation"] / width for p in parts if p["steps"])
    return {"steps": steps, "slots": slots, "groups": sum(p["groups"] for p in parts),
            "utilisation": steps / (width * slots) if slots else float("nan"),
            "merged_utilisation": steps / (width * merged) if merged else float("nan")}

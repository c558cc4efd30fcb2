"""The lockstep lane-utilisation model against hand-computed cases and a per-iteration Python loop."""

from __future__ import annotations

import numpy as np

from viewer.bench.lockstep import combine, lane_utilisation


def _slow(seq: np.ndarray, w: int) -> tuple[int, int]:
    steps = slots = 0
    for g0 in range(0, len(seq), w):
        grp = seq[g0:g0 + w]
        for j in range(seq.shape[1]):
            kinds = {int(k) for k in grp[:, j] if k}
            slots += len(kinds)
            steps += sum(1 for k in grp[:, j] if k)
    return steps, slots


def test_hand_cases():
    same = np.array([[1, 1, 2, 0]] * 8, np.uint8)
    assert lane_utilisation(same, 8)["utilisation"] == 1.0
    # one lane of 8 walks 4 steps, the others 1: 11 steps in 4 slots of 8 lanes
    seq = np.zeros((8, 4), np.uint8)
    seq[:, 0] = 1
    seq[0, 1:] = 1
    r = lane_utilisation(seq, 8)
    assert (r["steps"], r["slots"]) == (11, 4) and r["utilisation"] == 11 / 32
    # two kinds in the same iteration cost two slots; merged counts one
    seq = np.array([[1], [2]], np.uint8)
    r = lane_utilisation(seq, 2)
    assert r["utilisation"] == 0.5 and r["merged_utilisation"] == 1.0
    # padding: 3 rays in a group of 4
    r = lane_utilisation(np.ones((3, 2), np.uint8), 4)
    assert r["utilisation"] == 6 / 8


def test_against_loop():
    rng = np.random.default_rng(2)
    n, L = 203, 30
    lengths = rng.integers(0, L + 1, n)
    seq = rng.integers(1, 5, (n, L)).astype(np.uint8)
    seq[np.arange(L)[None, :] >= lengths[:, None]] = 0
    for w in (8, 32, 64):
        r = lane_utilisation(seq, w)
        assert (r["steps"], r["slots"]) == _slow(seq, w)
        parts = [lane_utilisation(seq[:128], w), lane_utilisation(seq[128:], w)]
        c = combine(parts, w)
        if 128 % w == 0:
            assert c["slots"] == r["slots"] and abs(c["merged_utilisation"] - r["merged_utilisation"]) < 1e-12

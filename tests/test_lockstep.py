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


def test_device_lockstep_matches_numpy():
    """lockstep.cl on device buffers against the NumPy definition; bytes past a ray's length hold
    garbage (the recording kernel leaves them), which the device reduction must not read."""
    from tests.conftest import opencl_missing

    if opencl_missing() is not None:
        import pytest

        pytest.skip(opencl_missing())
    from viewer.bench.lockstep import DeviceLockstep
    from viewer.cl import cl_context

    ctx = cl_context()
    rng = np.random.default_rng(5)
    n, L = 1000, 40
    lengths = rng.integers(0, L + 20, n)  # some rays longer than L: only their first L steps count
    kinds = rng.integers(1, 5, (n, L)).astype(np.uint8)
    kinds[rng.random(n) < 0.3] = 1  # some uniform rays
    clean = kinds.copy()
    clean[np.arange(L)[None, :] >= lengths[:, None]] = 0
    garbage = kinds.copy()
    garbage[np.arange(L)[None, :] >= lengths[:, None]] = rng.integers(1, 255, int((clean == 0).sum()))
    rec = np.zeros((n, 4), np.int32)
    split = rng.integers(0, lengths + 1)
    rec[:, 0], rec[:, 3] = split, lengths - split  # only the sum is the length
    mf = ctx.cl.mem_flags
    seq_b = ctx.cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=garbage)
    rec_b = ctx.cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rec)
    dev = DeviceLockstep(ctx, n)
    try:
        for w in (1, 8, 32, 64):
            want = lane_utilisation(clean, w)
            got = dev(seq_b, rec_b, n, L, w)
            assert (got["steps"], got["slots"], got["merged_slots"], got["groups"]) == \
                (want["steps"], want["slots"], want["merged_slots"], want["groups"])
            assert got["utilisation"] == want["utilisation"]
    finally:
        dev.release()
        seq_b.release()
        rec_b.release()

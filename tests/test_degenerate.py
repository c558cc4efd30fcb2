"""viewer.degenerate.unhittable (what trace_rays leaves out) against the reference's own exact
zero-area decision (viewer.reference, rational arithmetic where needed)."""

from __future__ import annotations

import numpy as np

from tests.test_hard_cases import collinear_probe
from viewer.degenerate import unhittable
from viewer.reference import _exact_zero_area


def test_unhittable_matches_the_exact_zero_area_decision():
    tris, _, _, degenerate = collinear_probe(seed=5)
    extra = np.array([
        [[0, 0, 0], [0, 0, 0], [1, 1, 1]],                   # repeated vertex
        [[1, 1, 1], [1, 1, 1], [1, 1, 1]],                   # a point
        [[0, 0, 0], [1, 1, 1], [2, 2, 2 + 2.0 ** -22]],      # sliver: kept
        [[1e-30, 0, 0], [1e30, 0, 0], [0, 1e-30, 0]],        # huge range, genuine
        [[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]],              # non-finite
        [[np.inf, 0, 0], [1, 0, 0], [0, 1, 0]],
    ], np.float32)
    tris = np.concatenate([tris, extra])
    got = unhittable(tris)
    finite = np.isfinite(tris).all(axis=(1, 2))
    with np.errstate(all="ignore"):  # the reference warns on the non-finite rows
        expected = _exact_zero_area(tris) | ~finite
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[:len(degenerate)], degenerate)
    assert got[-6:].tolist() == [True, True, False, False, True, True]
    assert unhittable(np.zeros((0, 3, 3), np.float32)).shape == (0,)

"""The six-separating voxelizer against float64 references written independently of it:
the rule evaluated per triangle over every voxel of a small grid, the separating-axis
triangle/box overlap test (Akenine-Moller), and 6-connected flood fill of closed meshes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from viewer.accel.voxelize import VoxelGrid, voxel_keys, voxelize
from viewer.errors import RtwalkError
from viewer.procedural import _icosphere, _placed_box


def _centres(R: int) -> np.ndarray:
    i = np.arange(R) + 0.5
    z, y, x = np.meshgrid(i, i, i, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)  # key order: x fastest


def reference_rule(g: np.ndarray, R: int) -> np.ndarray:
    """bool (R^3,) in key order: voxels the six-separating rule sets, one triangle at a time over
    all voxels (grid-unit triangles g, float64)."""
    c = _centres(R)
    out = np.zeros(len(c), bool)
    for v in g:
        n = np.cross(v[1] - v[0], v[2] - v[0])
        if not np.any(n):
            continue
        ok = np.all((c + 0.5 >= v.min(axis=0)) & (c - 0.5 <= v.max(axis=0)), axis=1)
        ok &= np.abs((c - v[0]) @ n) <= 0.5 * np.max(np.abs(n))
        for p, q, r in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
            for i in range(3):
                e = v[(i + 1) % 3] - v[i]
                m = np.array([-e[q], e[p]]) * np.sign(n[r])
                d2 = (c[:, [p, q]] - v[i, [p, q]]) @ m
                ok &= d2 + 0.5 * np.max(np.abs(m)) >= 0
        out |= ok
    return out


def tri_box_overlap(v: np.ndarray, lo: np.ndarray, hi: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """Separating-axis test: does triangle v (3, 3) touch the closed boxes [lo, hi] (k, 3)?"""
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    p = v[None, :, :] - c[:, None, :]  # (k, 3, 3)
    edges = [v[1] - v[0], v[2] - v[1], v[0] - v[2]]
    axes = [np.eye(3)[i] for i in range(3)] + [np.cross(edges[0], edges[1])]
    axes += [np.cross(e, np.eye(3)[i]) for e in edges for i in range(3)]
    ok = np.ones(len(lo), bool)
    for a in axes:
        if not np.any(a):
            continue
        proj = p @ a  # (k, 3)
        r = h @ np.abs(a)
        ok &= ~((proj.min(axis=1) > r + eps) | (proj.max(axis=1) < -r - eps))
    return ok


def _scene(seed: int, n: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.random((n, 1, 3)) * 10
    return (base + rng.normal(size=(n, 3, 3)) * rng.choice([0.2, 1.0, 3.0], size=(n, 1, 1))).astype(np.float32)


@pytest.mark.parametrize("seed,R", [(1, 16), (2, 32), (3, 8)])
def test_matches_rule_and_touches(seed, R):
    tris = _scene(seed)
    vox = voxelize(tris, R)
    g = vox.grid.to_grid(tris)
    ref = reference_rule(g, R)
    got = np.zeros(R ** 3, bool)
    got[vox.keys] = True
    missing = np.flatnonzero(ref & ~got)
    extra = np.flatnonzero(got & ~ref)
    assert len(missing) == 0, f"{len(missing)} voxels the rule requires are not set"
    assert len(extra) == 0, f"{len(extra)} voxels set that the rule does not require"
    # every set voxel is touched by a triangle, and its representative triangle touches it
    lo = vox.coords.astype(np.float64)
    touched = np.zeros(vox.count, bool)
    for v in g:
        touched |= tri_box_overlap(v, lo, lo + 1)
    assert touched.all()
    rep_ok = np.array([tri_box_overlap(g[t], lo[i:i + 1], lo[i:i + 1] + 1)[0] for i, t in enumerate(vox.tri)])
    assert rep_ok.all()
    assert np.all(np.diff(vox.keys) > 0)  # sorted, unique
    assert vox.coords.dtype == np.uint16 and vox.tri.dtype == np.int32


def test_chunking_does_not_change_result(monkeypatch):
    import viewer.accel.voxelize as vz

    tris = _scene(5, 60)
    a = voxelize(tris, 32)
    monkeypatch.setattr(vz, "CHUNK_COLUMNS", 7)
    b = voxelize(tris, 32)
    assert np.array_equal(a.coords, b.coords) and np.array_equal(a.tri, b.tri)


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_closed_mesh_is_six_separating(shape):
    """Flood fill from outside through empty voxels (6-connected) never reaches a voxel whose centre
    is inside the closed mesh: no 6-connected tunnel through the surface."""
    if shape == "sphere":
        tris = _icosphere(3, 3.0, (0.1, 0.2, 0.3)).reshape(-1, 3, 3)
    else:
        tris = _placed_box((4.0, 3.0, 5.0), (0.0, 0.0, 0.0), 0.6).reshape(-1, 3, 3)
    R = 64
    lo = tris.reshape(-1, 3).min(axis=0) - 1
    hi = tris.reshape(-1, 3).max(axis=0) + 1
    grid = VoxelGrid.around(lo, hi, R)
    vox = voxelize(tris, R, grid=grid)
    occ = np.zeros((R, R, R), bool)
    occ[vox.coords[:, 2], vox.coords[:, 1], vox.coords[:, 0]] = True
    labels, _ = ndimage.label(~occ)  # default structure: 6-connectivity
    outside = labels[0, 0, 0]
    c = _centres(R)
    world = c / grid.scale + grid.origin
    if shape == "sphere":
        inside = np.linalg.norm(world - np.array([0.1, 0.2, 0.3]), axis=1) < 2.9  # inscribed in the mesh
    else:
        ang = -0.6
        x = np.cos(ang) * world[:, 0] + np.sin(ang) * world[:, 2]
        z = -np.sin(ang) * world[:, 0] + np.cos(ang) * world[:, 2]
        inside = (np.abs(x) < 1.9) & (np.abs(world[:, 1]) < 1.4) & (np.abs(z) < 2.4)
    inside_lab = labels.reshape(-1)[inside & ~occ.reshape(-1)]
    assert inside.sum() > 1000
    assert not np.any(inside_lab == outside)


def test_bad_resolution():
    with pytest.raises(RtwalkError):
        voxelize(_scene(1), 48)


def test_keys_roundtrip():
    vox = voxelize(_scene(4), 16)
    k = voxel_keys(vox.coords, 16)
    assert np.array_equal(k, vox.keys)

"""Six-separating surface voxelization of a triangle scene (Schwarz & Seidel 2010), sparse output.

Why six-separating: it is the thinnest voxel surface that no 6-connected path crosses, so the
voxel count (and every structure built on it) stays minimal while rays cannot slip through it
between axis-aligned neighbours. Chajdas & Westermann voxelize this way for the same reason.

Grid: a cube of `resolution`^3 voxels (a power of two) over the scene bounds (VoxelGrid); voxel
(i, j, k) covers [i, i+1] x [j, j+1] x [k, k+1] in grid units, g = (p - origin) * scale.

The rule, evaluated in float64 in grid units (voxel edge 1, centre c = (i, j, k) + 0.5), for a
non-degenerate triangle (v0, v1, v2) with normal n = (v1 - v0) x (v2 - v0) sets voxel c when
  1. the voxel's closed box overlaps the triangle's bounding box;
  2. the triangle's plane meets the voxel's diamond (the octahedron spanned by its face
     centres): |n . (c - v0)| <= 0.5 * max|n_i|;
  3. in each of the three axis projections (xy, yz, zx; r = the dropped axis), every edge
     e_i = v_{i+1} - v_i with inward normal m_i = (-e_i,q, e_i,p) * sign(n_r) keeps part of the
     projected voxel's 2D diamond: m_i . (c - v_i) + 0.5 * max(|m_i,p|, |m_i,q|) >= 0.
Since the diamonds lie inside the voxel, 1-3 are the 13 separating-axis tests of triangle/box
overlap made stricter, so every set voxel touches a triangle; the rule is S&S's six-separating
test. Zero-area triangles are skipped (no ray hits them; with n = 0 the rule would fill their box).

Vectorised: the rule for the dominant normal axis a allows at most two voxels per grid column
along a (the plane crosses the diamond of a column in a slab of height 1), so each triangle
expands to its projected bounding-box columns x 3 candidates (the plane's voxel and its two
neighbours, absorbing rounding), in chunks of triangles bounded by CHUNK_COLUMNS columns.

Per voxel, the representative triangle (shading: albedo, normal) is the one whose plane passes
nearest the voxel centre (ties: smallest triangle id).

Layout (Voxels): coords uint16 (n, 3) sorted by key = x + R * (y + R * z); tri int32 (n,).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from viewer.errors import RtwalkError

CHUNK_COLUMNS = 400_000  # columns expanded per chunk (x 3 candidates, ~30 float64 temporaries each)
MAX_RESOLUTION = 1 << 15  # uint16 coordinates; keys need 3 * 15 bits

Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class VoxelGrid:
    """A cube of resolution^3 voxels: world point p is at grid point (p - origin) * scale."""

    origin: np.ndarray  # float64 (3,), world position of grid point (0, 0, 0)
    size: float  # world edge length of the cube
    resolution: int

    @property
    def scale(self) -> float:
        return self.resolution / self.size

    @property
    def voxel_size(self) -> float:
        return self.size / self.resolution

    def to_grid(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, np.float64) - self.origin) * self.scale

    @staticmethod
    def around(lo: np.ndarray, hi: np.ndarray, resolution: int) -> VoxelGrid:
        """The cube centred on the box [lo, hi], edge = its longest side plus 1e-4 of margin
        (no triangle lies on the grid's outer faces)."""
        check_resolution(resolution)
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        size = float(np.max(hi - lo)) * (1 + 1e-4)
        size = size if size > 0 else 1.0
        origin = 0.5 * (lo + hi) - 0.5 * size
        return VoxelGrid(origin, size, int(resolution))


def check_resolution(resolution: int) -> None:
    if resolution < 2 or resolution > MAX_RESOLUTION or resolution & (resolution - 1):
        raise RtwalkError(f"voxel resolution must be a power of two in 2..{MAX_RESOLUTION} (got {resolution})")


@dataclass
class Voxels:
    """A sparse voxel set: grid, uint16 coordinates sorted by key, representative triangle per voxel."""

    grid: VoxelGrid
    coords: np.ndarray  # uint16 (n, 3)
    tri: np.ndarray  # int32 (n,)
    stats: dict = field(default_factory=dict)  # count, seconds, bytes, peak_candidates, skipped

    @property
    def count(self) -> int:
        return int(self.coords.shape[0])

    @property
    def keys(self) -> np.ndarray:
        return voxel_keys(self.coords, self.grid.resolution)

    @property
    def nbytes(self) -> int:
        return int(self.coords.nbytes + self.tri.nbytes)


def voxel_keys(coords: np.ndarray, resolution: int) -> np.ndarray:
    c = np.asarray(coords, np.int64)
    return c[:, 0] + resolution * (c[:, 1] + resolution * c[:, 2])


def _chunks(columns: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Consecutive triangle ranges whose column counts sum to about `budget` (at least one each)."""
    csum = np.cumsum(columns)
    out, start, done = [], 0, 0
    while start < len(columns):
        end = int(np.searchsorted(csum, done + budget, side="right"))
        end = max(end, start + 1)
        out.append((start, end))
        done = int(csum[end - 1])
        start = end
    return out


def _rule(v: np.ndarray, n: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Conditions 2 and 3 of the module docstring for candidate centres c (k, 3) of triangles
    v (k, 3, 3) with normals n (k, 3), float64 grid units."""
    ok = np.abs(np.einsum("ij,ij->i", n, c - v[:, 0])) <= 0.5 * np.abs(n).max(axis=1)
    for p, q, r in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        s = np.sign(n[:, r])
        for i in range(3):
            a, b = v[:, i], v[:, (i + 1) % 3]
            mp = -(b[:, q] - a[:, q]) * s
            mq = (b[:, p] - a[:, p]) * s
            ok &= mp * (c[:, p] - a[:, p]) + mq * (c[:, q] - a[:, q]) + 0.5 * np.maximum(np.abs(mp), np.abs(mq)) >= 0
    return ok


def voxelize(triangles: np.ndarray, resolution: int, grid: VoxelGrid | None = None,
             progress: Progress | None = None) -> Voxels:
    """Six-separating voxelization of float (N, 3, 3) triangles (module docstring)."""
    t_start = time.perf_counter()
    tris = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    if grid is None:
        if len(tris) == 0:
            raise RtwalkError("cannot voxelize an empty scene")
        flat = tris.reshape(-1, 3)
        grid = VoxelGrid.around(flat.min(axis=0), flat.max(axis=0), resolution)
    check_resolution(grid.resolution)
    R = grid.resolution
    g = (tris - grid.origin) * grid.scale
    n_all = np.cross(g[:, 1] - g[:, 0], g[:, 2] - g[:, 0])
    keep = np.flatnonzero(np.abs(n_all).max(axis=1) > 0)
    skipped = len(tris) - len(keep)
    g, n_all = g[keep], n_all[keep]
    # closed-box overlap with the bounding box: voxels ceil(min) - 1 .. floor(max), clipped
    lo = np.clip(np.ceil(g.min(axis=1)) - 1, 0, R - 1).astype(np.int64)
    hi = np.clip(np.floor(g.max(axis=1)), 0, R - 1).astype(np.int64)
    dom = np.abs(n_all).argmax(axis=1)
    ax_u = (dom + 1) % 3
    ax_w = (dom + 2) % 3
    rows = np.arange(len(g))
    ext = hi - lo + 1
    cols = ext[rows, ax_u] * ext[rows, ax_w]

    keys_out, dist_out, tri_out = [], [], []
    peak = 0
    chunks = _chunks(cols, CHUNK_COLUMNS)
    for ci, (s, e) in enumerate(chunks):
        idx = np.repeat(np.arange(s, e), cols[s:e])
        first = np.cumsum(cols[s:e]) - cols[s:e]
        local = np.arange(len(idx)) - np.repeat(first, cols[s:e])
        a, u, w = dom[idx], ax_u[idx], ax_w[idx]
        nu = ext[idx, w]
        cu = lo[idx, u] + local // nu
        cw = lo[idx, w] + local % nu
        n = n_all[idx]
        v0 = g[idx, 0]
        ri = np.arange(len(idx))
        # plane height along the dominant axis at the column centre
        za = (np.einsum("ij,ij->i", n, v0) - n[ri, u] * (cu + 0.5) - n[ri, w] * (cw + 0.5)) / n[ri, a]
        k0 = np.floor(za - 0.5).astype(np.int64)  # the rule needs k in [za - 1, za]: within k0 - 1 .. k0 + 1
        cand = np.concatenate([k0 - 1, k0, k0 + 1])
        rep = np.tile(ri, 3)
        inside = (cand >= lo[idx[rep], a[rep]]) & (cand <= hi[idx[rep], a[rep]])
        rep, cand = rep[inside], cand[inside]
        c = np.empty((len(rep), 3), np.int64)
        c[np.arange(len(rep)), a[rep]] = cand
        c[np.arange(len(rep)), u[rep]] = cu[rep]
        c[np.arange(len(rep)), w[rep]] = cw[rep]
        peak = max(peak, len(rep))
        centre = c + 0.5
        tv = g[idx[rep]]
        tn = n[rep]
        ok = _rule(tv, tn, centre)
        c, rep, centre, tv, tn = c[ok], rep[ok], centre[ok], tv[ok], tn[ok]
        dist = np.abs(np.einsum("ij,ij->i", tn, centre - tv[:, 0])) / np.linalg.norm(tn, axis=1)
        keys_out.append(c[:, 0] + R * (c[:, 1] + R * c[:, 2]))
        dist_out.append(dist)
        tri_out.append(keep[idx[rep]])
        if progress is not None:
            progress((ci + 1) / len(chunks), f"voxelize {R}^3: {e}/{len(g)} triangles")

    keys = np.concatenate(keys_out) if keys_out else np.zeros(0, np.int64)
    dist = np.concatenate(dist_out) if dist_out else np.zeros(0)
    tri = np.concatenate(tri_out) if tri_out else np.zeros(0, np.int64)
    order = np.lexsort((tri, dist, keys))
    keys, tri = keys[order], tri[order]
    first = np.ones(len(keys), bool)
    first[1:] = keys[1:] != keys[:-1]
    keys, tri = keys[first], tri[first]
    coords = np.stack([keys % R, (keys // R) % R, keys // (R * R)], axis=1).astype(np.uint16)
    vox = Voxels(grid, coords, tri.astype(np.int32))
    vox.stats = {"count": vox.count, "seconds": time.perf_counter() - t_start, "bytes": vox.nbytes,
                 "peak_candidates": peak, "skipped_degenerate": skipped, "resolution": R}
    return vox

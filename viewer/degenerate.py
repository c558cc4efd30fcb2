"""Which float32 triangles can never be hit: zero area (three collinear or repeated vertices,
decided exactly) or a non-finite vertex.

The tracers' watertight test evaluates its edge functions in float32: for a zero-area triangle
they need not cancel, and rays through the segment it collapses to would report hits (388 of
4,096 rays aimed at such segments did, on every backend). The scene loader drops these triangles
(scene_io.clean_triangles); viewer.tracing.trace_rays, which takes raw arrays, drops them with
`unhittable` and maps the ids back.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np


def unhittable(tris: np.ndarray) -> np.ndarray:
    """Bool (N,): no ray can hit the float32 triangle (N, 3, 3): it has exactly zero area or a
    non-finite vertex.

    A float64 cross product of the edges sorts out the clear cases; the rest (cross product tiny
    against the edge lengths, or zero) are decided exactly: when both edges are float32 numbers,
    every product of the cross product is exact in float64 (24 + 24 bits), so a component is zero
    iff its two products are equal; otherwise in rational arithmetic."""
    tris = np.asarray(tris, np.float32).reshape(-1, 3, 3)
    out = ~np.isfinite(tris).all(axis=(1, 2))
    v = tris.astype(np.float64)
    with np.errstate(all="ignore"):
        e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
        cr = np.cross(e1, e2)
        size = np.sqrt((e1 * e1).sum(1) * (e2 * e2).sum(1))
        unclear = ~out & ~(np.sqrt((cr * cr).sum(1)) > 1e-9 * size)
        f32_edges = (e1.astype(np.float32) == e1).all(1) & (e2.astype(np.float32) == e2).all(1)
    fast = unclear & f32_edges
    a1, a2 = e1[fast], e2[fast]
    out[fast] = ((a1[:, 1] * a2[:, 2] == a1[:, 2] * a2[:, 1]) & (a1[:, 2] * a2[:, 0] == a1[:, 0] * a2[:, 2])
                 & (a1[:, 0] * a2[:, 1] == a1[:, 1] * a2[:, 0]))
    for i in np.flatnonzero(unclear & ~f32_edges):
        p = [[Fraction(float(c)) for c in vert] for vert in tris[i]]
        a = [p[1][k] - p[0][k] for k in range(3)]
        b = [p[2][k] - p[0][k] for k in range(3)]
        out[i] = a[1] * b[2] == a[2] * b[1] and a[2] * b[0] == a[0] * b[2] and a[0] * b[1] == a[1] * b[0]
    return out


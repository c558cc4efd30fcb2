"""A few hundred rays on the CPU through the canonical BVH, vectorised over (ray, node) pairs.

For decisions made once per scene (where the default lights go), not for frames: no GL or OpenCL
context is needed, and the cost is a handful of NumPy passes per BVH level. Traversal is
breadth-first over (ray, node) pairs: the pairs whose conservative slab test passes (far distance
scaled by 1 + 2 gamma(3), safe reciprocals, as in shaders/intersect.glsl) open their children;
leaves expand to (ray, triangle) pairs tested with the watertight test (Woop, Benthin, Wald 2013)
in float64. Closest hit keeps the smallest t (ties: smallest slot); any-hit stops a ray at its first
hit. Conventions as viewer.tracing: t in units of |d|, hits only for tmin < t < tmax, +inf / -1 on
a miss, triangle ids are leaf-order slots.
"""

from __future__ import annotations

import numpy as np

from viewer.accel.bvh import BVH

_GAMMA3 = 3 * np.finfo(np.float64).eps / (1 - 3 * np.finfo(np.float64).eps)


def _safe_rcp(d: np.ndarray) -> np.ndarray:
    tiny = np.abs(d) < 1e-30
    sign = np.where(np.signbit(d), -1.0, 1.0)
    with np.errstate(divide="ignore"):
        return np.where(tiny, sign * 1e30, 1.0 / np.where(tiny, 1.0, d))


def _watertight(v: np.ndarray, o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """t (K,) of K (ray, triangle) pairs, +inf on a miss; v (K, 3, 3), o/d (K, 3), lo/hi (K,)."""
    kz = np.argmax(np.abs(d), axis=1)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = d[np.arange(len(d)), kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)
    perm = np.stack([kx, ky, kz], axis=1)
    dp = np.take_along_axis(d, perm, axis=1)
    rel = np.take_along_axis(v - o[:, None, :], perm[:, None, :], axis=2)  # (K, 3 vertices, xyz permuted)
    sx, sy, sz = dp[:, 0] / dp[:, 2], dp[:, 1] / dp[:, 2], 1.0 / dp[:, 2]
    px = rel[:, :, 0] - sx[:, None] * rel[:, :, 2]
    py = rel[:, :, 1] - sy[:, None] * rel[:, :, 2]
    (ax, bx, cx), (ay, by, cy) = px.T, py.T
    u = cx * by - cy * bx
    w = bx * ay - by * ax
    vv = ax * cy - ay * cx
    inside = ((u >= 0) & (vv >= 0) & (w >= 0)) | ((u <= 0) & (vv <= 0) & (w <= 0))
    det = u + vv + w
    inside &= det != 0
    t = (u * rel[:, 0, 2] + vv * rel[:, 1, 2] + w * rel[:, 2, 2]) * sz
    with np.errstate(divide="ignore", invalid="ignore"):
        t = t / det
    inside &= (t > lo) & (t < hi)
    return np.where(inside, t, np.inf)


def cast_rays(bvh: BVH, triangles: np.ndarray, origins, directions, tmin=0.0, tmax=np.inf,
              any_hit: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(t float64 (R,), slot int64 (R,)) of rays through `bvh`; `triangles` in leaf order (N, 3, 3)."""
    o = np.atleast_2d(np.asarray(origins, np.float64))
    d = np.atleast_2d(np.asarray(directions, np.float64))
    r = len(o)
    lo = np.broadcast_to(np.asarray(tmin, np.float64), (r,)).copy()
    best_t = np.broadcast_to(np.asarray(tmax, np.float64), (r,)).copy()
    best_id = np.full(r, -1, np.int64)
    ok = np.isfinite(o).all(1) & np.isfinite(d).all(1) & (np.abs(d).max(1) > 0) & (best_t > lo)
    inv = _safe_rcp(d)
    nmin, nmax = bvh.node_min.astype(np.float64), bvh.node_max.astype(np.float64)
    tris = np.asarray(triangles, np.float64)
    ray = np.flatnonzero(ok)
    node = np.zeros(len(ray), np.int64)
    done = np.zeros(r, bool)
    while len(ray):
        if any_hit:
            keep = ~done[ray]
            ray, node = ray[keep], node[keep]
        t0 = (nmin[node] - o[ray]) * inv[ray]
        t1 = (nmax[node] - o[ray]) * inv[ray]
        near = np.maximum(np.minimum(t0, t1).max(1), lo[ray])
        far = np.minimum(np.maximum(t0, t1).min(1) * (1 + 2 * _GAMMA3), best_t[ray])
        hit_box = near <= far
        ray, node = ray[hit_box], node[hit_box]
        leaf = bvh.node_left[node] < 0
        lr, ln = ray[leaf], node[leaf]
        if len(lr):
            counts = bvh.node_count[ln].astype(np.int64)
            pr = np.repeat(lr, counts)
            starts = np.repeat(np.cumsum(counts) - counts, counts)
            slot = np.repeat(bvh.node_first[ln].astype(np.int64), counts) + np.arange(len(pr)) - starts
            t = _watertight(tris[slot], o[pr], d[pr], lo[pr], best_t[pr])
            hit = t < np.inf
            pr, slot, t = pr[hit], slot[hit], t[hit]
            if len(pr):
                order = np.lexsort((slot, t, pr))
                pr, slot, t = pr[order], slot[order], t[order]
                first = np.ones(len(pr), bool)
                first[1:] = pr[1:] != pr[:-1]
                pr, slot, t = pr[first], slot[first], t[first]
                better = (t < best_t[pr]) | ((t == best_t[pr]) & (slot < best_id[pr]))
                best_t[pr[better]] = t[better]
                best_id[pr[better]] = slot[better]
                done[pr] = True
        ir, inn = ray[~leaf], node[~leaf]
        ray = np.concatenate([ir, ir])
        node = np.concatenate([bvh.node_left[inn], bvh.node_right[inn]]).astype(np.int64)
    best_t[best_id < 0] = np.inf
    return best_t, best_id

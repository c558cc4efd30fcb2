"""Independent CPU reference ray tracers used to check the project's GPU tracers.

Convention shared by every tracer in the project (the GLSL tracer in ``viewer.tracing`` follows it):

``trace(triangles, origins, directions, tmin, tmax, any_hit) -> (t, tri)``

* ``triangles``: float32 ``(N, 3, 3)`` (triangle, vertex, xyz). Triangle ids are the input order.
* ``origins``, ``directions``: ``(R, 3)``. Directions need not be unit length; the returned ``t`` is in
  units of ``|direction|``, i.e. the hit point is ``origin + t * direction``.
* ``tmin``, ``tmax``: ``(R,)`` (scalars are broadcast). A hit counts only if ``tmin < t < tmax``
  (both strict).
* A ray is *inactive* (always a miss) when ``tmax <= tmin``, when its origin or direction has a
  non-finite component, when its direction is the zero vector, when ``tmin`` is not finite or when
  ``tmax`` is NaN. ``tmax = +inf`` is allowed.
* Result: ``t`` float32 ``(R,)``, ``+inf`` for a miss; ``tri`` int32 ``(R,)``, ``-1`` for a miss.
  The returned float32 ``t`` itself satisfies ``tmin < t < tmax`` (the references decide in float64 and
  move a value that rounds onto a range end one float32 step inwards).
* ``any_hit=False``: the closest hit. ``any_hit=True``: only "occluded or not" matters; ``t``/``tri``
  describe *some* valid hit in range (never garbage).
* Back faces are hit too (no culling). Zero-area triangles never hit.

Two implementations:

* :class:`EmbreeTracer` -- Intel Embree 4 through ``embreex``; fast, float32, for big scenes.
* :func:`trace_float64` -- brute force, float64, watertight (Woop et al. 2013); for small scenes.

and :func:`compare_hits`, the agreement statistics used by tests and benchmarks.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

REFERENCE_BACKEND = "embree"  # the registry name of the backend that traces with EmbreeTracer

__all__ = ["EmbreeTracer", "trace_float64", "compare_hits", "prepare_rays", "point_triangle_distance",
           "ray_edge_distance", "f32_ulp"]

# ----------------------------------------------------------------------------------------------
# input handling shared by both tracers
# ----------------------------------------------------------------------------------------------

def _as_triangles(triangles) -> np.ndarray:
    tris = np.asarray(triangles, dtype=np.float32)
    if tris.size == 0:
        return np.zeros((0, 3, 3), np.float32)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (N, 3, 3), got {tris.shape}")
    return np.ascontiguousarray(tris)


def prepare_rays(origins, directions, tmin, tmax):
    """Validate and broadcast ray arrays.

    Returns ``(o, d, tmin, tmax, active)`` with ``o``/``d`` float64 ``(R, 3)``, ``tmin``/``tmax`` float64
    ``(R,)`` and ``active`` bool ``(R,)`` (see the module docstring for what makes a ray inactive).
    The float64 arrays hold exactly the caller's values (float32 inputs convert exactly).
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.size == 0 and d.size == 0:
        o = o.reshape(0, 3)
        d = d.reshape(0, 3)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must both have shape (R, 3), got {o.shape} and {d.shape}")
    r = o.shape[0]
    t0 = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (r,)).copy()
    t1 = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (r,)).copy()
    with np.errstate(invalid="ignore"):
        active = (
            np.isfinite(o).all(axis=1)
            & np.isfinite(d).all(axis=1)
            & (d != 0).any(axis=1)
            & np.isfinite(t0)
            & ~np.isnan(t1)
            & (t1 > t0)
        )
    return o, d, t0, t1, active


def _miss(r: int):
    return np.full(r, np.inf, np.float32), np.full(r, -1, np.int32)


def _to_f32_in_range(t, lo, hi):
    """Round float64 hit distances (lo < t < hi) to float32 without leaving the open range.

    Plain rounding can land exactly on ``tmin``/``tmax``; such values are moved one float32 step
    inwards (still the float32 neighbour of the exact t). Returns ``(t32, ok)``; ``ok`` is False only
    where no float32 lies strictly inside the range.
    """
    t32 = t.astype(np.float32)
    up = t32.astype(np.float64) >= hi
    t32[up] = np.nextafter(t32[up], np.float32(-np.inf))
    down = t32.astype(np.float64) <= lo
    t32[down] = np.nextafter(t32[down], np.float32(np.inf))
    t64 = t32.astype(np.float64)
    return t32, (t64 > lo) & (t64 < hi)


def _exact_zero_area(tris: np.ndarray) -> np.ndarray:
    """Bool (N,): triangle has exactly zero area (collinear or repeated vertices), decided exactly.

    A float64 cross product is used as a filter; triangles whose cross product is tiny compared with
    their edge lengths (or exactly zero) are re-checked in exact rational arithmetic, so a thin but
    genuine triangle is never discarded and a degenerate one is never kept.
    """
    if len(tris) == 0:
        return np.zeros(0, bool)
    v = tris.astype(np.float64)
    e1 = v[:, 1] - v[:, 0]
    e2 = v[:, 2] - v[:, 0]
    cr = np.cross(e1, e2)
    crn = np.sqrt((cr * cr).sum(axis=1))
    scale = np.sqrt((e1 * e1).sum(axis=1) * (e2 * e2).sum(axis=1))
    with np.errstate(invalid="ignore"):
        suspicious = ~(crn > 1e-9 * scale)          # includes crn == 0 and NaN
    out = np.zeros(len(tris), bool)
    # Fast exact path: when both edge vectors are float32-exact, every product in the cross product is
    # exact in float64 (24 + 24 bits), so a component is zero iff its two products are equal.
    with np.errstate(over="ignore", invalid="ignore"):
        exact = ((e1.astype(np.float32) == e1).all(axis=1) & (e2.astype(np.float32) == e2).all(axis=1)
                 & np.isfinite(v).all(axis=(1, 2)))
    fast = suspicious & exact
    out[fast] = (cr[fast] == 0).all(axis=1)
    for i in np.flatnonzero(suspicious & ~exact):
        if not np.isfinite(tris[i]).all():
            out[i] = True                            # unusable; callers drop non-finite triangles anyway
            continue
        p = [[Fraction(float(c)) for c in vert] for vert in tris[i]]
        a = [p[1][k] - p[0][k] for k in range(3)]
        b = [p[2][k] - p[0][k] for k in range(3)]
        cx = a[1] * b[2] - a[2] * b[1]
        cy = a[2] * b[0] - a[0] * b[2]
        cz = a[0] * b[1] - a[1] * b[0]
        out[i] = cx == 0 and cy == 0 and cz == 0
    return out


# ----------------------------------------------------------------------------------------------
# Embree
# ----------------------------------------------------------------------------------------------

class EmbreeTracer:
    """Intel Embree 4 (via ``embreex``) tracer for one fixed triangle set.

    ``embreex.rtcore_scene.EmbreeScene.run(vec_origins, vec_directions, dists=None, query='INTERSECT',
    output=None)`` traces float32 ``(R, 3)`` rays one by one (``rtcIntersect1``/``rtcOccluded1``; ~5 M
    rays/s here on a 1280-triangle sphere). ``dists`` is the per-ray ``tfar`` (float32 ``(R,)``; it is
    overwritten in place with the hit distance when ``output`` is truthy, so we always pass a fresh
    array). ``tnear`` is hard-wired
    to 0 and not exposed. ``query='INTERSECT', output=1`` returns a dict with ``primID``/``geomID``
    (-1 for a miss), ``tfar`` (hit distance, or the input ``tfar`` on a miss), ``u``, ``v``, ``Ng``.
    ``query='OCCLUDED'`` returns int32 ``geomID`` per ray: 0 occluded, -1 not (``output`` must stay off
    for OCCLUDED: it returns uninitialised memory).

    Consequences handled here:

    * ``tnear``: for rays with ``tmin != 0`` the origin is moved to ``o + tmin * d`` (computed in float64
      and rounded to float32), ``tfar`` becomes ``tmax - tmin`` and ``tmin`` is added back to ``t``.
      The rounding of the moved origin perturbs the ray by up to half an ulp of ``|o + tmin d|``, so the
      returned ``t`` carries an extra absolute error of about ``ulp(|o + tmin d|) / |d|`` and hits within
      that distance of ``tmin`` may be classified either way. Rays with ``tmin == 0`` are passed exactly.
    * Embree's range test is inclusive at both ends in robust mode (``tnear <= t <= tfar``; measured: a ray
      starting exactly on a triangle gets ``t = -0.0`` with ``tnear = 0``; the non-robust mode excludes
      it), inclusive at the far end in both modes. ``tfar`` is therefore the float32 strictly below
      ``tmax - tmin``, results are post-filtered to ``tmin < t < tmax`` in float64, and a ray whose
      closest Embree hit is at or before ``tmin`` is traced again from a start nudged forward by a few
      float32 ulps of the origin (a hit within that distance past ``tmin`` can be skipped; it is within
      the rounding of the moved origin anyway).
    * Embree works in float32 throughout (its ``t`` has ~1e-7 relative error, more for grazing hits and
      hits close to the origin). The scene is created with ``robust=True`` by default
      (``RTC_SCENE_FLAG_ROBUST``: "avoid optimizations that reduce arithmetic accuracy"). Measured: in
      robust mode no ray aimed exactly at a vertex or an edge of a closed mesh leaks; with
      ``robust=False`` about 10 % of such rays from inside an icosphere escape. Embree does not cull
      back faces. Embree normalises nothing: ``t`` is in units of ``|d|``.
    * ``any_hit=True`` uses ``OCCLUDED`` for the occluded/not decision and a closest-hit query on the
      occluded rays to produce a valid ``(t, tri)``; an occlusion the closest-hit query cannot confirm
      strictly inside ``(tmin, tmax)`` (the inclusive near end; with ``robust=False`` also kernel
      differences, seen near ``t == tmax``) is reported as a miss.
    * Zero-area triangles are removed before the build (they could never hit; Embree should not report
      them either, this just makes it certain); ids still refer to the input order.
    """

    def __init__(self, triangles, robust: bool = True):
        if not self.available():
            raise RuntimeError("embreex is not installed (pip install embreex): "
                               "the Embree reference tracer is unavailable")
        from embreex import mesh_construction, rtcore_scene

        self.triangles = _as_triangles(triangles)
        self.robust = robust
        keep = ~_exact_zero_area(self.triangles) & np.isfinite(self.triangles).all(axis=(1, 2))
        self._ids = np.flatnonzero(keep).astype(np.int32)     # Embree primID -> input triangle id
        self._scene = None
        if len(self._ids):
            self._scene = rtcore_scene.EmbreeScene(robust=robust)
            kept = np.ascontiguousarray(self.triangles[keep])
            self._mesh = mesh_construction.TriangleMesh(self._scene, kept)

    @staticmethod
    def available() -> bool:
        """True when ``embreex`` can be imported."""
        try:
            import embreex.mesh_construction  # noqa: F401
            import embreex.rtcore_scene  # noqa: F401
        except Exception:
            return False
        return True

    def __len__(self) -> int:
        return len(self.triangles)

    def trace(self, origins, directions, tmin, tmax, any_hit: bool = False):
        """Trace rays; see the module docstring for the convention. Returns ``(t f32, tri i32)``."""
        o, d, t0, t1, active = prepare_rays(origins, directions, tmin, tmax)
        r = len(o)
        t_out, id_out = _miss(r)
        if r == 0 or self._scene is None or not active.any():
            return t_out, id_out
        # rays whose float32 version overflows cannot be traced by Embree: they stay misses
        with np.errstate(over="ignore"):
            fits = np.isfinite(o.astype(np.float32)) & np.isfinite(d.astype(np.float32))
        active &= fits.all(axis=1)
        idx = np.flatnonzero(active)
        o, d, t0, t1 = o[idx], d[idx], t0[idx], t1[idx]
        if any_hit:
            o32, d32, far = self._embree_rays(o, d, t0, t1)
            occ = np.flatnonzero(self._scene.run(o32, d32, dists=far, query="OCCLUDED") >= 0)
            # (t, tri) of some valid hit: the closest one; an occlusion that has no hit strictly inside
            # (tmin, tmax) -- Embree's near end is inclusive -- becomes a miss
            idx, o, d, t0, t1 = idx[occ], o[occ], d[occ], t0[occ], t1[occ]
        t, prim = self._closest(o, d, t0, t1)
        hit = np.flatnonzero(prim >= 0)
        t32, inside = _to_f32_in_range(t[hit], t0[hit], t1[hit])
        hit = hit[inside]
        t_out[idx[hit]] = t32[inside]
        id_out[idx[hit]] = self._ids[prim[hit]]
        return t_out, id_out

    @staticmethod
    def _embree_rays(o, d, lo, hi):
        """float32 rays for embreex (tnear is always 0): origin moved to o + lo d where lo != 0, and
        tfar = the largest float32 strictly below hi - lo (Embree's far end is inclusive)."""
        shift = lo != 0
        o_emb = o.copy()
        o_emb[shift] = o[shift] + lo[shift, None] * d[shift]
        o32 = np.ascontiguousarray(o_emb.astype(np.float32))
        d32 = np.ascontiguousarray(d.astype(np.float32))
        span = hi - lo                                     # > 0, may be +inf
        with np.errstate(over="ignore"):
            far = span.astype(np.float32)
        too_big = far.astype(np.float64) >= span
        far[too_big] = np.nextafter(far[too_big], np.float32(0))
        return o32, d32, np.ascontiguousarray(np.maximum(far, np.float32(0)))

    def _closest(self, o, d, t0, t1, retries: int = 4):
        """Closest hit with tmin < t < tmax (float64 t, Embree primID or -1).

        Robust Embree accepts a hit exactly at tnear (e.g. a ray starting on a surface with tmin = 0).
        Such rays are traced again from a start nudged forward by a few float32 ulps of the origin
        (doubling each retry): hits within that distance of tmin are within the rounding of the moved
        origin anyway.
        """
        n = len(o)
        t_res = np.full(n, np.inf)
        p_res = np.full(n, -1, np.int64)
        todo = np.arange(n)
        lo = t0.copy()
        for attempt in range(retries + 1):
            if len(todo) == 0:
                break
            o32, d32, far = self._embree_rays(o[todo], d[todo], lo, t1[todo])
            res = self._scene.run(o32, d32, dists=far, query="INTERSECT", output=1)
            prim = np.asarray(res["primID"]).astype(np.int64)
            t = np.asarray(res["tfar"], dtype=np.float64) + lo
            with np.errstate(invalid="ignore"):
                hit = (prim >= 0) & (t < t1[todo])
                good = hit & (t > t0[todo])
            t_res[todo[good]] = t[good]
            p_res[todo[good]] = prim[good]
            again = hit & ~good
            if attempt == retries or not again.any():
                break
            todo = todo[again]
            start = o[todo] + lo[again, None] * d[todo]
            ulp = f32_ulp(np.abs(start).max(axis=1))
            step = 4.0 * (2.0 ** attempt) * ulp / np.linalg.norm(d[todo], axis=1)
            lo = np.maximum(lo[again], t[again]) + step
        return t_res, p_res


# ----------------------------------------------------------------------------------------------
# float64 watertight brute force
# ----------------------------------------------------------------------------------------------

def trace_float64(triangles, origins, directions, tmin, tmax, any_hit: bool = False,
                  max_pairs: int = 1 << 20):
    """Brute-force float64 watertight reference (Woop, Benthin, Wald 2013).

    For each ray: ``kz`` = axis of the largest ``|d|`` component, ``kx = (kz+1)%3``, ``ky = (kx+1)%3``,
    swapped if ``d[kz] < 0`` (keeps the winding); vertices relative to the origin are sheared so the
    ray becomes the +z axis; the 2D edge functions ``U, V, W`` decide the hit: it is a hit when all are
    >= 0 or all <= 0 (no back-face culling) and ``det = U + V + W != 0``; ``t = (U Az + V Bz + W Cz) / det``.

    Watertightness: the edge function of an edge shared by two triangles is computed from identical
    transformed vertices and is the exact negation of the neighbour's (the float products commute), so
    a ray can never pass between two triangles sharing an edge or a vertex, whatever the rounding.
    The paper's higher-precision fallback (recompute ``U, V, W`` in double when one is exactly 0 in float)
    is skipped: everything is already float64 (from float32 inputs), so an edge function that rounds to
    exactly 0 is treated as "on the edge" (counted as a hit for both neighbours). This only matters for
    rays within ~1e-16 relative of an edge and never creates a leak.

    The range test ``tmin < t < tmax`` is made on the float64 ``t`` (relative error ~1e-16): a hit that
    lies exactly at ``tmax`` in real arithmetic (a shadow ray ending on the light's own surface) can be
    counted or not; callers that care must treat hits within rounding of the range ends as ambiguous.

    Zero-area triangles (decided exactly) never hit. Ties: smallest ``t``, then the smallest triangle id.
    ``any_hit`` is accepted for API symmetry; the closest hit is returned (a valid any-hit answer).

    Cost is O(R * N) (~25 ns per pair for a bounding-sphere prefilter, then the exact test on the
    surviving pairs); work is chunked so at most ``max_pairs`` (ray, triangle) pairs are live at once
    (~100 bytes each -> ~100 MB with the default). Meant for <= a few thousand triangles, <= ~1e5 rays.
    """
    del any_hit  # the closest hit is a valid any-hit answer
    tris = _as_triangles(triangles)
    o, d, t0, t1, active = prepare_rays(origins, directions, tmin, tmax)
    r = len(o)
    best_t = np.full(r, np.inf)
    best_id = np.full(r, -1, np.int64)
    if r == 0 or len(tris) == 0 or not active.any():
        return _miss(r)

    good = ~_exact_zero_area(tris) & np.isfinite(tris).all(axis=(1, 2))
    tri_ids = np.flatnonzero(good)
    if len(tri_ids) == 0:
        return _miss(r)
    verts = tris[tri_ids].astype(np.float64)                # (M, 3, 3)

    ad = np.abs(d)
    kz = np.argmax(ad, axis=1)                              # first max on ties: deterministic
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = d[np.arange(r), kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)

    # Conservative bounding-sphere prefilter: only (ray, triangle) pairs whose line passes within the
    # padded sphere are tested exactly. Rounding in the filter is ~1e-15 of the coordinate magnitude;
    # the padding (1e-9 relative + 1e-12 of the scene/origin scale) is far larger, so no hit is lost.
    centre = verts.mean(axis=1)
    rad = np.sqrt(((verts - centre[:, None, :]) ** 2).sum(axis=2).max(axis=1))
    scale = float(np.abs(centre).max() + np.abs(o[active]).max())
    rad2 = (rad * (1 + 1e-9) + 1e-12 * scale) ** 2
    dd = (d * d).sum(axis=1)

    m = len(tri_ids)
    tri_chunk = max(1, min(m, max_pairs))
    ray_chunk = max(1, max_pairs // tri_chunk)
    code = kz * 2 + neg
    for c in np.unique(code[active]):
        sel = np.flatnonzero(active & (code == c))
        p = [int(kx[sel[0]]), int(ky[sel[0]]), int(kz[sel[0]])]
        vp = verts[:, :, p]                                 # (M, 3, 3) permuted to (x, y, z)
        for rs in range(0, len(sel), ray_chunk):
            rid = sel[rs:rs + ray_chunk]
            for ts in range(0, m, tri_chunk):
                te = min(m, ts + tri_chunk)
                ri, ti = _sphere_candidates(centre[ts:te], rad2[ts:te], o[rid], d[rid], dd[rid])
                if len(ri) == 0:
                    continue
                ti += ts
                rg = rid[ri]                                # global ray index of each pair
                t = _woop_pairs(vp[ti], o[rg][:, p], d[rg][:, p], t0[rg], t1[rg])
                ok = t < np.inf
                rg, ti, t = rg[ok], ti[ok], t[ok]
                if len(t) == 0:
                    continue
                # closest per ray, ties -> smallest triangle id (ids increase with ti)
                order = np.lexsort((ti, t, rg))
                rg, ti, t = rg[order], ti[order], t[order]
                first = np.ones(len(rg), bool)
                first[1:] = rg[1:] != rg[:-1]
                rg, ti, t = rg[first], ti[first], t[first]
                better = t < best_t[rg]                     # strict: earlier chunks (smaller ids) win ties
                best_t[rg[better]] = t[better]
                best_id[rg[better]] = tri_ids[ti[better]]

    hit = np.flatnonzero(best_id >= 0)
    t_out, id_out = _miss(r)
    t32, inside = _to_f32_in_range(best_t[hit], t0[hit], t1[hit])
    t_out[hit[inside]] = t32[inside]
    id_out[hit[inside]] = best_id[hit[inside]]
    return t_out, id_out


def _sphere_candidates(centre, rad2, o, d, dd):
    """(ray, triangle) index pairs whose ray line passes within the (padded) bounding sphere."""
    wx = centre[None, :, 0] - o[:, None, 0]
    wy = centre[None, :, 1] - o[:, None, 1]
    wz = centre[None, :, 2] - o[:, None, 2]
    cx = wy * d[:, None, 2]
    cx -= wz * d[:, None, 1]
    cy = wz * d[:, None, 0]
    cy -= wx * d[:, None, 2]
    cz = wx * d[:, None, 1]
    cz -= wy * d[:, None, 0]
    cx *= cx
    cy *= cy
    cz *= cz
    cx += cy
    cx += cz
    return np.nonzero(cx <= rad2[None, :] * dd[:, None])


def _woop_pairs(v, op, dp, lo, hi):
    """Watertight test of K (ray, triangle) pairs, axes already permuted to (kx, ky, kz).

    ``v`` (K, 3, 3) vertices, ``op``/``dp`` (K, 3) origins/directions, ``lo``/``hi`` (K,) range.
    Returns t (K,) with +inf for a miss.
    """
    sx = dp[:, 0] / dp[:, 2]
    sy = dp[:, 1] / dp[:, 2]
    sz = 1.0 / dp[:, 2]
    # vertices relative to the ray origin, then sheared; the same expression for every vertex, so a
    # vertex shared by two triangles transforms to identical values for both
    a = v[:, 0] - op
    b = v[:, 1] - op
    c = v[:, 2] - op
    ax = a[:, 0] - sx * a[:, 2]
    ay = a[:, 1] - sy * a[:, 2]
    bx = b[:, 0] - sx * b[:, 2]
    by = b[:, 1] - sy * b[:, 2]
    cx = c[:, 0] - sx * c[:, 2]
    cy = c[:, 1] - sy * c[:, 2]
    u = cx * by - cy * bx
    w_ = bx * ay - by * ax
    vv = ax * cy - ay * cx
    inside = ((u >= 0) & (vv >= 0) & (w_ >= 0)) | ((u <= 0) & (vv <= 0) & (w_ <= 0))
    det = u + vv + w_
    inside &= det != 0
    tt = u * (sz * a[:, 2]) + vv * (sz * b[:, 2]) + w_ * (sz * c[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = tt / det
    inside &= (tt > lo) & (tt < hi)
    tt[~inside] = np.inf
    return tt


# ----------------------------------------------------------------------------------------------
# comparison
# ----------------------------------------------------------------------------------------------

def compare_hits(t_a, id_a, t_b, id_b, triangles=None, rel_tol: float = 1e-5, tie_rel: float = 1e-6,
                 abs_tol=0.0) -> dict:
    """Agreement statistics between two tracers' results on the same rays (``b`` is the reference).

    A ray *hits* when its id is >= 0. Where both hit with different ids, the ids count as a *tie*
    (agreement) when ``|t_a - t_b| <= tie_rel * max(|t_a|, |t_b|)`` (the two triangles are met at the same
    distance: shared edge/vertex, coplanar overlap), or when both ids name triangles with identical
    vertex sets (duplicates; needs ``triangles``). Relative distance error is
    ``|t_a - t_b| / max(|t_a|, |t_b|)`` (0 where both are 0) over rays where both hit.
    ``abs_tol`` (scalar or per ray, in units of ``t``; default 0) is added to both tolerances
    (``tie_rel * max(t) + abs_tol`` and ``rel_tol * max(t) + abs_tol``): use it where float32 inputs carry
    an absolute error, e.g. a scene far from the origin (a few float32 ulps of the coordinates / ``|d|``).

    Returned keys:
      n_rays, n_both_hit, n_both_miss, n_a_only (a hits, b misses), n_b_only,
      hitmiss_agree (fraction of rays), n_same_id, n_tie, n_id_mismatch (both hit, different ids, no tie),
      id_agree (fraction of all rays: both miss, or both hit with same id or a tie),
      id_agree_hits (same over rays where both hit; 1.0 when there are none),
      max_rel_err, p999_rel_err (0.0 when no ray hits in both),
      n_t_exceed (both hit, |t_a - t_b| > rel_tol * max(t) + abs_tol; rays with different ids count too),
      n_bad_id (a hit id outside [0, N) when ``triangles`` is given), rel_tol, tie_rel,
      ok (no hit/miss disagreement, no id mismatch, no t beyond rel_tol, no bad id).
    """
    t_a = np.asarray(t_a, np.float64).ravel()
    t_b = np.asarray(t_b, np.float64).ravel()
    id_a = np.asarray(id_a, np.int64).ravel()
    id_b = np.asarray(id_b, np.int64).ravel()
    if not (len(t_a) == len(t_b) == len(id_a) == len(id_b)):
        raise ValueError("compare_hits: all arrays must have the same length")
    n = len(t_a)
    ha, hb = id_a >= 0, id_b >= 0
    both = ha & hb
    n_both = int(both.sum())
    same = both & (id_a == id_b)

    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.maximum(np.abs(t_a), np.abs(t_b))
        diff = np.abs(t_a - t_b)
        rel = np.where(diff == 0, 0.0, diff / scale)
    rel = np.where(both, rel, 0.0)
    rel = np.where(np.isnan(rel), np.inf, rel)
    abs_tol = np.broadcast_to(np.asarray(abs_tol, np.float64), t_a.shape)
    with np.errstate(invalid="ignore"):
        tie = both & ~same & (diff <= tie_rel * scale + abs_tol)
        exceed = both & (diff > rel_tol * scale + abs_tol)

    n_bad = 0
    if triangles is not None:
        tris = np.asarray(triangles)
        ntri = len(tris)
        bad = (ha & (id_a >= ntri)) | (hb & (id_b >= ntri))
        n_bad = int(bad.sum())
        for i in np.flatnonzero(both & ~same & ~tie & ~bad):
            va = sorted(map(tuple, np.asarray(tris[id_a[i]]).reshape(3, 3).tolist()))
            vb = sorted(map(tuple, np.asarray(tris[id_b[i]]).reshape(3, 3).tolist()))
            tie[i] = va == vb

    mismatch = both & ~same & ~tie
    relb = rel[both]
    n_exceed = int(exceed.sum())
    out = {
        "n_rays": n,
        "n_both_hit": n_both,
        "n_both_miss": int((~ha & ~hb).sum()),
        "n_a_only": int((ha & ~hb).sum()),
        "n_b_only": int((~ha & hb).sum()),
        "hitmiss_agree": float((ha == hb).mean()) if n else 1.0,
        "n_same_id": int(same.sum()),
        "n_tie": int(tie.sum()),
        "n_id_mismatch": int(mismatch.sum()),
        "id_agree": float(((~ha & ~hb) | same | tie).mean()) if n else 1.0,
        "id_agree_hits": float((same | tie)[both].mean()) if n_both else 1.0,
        "max_rel_err": float(relb.max()) if n_both else 0.0,
        "p999_rel_err": float(np.quantile(relb, 0.999)) if n_both else 0.0,
        "n_t_exceed": n_exceed,
        "n_bad_id": n_bad,
        "rel_tol": rel_tol,
        "tie_rel": tie_rel,
    }
    out["ok"] = (out["n_a_only"] == 0 and out["n_b_only"] == 0 and out["n_id_mismatch"] == 0
                 and n_exceed == 0 and n_bad == 0)
    return out


# ----------------------------------------------------------------------------------------------
# geometric helpers for judging disagreements (tests, benchmarks)
# ----------------------------------------------------------------------------------------------

def f32_ulp(x) -> np.ndarray:
    """Float32 spacing at ``|x|`` (float64 array)."""
    a = np.abs(np.asarray(x, np.float64)).astype(np.float32)
    return (np.nextafter(a, np.float32(np.inf)) - a).astype(np.float64)


def _seg_dist(p, a, b):
    ab = b - a
    ap = p - a
    den = (ab * ab).sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip((ap * ab).sum(axis=-1) / den, 0.0, 1.0)
    s = np.where(den > 0, s, 0.0)
    q = ap - s[..., None] * ab
    return np.sqrt((q * q).sum(axis=-1))


def point_triangle_distance(points, triangles) -> np.ndarray:
    """Euclidean distance (float64, (K,)) from each point (K, 3) to the matching triangle (K, 3, 3)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    v = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    n = np.cross(v1 - v0, v2 - v0)
    nn = np.sqrt((n * n).sum(axis=1))
    e = np.minimum(np.minimum(_seg_dist(p, v0, v1), _seg_dist(p, v1, v2)), _seg_dist(p, v2, v0))
    c0 = (np.cross(v1 - p, v2 - p) * n).sum(axis=1)
    c1 = (np.cross(v2 - p, v0 - p) * n).sum(axis=1)
    c2 = (np.cross(v0 - p, v1 - p) * n).sum(axis=1)
    inside = (nn > 0) & (c0 >= 0) & (c1 >= 0) & (c2 >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = np.abs(((p - v0) * n).sum(axis=1)) / nn
    return np.where(inside, plane, e)


def ray_edge_distance(triangles, ids, origins, directions):
    """Distance (float64, (K,)) between each ray's line and the nearest edge of triangle ``ids[i]``.

    ``+inf`` where ``ids[i] < 0``. This is the quantity that decides how ill-conditioned a hit/miss
    decision is: a float32 tracer working in ray space (or world space) makes errors of a few ulps of
    the coordinate magnitude in it, whatever the angle between the ray and the triangle, so grazing
    rays are covered as well. Used to excuse hit/miss disagreements within rounding of an edge.
    """
    tris = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    ids = np.asarray(ids).ravel()
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    out = np.full(len(ids), np.inf)
    sel = np.flatnonzero(ids >= 0)
    if len(sel) == 0:
        return out
    v = tris[ids[sel]]
    dn = d[sel] / np.linalg.norm(d[sel], axis=1, keepdims=True)

    def perp(x):                        # component perpendicular to the ray
        return x - (x * dn).sum(axis=1, keepdims=True) * dn

    best = np.full(len(sel), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        w = perp(v[:, a] - o[sel])
        e = perp(v[:, b] - v[:, a])
        ee = (e * e).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.clip(-(w * e).sum(axis=1) / ee, 0.0, 1.0)
        u = np.where(ee > 0, u, 0.0)
        q = w + u[:, None] * e
        best = np.minimum(best, np.sqrt((q * q).sum(axis=1)))
    out[sel] = best
    return out

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

* :class:`EmbreeTracer` -- Intel Embree 4 through ``embreex`` finds the triangle (float32, fast, for big
  scenes); distances and range decisions are float64 (see the class).
* :func:`trace_float64` -- brute force, float64, watertight (Woop et al. 2013); for small scenes.

and :func:`compare_hits`, the agreement statistics used by tests and benchmarks.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

REFERENCE_BACKEND = "embree"  # the registry name of the backend that traces with EmbreeTracer

__all__ = ["EmbreeTracer", "RawRays", "trace_float64", "compare_hits", "prepare_rays", "point_triangle_distance",
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

def _fits_float32(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Rays whose float32 origin and direction are finite: the only ones Embree can trace."""
    with np.errstate(over="ignore"):
        return (np.isfinite(o.astype(np.float32)) & np.isfinite(d.astype(np.float32))).all(axis=1)


@dataclass
class RawRays:
    """Rays exactly as EmbreeTracer hands them to embreex's run(): float32 origins with tmin folded
    in (Embree's tnear is 0), directions and the slightly widened tfar (see EmbreeTracer)."""

    origins: np.ndarray  # float32 (A, 3), contiguous
    directions: np.ndarray  # float32 (A, 3), contiguous
    far: np.ndarray  # float32 (A,)

    def __len__(self) -> int:
        return len(self.far)


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

    * Embree only chooses the triangle; the distance and the range decision are float64. For the
      triangle Embree returns, ``t`` is recomputed on the caller's ray (``range_decision``: the plane
      distance in float64, in rational arithmetic where it lies within its error bound of ``tmin`` or
      ``tmax``), and ``tmin < t < tmax`` is decided on that, never on Embree's float32 ``t`` (which on
      an AVX2 CPU returned 0.99999994 for an exact 1 = tmax). Embree therefore gets a slightly longer
      range than asked (``_embree_rays``): ``tnear`` is hard-wired to 0, so for ``tmin != 0`` the origin
      moves to ``o + (tmin - m) d`` (float32), m = 64 float32 ulps of the coordinates over ``|d|``, and
      ``tfar`` ends 1e-3 relative plus m past ``tmax``.
    * A ray whose closest Embree hit lies at or before ``tmin`` in float64 starts on (or within float32
      rounding of) a surface: Embree's robust mode accepts ``t = 0`` (its near end is inclusive), and far
      from the origin a float32 start is up to 1/32 unit off the surface (at 1e6). Such rays are not
      decided by a re-trace from a nudged start (that jumped past real hits, 1/4 unit at 1e6): Embree,
      traced from a little after ``tmin``, only bounds a segment of the ray, which is searched with the
      float64 watertight test over the triangles near it (``_TriangleGrid``, ``_resolve_from_start``).
    * Embree works in float32 throughout (its ``t`` has ~1e-7 relative error, more for grazing hits and
      hits close to the origin). The scene is created with ``robust=True`` by default
      (``RTC_SCENE_FLAG_ROBUST``: "avoid optimizations that reduce arithmetic accuracy"). Measured: in
      robust mode no ray aimed exactly at a vertex or an edge of a closed mesh leaks; with
      ``robust=False`` about 10 % of such rays from inside an icosphere escape. Embree does not cull
      back faces. Embree normalises nothing: ``t`` is in units of ``|d|``.
    * ``any_hit=True`` uses ``OCCLUDED`` (over the same widened range) to find the rays that may be
      occluded and the closest-hit path above on those, so occluded-or-not is decided in float64 too.
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
        self._v64: np.ndarray | None = None
        self._scale = float(np.abs(self.triangles[keep]).max()) if keep.any() else 0.0
        self._grid_cache: _TriangleGrid | None = None
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
        active &= _fits_float32(o, d)  # rays whose float32 version overflows stay misses
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

    def raw_rays(self, origins, directions, tmin, tmax) -> RawRays:
        """The active rays as trace() gives them to Embree (inactive or float32-overflowing rays dropped),
        for timing Embree alone on the same rays (time_raw)."""
        o, d, t0, t1, active = prepare_rays(origins, directions, tmin, tmax)
        active &= _fits_float32(o, d)
        return RawRays(*self._embree_rays(o[active], d[active], t0[active], t1[active]))

    def time_raw(self, rays: RawRays, any_hit: bool, threads: int = 1) -> tuple[float, float]:
        """(wall ms, process CPU ms) of embreex's bare run() -- INTERSECT, or OCCLUDED for `any_hit` --
        over `rays`, split in equal slices over `threads` Python threads (run() releases the GIL). No
        float64 decision: the cost of Embree itself, to compare tracers against."""
        if self._scene is None or len(rays) == 0:
            return 0.0, 0.0
        query = "OCCLUDED" if any_hit else "INTERSECT"

        def run(lo: int, hi: int) -> None:
            self._scene.run(rays.origins[lo:hi], rays.directions[lo:hi], dists=rays.far[lo:hi].copy(), query=query)

        bounds = np.linspace(0, len(rays), max(1, threads) + 1).astype(int)
        workers = [threading.Thread(target=run, args=(int(bounds[i]), int(bounds[i + 1]))) for i in range(threads)]
        c0 = time.process_time()
        t0 = time.perf_counter()
        if threads <= 1:
            run(0, len(rays))
        else:
            for w in workers:
                w.start()
            for w in workers:
                w.join()
        return (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3

    def _embree_rays(self, o, d, lo, hi, back: bool = True):
        """float32 rays for embreex (tnear is always 0), covering a little more than (lo, hi): the
        float64 decision follows, so Embree must not drop a hit that float32 rounding puts just outside.

        Where lo != 0 the origin moves to o + (lo - m) d (`back`; else to o + lo d), m = 64 float32
        ulps of the larger of |start| and the scene's coordinates over |d|: rounding the moved origin
        and Embree's float32 distance (its error grows with the vertices' magnitude) must not skip a
        hit just after lo. tfar ends 1e-3 relative plus m past hi (a float32 t may round past tmax,
        more so for grazing hits). Embree's t is not used: callers recompute distances in float64."""
        dn = np.linalg.norm(d, axis=1)
        shift = lo != 0
        o_emb = o.copy()
        o_emb[shift] = o[shift] + lo[shift, None] * d[shift]
        m = self._margin(o_emb, dn)
        start = np.where(shift, lo - m, 0.0) if back else np.where(shift, lo, 0.0)
        o_emb[shift] = o[shift] + start[shift, None] * d[shift]
        o32 = np.ascontiguousarray(o_emb.astype(np.float32))
        d32 = np.ascontiguousarray(d.astype(np.float32))
        span = hi - start                                  # > 0, may be +inf
        slack = 1e-3 * span + m
        with np.errstate(over="ignore", invalid="ignore"):
            far = (span + slack).astype(np.float32)
        far[~np.isfinite(far)] = np.float32(np.inf)
        return o32, d32, np.ascontiguousarray(far)

    def _closest(self, o, d, t0, t1):
        """Closest hit with tmin < t < tmax, decided in float64 (t float64, Embree primID or -1).

        Embree finds the triangle; its distance is recomputed in float64 on the caller's ray and
        ``tmin < t < tmax`` is decided on that (exactly near the ends, see ``range_decision``), never on
        Embree's float32 t. Embree is given a slightly longer ``tfar`` so that a hit whose float32 t
        rounds past ``tmax`` is still seen. A ray whose closest Embree hit lies at or before ``tmin``
        (it starts on a surface, or its float32 start rounded onto or past one) is resolved by
        ``_resolve_from_start``."""
        n = len(o)
        t_res = np.full(n, np.inf)
        p_res = np.full(n, -1, np.int64)
        if n == 0:
            return t_res, p_res
        prim = self._run_closest(o, d, t0, t1)
        hit = np.flatnonzero(prim >= 0)
        if len(hit) == 0:
            return t_res, p_res
        v = self._verts64[prim[hit]]
        t, ok = range_decision(v, o[hit], d[hit], t0[hit], t1[hit])
        t_res[hit[ok]] = t[ok]
        p_res[hit[ok]] = prim[hit[ok]]
        with np.errstate(invalid="ignore"):
            before = ~ok & ~(t >= t1[hit])               # at/before tmin, or parallel: Embree's t is noise
        flagged = hit[before]
        if len(flagged):
            tf, pf = self._resolve_from_start(o[flagged], d[flagged], t0[flagged], t1[flagged])
            t_res[flagged] = tf
            p_res[flagged] = pf
        return t_res, p_res

    def _margin(self, p, dn, ulps: int = 64):
        """`ulps` float32 ulps of max(|p|, the scene's largest coordinate) over |d|: the reach of
        float32 rounding along the ray (positions, Embree's distances; x 1/sin for a hit at angle sin
        to its plane: 64 covers sin down to ~0.01) in units of t."""
        return ulps * f32_ulp(np.maximum(np.abs(p).max(axis=1), self._scale)) / dn

    def _run_closest(self, o, d, t0, t1, back: bool = True) -> np.ndarray:
        """Embree's closest hit (primID or -1) from o + t0 d (backed off, see _embree_rays), up to a
        little past t1."""
        o32, d32, far = self._embree_rays(o, d, t0, t1, back)
        res = self._scene.run(o32, d32, dists=far, query="INTERSECT", output=1)
        return np.asarray(res["primID"]).astype(np.int64)

    def _resolve_from_start(self, o, d, t0, t1, rounds: int = 4):
        """Rays whose closest Embree hit is at or before tmin: their hits are found in float64.

        Embree cannot say what lies within float32 rounding of the ray's start (about ulp(|start|), a
        quarter unit at 1e6), and a start moved along the ray and rounded to float32 is off the ray by
        up to half an ulp sideways (1/32 unit at 1e6), which changes which triangle an edge-near ray
        meets. So Embree only bounds the search: it traces from lo + w (w = 16 float32 ulps of the
        start or the scene's coordinates, `_margin`), its triangle's float64 distance t_T on the
        caller's ray gives the segment (lo, t_T + 2w], and every triangle near that segment (grid
        lookup) is tested with the float64 watertight test; the closest hit there is the answer.
        Where the segment holds none (Embree's start was behind a surface, or it found nothing: then
        the segment is (lo, lo + 2w]), the next round starts at the segment's end with w x 4. Rays left
        after `rounds` are traced by brute force over all triangles."""
        n = len(o)
        t_res = np.full(n, np.inf)
        p_res = np.full(n, -1, np.int64)
        dn = np.linalg.norm(d, axis=1)
        lo = t0.copy()
        todo = np.arange(n)
        w = self._margin(o + t0[:, None] * d, dn, 16)
        grid = self._grid()
        for _ in range(rounds):
            if len(todo) == 0:
                break
            oo, dd, ll, hh, ww = o[todo], d[todo], lo[todo], t1[todo], w[todo]
            prim = self._run_closest(oo, dd, ll + ww, hh, back=False)
            end = ll + 2 * ww
            hit = np.flatnonzero(prim >= 0)
            if len(hit):
                t_t, _ = _plane_t(self._verts64[prim[hit]], oo[hit], dd[hit])
                with np.errstate(invalid="ignore"):
                    end[hit] = np.maximum(end[hit], np.where(np.isfinite(t_t), t_t, -np.inf) + 2 * ww[hit])
            end = np.minimum(end, hh)
            top = np.minimum(np.nextafter(end, np.inf), hh)          # the segment includes its end
            ri, ti = grid.candidates(oo + ll[:, None] * dd, oo + end[:, None] * dd)
            tw, pw = _closest_pairs(self._verts64, ri, ti, oo, dd, ll, top, len(todo))
            found = pw >= 0
            t_res[todo[found]] = tw[found]
            p_res[todo[found]] = pw[found]
            again = ~found & (end < hh) & (prim >= 0)                # Embree saw nothing past lo + w: a miss
            todo = todo[again]
            lo[todo] = end[again]
            w[todo] *= 4
        if len(todo):
            tb, pb = trace_float64(self.triangles[self._ids], o[todo], d[todo], lo[todo], t1[todo])
            t_res[todo] = tb
            p_res[todo] = pb
        return t_res, p_res

    @property
    def _verts64(self) -> np.ndarray:
        """float64 (M, 3, 3) vertices of the triangles given to Embree (indexed by primID)."""
        if self._v64 is None:
            self._v64 = self.triangles[self._ids].astype(np.float64)
        return self._v64

    def _grid(self) -> _TriangleGrid:
        if self._grid_cache is None:
            self._grid_cache = _TriangleGrid(self._verts64)
        return self._grid_cache


def _closest_pairs(verts, ri, ti, o, d, lo, hi, n):
    """Closest float64 watertight hit per ray over (ray, triangle) pairs ri/ti (ray index into o/d/lo/hi,
    triangle index into verts). Returns (t (n,), triangle (n,) or -1); ties: the smallest index."""
    t_out = np.full(n, np.inf)
    p_out = np.full(n, -1, np.int64)
    if len(ri) == 0:
        return t_out, p_out
    ad = np.abs(d[ri])
    kz = np.argmax(ad, axis=1)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = d[ri][np.arange(len(ri)), kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)
    perm = np.stack([kx, ky, kz], axis=1)
    vp = np.take_along_axis(verts[ti], perm[:, None, :], axis=2)
    op = np.take_along_axis(o[ri], perm, axis=1)
    dp = np.take_along_axis(d[ri], perm, axis=1)
    t = _woop_pairs(vp, op, dp, lo[ri], hi[ri])
    ok = t < np.inf
    ri, ti, t = ri[ok], ti[ok], t[ok]
    if len(t) == 0:
        return t_out, p_out
    order = np.lexsort((ti, t, ri))
    ri, ti, t = ri[order], ti[order], t[order]
    first = np.ones(len(ri), bool)
    first[1:] = ri[1:] != ri[:-1]
    t_out[ri[first]] = t[first]
    p_out[ri[first]] = ti[first]
    return t_out, p_out


class _TriangleGrid:
    """Uniform grids over triangle bounding boxes, for "which triangles are near this short segment".

    Level k has cells of 4^k times the median bounding-box extent; a triangle goes to the first level
    where its box spans at most 27 cells, or, past the last level, to a list tested against every
    query. Cells are keyed by their integer coordinates packed in an int64 (no collisions for grids
    up to 2^21 cells a side; beyond, distinct cells may share a key, which only adds candidates)."""

    MAX_CELLS = 27
    LEVELS = 6

    def __init__(self, verts: np.ndarray):
        lo = verts.min(axis=1)
        hi = verts.max(axis=1)
        ext = (hi - lo).max(axis=1)
        self.origin = lo.min(axis=0) if len(lo) else np.zeros(3)
        span = float((hi.max(axis=0) - self.origin).max()) if len(hi) else 1.0
        base = max(float(np.median(ext)) if len(ext) else 1.0, span / 2**20, 1e-30)
        self.levels: list[tuple[float, np.ndarray, np.ndarray]] = []   # (cell, sorted keys, triangles)
        left = np.arange(len(verts))
        for k in range(self.LEVELS):
            cell = base * 4.0**k
            c0 = self._cell(lo[left], cell)
            c1 = self._cell(hi[left], cell)
            fits = (c1 - c0 + 1).prod(axis=1) <= self.MAX_CELLS
            keys, tris = _expand_cells(c0[fits], c1[fits], left[fits])
            order = np.argsort(keys, kind="stable")
            self.levels.append((cell, keys[order], tris[order]))
            left = left[~fits]
        self.big = left
        self.stride = len(verts) + 1

    def _cell(self, p, cell):
        return np.floor((p - self.origin) / cell).astype(np.int64)

    def candidates(self, a, b):
        """(query, triangle) pairs for segments a[i]..b[i] (K, 3): every triangle whose bounding box
        comes within a few float32 ulps of the segment's box (conservative), with repeats removed."""
        pad = 4 * f32_ulp(np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1)))[:, None]
        ri_all, ti_all = [], []
        for cell, keys, tris in self.levels:
            if len(keys) == 0:
                continue
            # a long diagonal segment is cut into pieces about one cell long: thin boxes, few cells
            pieces = np.clip(np.ceil(np.abs(b - a).max(axis=1) / cell), 1, 256).astype(np.int64)
            qi = np.repeat(np.arange(len(a)), pieces)
            j = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
            f0 = (j / pieces[qi])[:, None]
            f1 = ((j + 1) / pieces[qi])[:, None]
            p0 = a[qi] + f0 * (b[qi] - a[qi])
            p1 = a[qi] + f1 * (b[qi] - a[qi])
            lo = np.minimum(p0, p1) - pad[qi] - 1e-9 * cell
            hi = np.maximum(p0, p1) + pad[qi] + 1e-9 * cell
            qk, qi = _expand_cells(self._cell(lo, cell), self._cell(hi, cell), qi)
            first = np.searchsorted(keys, qk, side="left")
            cnt = np.searchsorted(keys, qk, side="right") - first
            rep = np.repeat(np.arange(len(qk)), cnt)
            off = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            ri_all.append(qi[rep])
            ti_all.append(tris[first[rep] + off])
        if len(self.big):
            ri_all.append(np.repeat(np.arange(len(a)), len(self.big)))
            ti_all.append(np.tile(self.big, len(a)))
        if not ri_all:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ri = np.concatenate(ri_all)
        ti = np.concatenate(ti_all)
        pair = np.unique(ri * self.stride + ti, return_index=True)[1]
        return ri[pair], ti[pair]


def _expand_cells(c0, c1, ids):
    """Every integer cell of the boxes c0[i]..c1[i] (inclusive): (packed keys, ids[i] per cell)."""
    size = c1 - c0 + 1
    count = size.prod(axis=1)
    rep = np.repeat(np.arange(len(ids)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = size[rep, 0], size[rep, 1]
    cx = c0[rep, 0] + k % sx
    cy = c0[rep, 1] + (k // sx) % sy
    cz = c0[rep, 2] + k // (sx * sy)
    m = (1 << 21) - 1
    keys = (cx & m) | ((cy & m) << 21) | ((cz & m) << 42)
    return keys, ids[rep]


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

    The range test ``tmin < t < tmax`` is exact: the float64 ``t`` decides where it is clear of both
    ends; within 1e-9 of the vertices' distance from the origin of an end (a ray starting on the
    triangle's plane gets t ~ 1e-20 instead of 0; a hit exactly at ``tmax``) the exact plane distance
    decides (``range_decision``). A hit exactly at ``tmax`` or ``tmin`` in real arithmetic is a miss.

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
    # t is float64-accurate relative to the vertices' distances from the origin, not to t itself: a ray
    # starting exactly on a triangle's plane gets t ~ 1e-20 instead of 0. Near a range end (within
    # 1e-9 of that scale) the decision tmin < t < tmax is made on the exact plane distance instead.
    reach = np.maximum(np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1)), np.abs(c).max(axis=1))
    band = 1e-9 * reach / np.abs(dp).max(axis=1)
    with np.errstate(invalid="ignore"):
        near = inside & ((np.abs(tt - lo) <= band) | (np.abs(tt - hi) <= band))
    ok = inside & (tt > lo) & (tt < hi)
    if near.any():
        k = np.flatnonzero(near)
        t_near, ok_near = range_decision(v[k], op[k], dp[k], lo[k], hi[k])
        tt[k] = t_near
        ok[k] = ok_near
    tt[~ok] = np.inf
    return tt


def _plane_t(v, o, d):
    """float64 distance along each ray to its triangle's plane (K,) and a bound on its rounding error.

    ``t = n . (v0 - o) / n . d`` with ``n = (v1 - v0) x (v2 - v0)``; NaN/inf where the ray is parallel to
    the plane. From float32 inputs the differences are exact and each product and sum adds at most one
    rounding, so ``|error| <= 16 eps (|n| |v0 - o| + |t| |n| |d|) / |n . d|``; 64 eps is used."""
    e1 = v[:, 1] - v[:, 0]
    e2 = v[:, 2] - v[:, 0]
    n = np.cross(e1, e2)
    w = v[:, 0] - o
    num = (n * w).sum(axis=1)
    den = (n * d).sum(axis=1)
    nn = np.abs(n).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
        err = 64 * np.finfo(np.float64).eps * (nn * np.abs(w).sum(axis=1) + np.abs(t) * nn * np.abs(d).sum(axis=1)) \
            / np.abs(den)
    return t, err


def _exact_plane_t(v, o, d) -> tuple[int, int] | None:
    """The exact plane distance of one ray as a fraction (num, den) of Python ints with den > 0; None
    when the ray is parallel to the plane. The coordinates are dyadic rationals: scaled by their
    largest denominator (a power of two) they are integers, and the products are exact big ints."""
    ratios = [float(x).as_integer_ratio() for x in (*np.ravel(v), *o, *d)]
    scale = max(b for _, b in ratios)
    ints = [a * (scale // b) for a, b in ratios]
    q = [ints[0:3], ints[3:6], ints[6:9]]
    oo = ints[9:12]
    dd = ints[12:15]
    e1 = [q[1][k] - q[0][k] for k in range(3)]
    e2 = [q[2][k] - q[0][k] for k in range(3)]
    n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
    den = sum(n[k] * dd[k] for k in range(3))
    if den == 0:
        return None
    num = sum(n[k] * (q[0][k] - oo[k]) for k in range(3))
    return (num, den) if den > 0 else (-num, -den)


def _compare(t: tuple[int, int], x: float) -> int:
    """Sign of num/den - x for t = (num, den), den > 0, and a finite float64 x (exact)."""
    a, b = float(x).as_integer_ratio()
    lhs = t[0] * b
    rhs = a * t[1]
    return (lhs > rhs) - (lhs < rhs)


def range_decision(v, o, d, lo, hi):
    """Decide ``lo < t < hi`` exactly for rays known to meet their triangle (v (K, 3, 3), o, d (K, 3),
    lo, hi (K,), all float64 holding float32-exact coordinates; lo/hi any float64).

    Returns ``(t, ok)``: the float64 plane distance (the exact one rounded where it was needed) and the
    decision. The float64 distance decides where its error bound keeps it clear of both ends; the few
    rays within the bound of an end (a ray starting on the surface, a hit exactly at ``tmax``) are
    decided in rational arithmetic. A ray parallel to the plane is never in range (as in the watertight
    test, whose determinant is then 0)."""
    t, err = _plane_t(v, o, d)
    with np.errstate(invalid="ignore"):
        ok = (t - err > lo) & (t + err < hi)
        unsure = np.isfinite(t) & ~ok & (t + err > lo) & (t - err < hi)
    for i in np.flatnonzero(unsure):           # few rays: the exact decision in integers
        te = _exact_plane_t(v[i], o[i], d[i])
        if te is None:
            continue
        above = np.isneginf(lo[i]) or _compare(te, lo[i]) > 0
        below = np.isposinf(hi[i]) or _compare(te, hi[i]) < 0
        ok[i] = above and below
        t[i] = te[0] / te[1]                   # correctly rounded int division
    return t, ok


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

"""A tiny CPU backend that exists only to show the backend contract from the outside.

It is a real tracer, just a slow one: it reads the rays back (`RayBatch.read()`), tests every
active ray against every triangle with the watertight ray/triangle test (Woop, Benthin, Wald
2013, as shaders/intersect.glsl) in float64 NumPy, and writes the nearest hit with
`HitBuffer.write()`. Meant for scenes of a few dozen triangles.

What it declares in `info` is what generic code (renderer, overlay views, panel, bench harness)
must be driven by without knowing it: parameters (`FakeParams`, with `validate`), two overlays,
counters and phase names. Overlays (R32I at the ray-batch size, row 0 = bottom, overwritten by
every pass, filled only while `overlays_enabled`):

* ``crossings`` (kind "heat"): how many triangles the ray crosses inside (tmin, tmax), all of them,
  not only the nearest (0 for pixels without a ray);
* ``hit_tri`` (kind "ids"): the nearest hit's triangle (-1 none), with ``tile_tris`` (its counts):
  the number of distinct triangles hit in the pixel's screen tile (level `tile_level(size)`).

Registered only by the tests: BACKENDS["fake"] = "tests.fake_backend:FakeBackend".
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.interface import BackendInfo, OverlaySpec, param
from viewer.errors import RtwalkError
from viewer.gl.textures import int_texture
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.screen_tiles import max_tile_level, tile_index

PAIRS_PER_BLOCK = 1 << 18  # (ray, triangle) pairs live at once: ~20 MB of float64 temporaries


@dataclass
class FakeParams:
    tile_level: int = param(2, "screen-tile level of the id view's outlines and per-tile counts (capped by the size)")
    max_triangles: int = param(4096, "refuse bigger scenes: the brute force is O(rays x triangles)")

    def validate(self, source: str = "--backend-params") -> None:
        if not 0 <= self.tile_level <= 8:
            raise RtwalkError(f"{source}: tile_level must be in 0..8, got {self.tile_level}")
        if self.max_triangles < 1:
            raise RtwalkError(f"{source}: max_triangles must be >= 1, got {self.max_triangles}")


def intersect_all(verts: np.ndarray, o: np.ndarray, d: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> np.ndarray:
    """float64 (K, N) distance of every (ray, triangle) pair, +inf where the ray misses the
    triangle or the hit is outside (lo, hi). Watertight: vertices are taken relative to the
    origin and sheared so the ray is the +z axis; edge functions of a shared edge are exact
    negations of each other, so no ray passes between two triangles."""
    kz = np.argmax(np.abs(d), axis=1)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = d[np.arange(len(d)), kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)  # keep the winding
    perm = np.stack([kx, ky, kz], axis=1)  # (K, 3)
    dp = np.take_along_axis(d, perm, axis=1)
    op = np.take_along_axis(o, perm, axis=1)
    sx, sy, sz = dp[:, 0] / dp[:, 2], dp[:, 1] / dp[:, 2], 1.0 / dp[:, 2]
    rel = np.moveaxis(verts[:, :, perm], 2, 0) - op[:, None, None, :]  # (K, N, 3 vertices, 3 axes)
    x = rel[..., 0] - sx[:, None, None] * rel[..., 2]
    y = rel[..., 1] - sy[:, None, None] * rel[..., 2]
    z = sz[:, None, None] * rel[..., 2]
    u = x[..., 2] * y[..., 1] - y[..., 2] * x[..., 1]
    v = x[..., 0] * y[..., 2] - y[..., 0] * x[..., 2]
    w = x[..., 1] * y[..., 0] - y[..., 1] * x[..., 0]
    inside = ((u >= 0) & (v >= 0) & (w >= 0)) | ((u <= 0) & (v <= 0) & (w <= 0))
    det = u + v + w
    inside &= det != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (u * z[..., 0] + v * z[..., 1] + w * z[..., 2]) / det
    inside &= (t > lo[:, None]) & (t < hi[:, None])
    return np.where(inside, t, np.inf)


class FakeBackend:
    info = BackendInfo(
        "fake", "test backend: every ray against every triangle in float64 NumPy",
        params=FakeParams,
        overlays=(OverlaySpec("fake_crossings", "heat", "crossings", "triangles crossed per ray"),
                  OverlaySpec("fake_tris", "ids", "hit_tri", "hit triangle; distinct triangles hit in the tile",
                              counts="tile_tris")),
        counters=("rays", "pair_tests", "hits"),
        phases=("fake:1-read", "fake:2-intersect", "fake:3-write"),
        device="cpu")

    def __init__(self, bc: BackendContext, params: FakeParams | None = None):
        self.bc = bc
        self.params = params or FakeParams()
        self.params.validate()
        tris = np.asarray(bc.scene.triangles, np.float64)
        if len(tris) > self.params.max_triangles:
            raise RtwalkError(f"backend 'fake' traces by brute force: {len(tris):,} triangles is over "
                              f"max_triangles={self.params.max_triangles}")
        self.verts = tris
        self.overlays_enabled = False
        self.frame = 0
        self.textures: dict[str, moderngl.Texture] = {}

    def begin_frame(self, frame_index: int) -> None:
        self.frame = int(frame_index)

    def scene_changed(self, bc: BackendContext) -> None:
        """Animated scenes: the brute-force copy of the vertices follows the moved triangles."""
        self.bc = bc
        self.verts = np.asarray(bc.scene.triangles, np.float64)

    def reset(self) -> None:
        pass

    def tile_level(self, size: tuple[int, int]) -> int:
        return min(self.params.tile_level, max_tile_level(size, 0.0))

    def _targets(self, size: tuple[int, int]) -> dict[str, moderngl.Texture]:
        if not self.textures or tuple(self.textures["crossings"].size) != tuple(size):
            self.release()
            self.textures = {name: int_texture(self.bc.ctx, size) for name in ("crossings", "hit_tri", "tile_tris")}
        return self.textures

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        prof = self.bc.profiler
        n_tris = len(self.verts)
        with prof.phase("fake:1-read"):
            r = rays.read()
            active = np.flatnonzero(r.active & np.isfinite(r.origins).all(1) & np.isfinite(r.directions).all(1)
                                    & np.isfinite(r.tmin) & np.isfinite(r.tmax))
        with prof.phase("fake:2-intersect"):
            t = np.full(len(r.tmin), np.inf)
            tri = np.full(len(r.tmin), -1, np.int64)
            crossings = np.zeros(len(r.tmin), np.int64)
            step = max(1, PAIRS_PER_BLOCK // max(n_tris, 1))
            for s in range(0, len(active), step):
                idx = active[s:s + step]
                tt = intersect_all(self.verts, r.origins[idx].astype(np.float64),
                                   r.directions[idx].astype(np.float64), r.tmin[idx].astype(np.float64),
                                   r.tmax[idx].astype(np.float64))
                best = np.argmin(tt, axis=1)  # ties: the smallest triangle id
                bt = tt[np.arange(len(idx)), best]
                hit = bt < np.inf
                t[idx[hit]] = bt[hit]
                tri[idx[hit]] = best[hit]
                crossings[idx] = (tt < np.inf).sum(axis=1)
        with prof.phase("fake:3-write"):
            t32 = t.astype(np.float32)
            tri32 = tri.astype(np.int32)
            hits.write(t32, tri32)
            tex = self._targets(tuple(rays.size))
            if self.overlays_enabled:
                self._write_overlays(tex, tuple(rays.size), crossings, tri32)
        stats = {"rays": len(active), "pair_tests": len(active) * n_tris, "hits": int((tri >= 0).sum())}
        return TraceResult(stats=stats, overlays=dict(tex))

    def _write_overlays(self, tex: dict[str, moderngl.Texture], size: tuple[int, int], crossings: np.ndarray,
                        tri: np.ndarray) -> None:
        tiles = tile_index(size, self.tile_level(size)).reshape(-1)
        hit = tri >= 0
        span = max(len(self.verts), 1)
        pairs = np.unique(tiles[hit] * span + tri[hit])
        per_tile = np.bincount(pairs // span, minlength=int(tiles.max()) + 1)
        tex["crossings"].write(crossings.astype(np.int32).tobytes())
        tex["hit_tri"].write(tri.astype(np.int32).tobytes())
        tex["tile_tris"].write(per_tile[tiles].astype(np.int32).tobytes())

    def release(self) -> None:
        for t in self.textures.values():
            t.release()
        self.textures = {}

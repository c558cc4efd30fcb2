"""Scene data passed between stages: flat float32 triangles, materials and lights.

Triangles are stored as one array so that every stage (BVH build, GPU upload, Embree
reference) sees exactly the same numbers; after the BVH build they are reordered into
leaf order (`Scene.reordered`) and that order is the triangle id everywhere.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from viewer.camera import Camera


@dataclass
class Material:
    """Lambertian material; `mirror` materials get reflection rays instead."""

    name: str
    albedo: np.ndarray  # float32 (3,), linear RGB in [0, 1]
    mirror: bool = False


@dataclass
class PointLight:
    position: np.ndarray  # float32 (3,)
    intensity: np.ndarray  # float32 (3,), radiant intensity (RGB), falls off with 1/r^2


@dataclass
class RectLight:
    """One-sided rectangular area light: points corner + s*edge_u + t*edge_v, s,t in [0,1].

    It emits on the side of normalize(cross(edge_u, edge_v)).
    """

    corner: np.ndarray  # float32 (3,)
    edge_u: np.ndarray  # float32 (3,)
    edge_v: np.ndarray  # float32 (3,)
    radiance: np.ndarray  # float32 (3,), emitted radiance (RGB)

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return (n / np.linalg.norm(n)).astype(np.float32)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))

    @property
    def center(self) -> np.ndarray:
        return (self.corner + 0.5 * self.edge_u + 0.5 * self.edge_v).astype(np.float32)


_WIDE = 128  # vertices per row of the bounds reduction


def _vertex_bounds(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact float32 (min, max) (3,) over all vertices. Why not min(axis=0) on (3N, 3): a reduction
    over rows three floats wide runs about 30x slower than one over rows of 128 vertices, whose
    384 columns are then folded to 3 (1 s against 0.035 s for a 10 M-triangle city)."""
    flat = np.ascontiguousarray(triangles, np.float32).reshape(-1)
    rows = len(flat) // (3 * _WIDE)
    head, tail = flat[:rows * 3 * _WIDE].reshape(rows, 3 * _WIDE), flat[rows * 3 * _WIDE:].reshape(-1, 3)
    lo = np.minimum(head.min(axis=0, initial=np.inf).reshape(_WIDE, 3).min(axis=0),
                    tail.min(axis=0, initial=np.inf))
    hi = np.maximum(head.max(axis=0, initial=-np.inf).reshape(_WIDE, 3).max(axis=0),
                    tail.max(axis=0, initial=-np.inf))
    return lo.astype(np.float32), hi.astype(np.float32)


@dataclass
class Scene:
    """A triangle soup ready for the GPU.

    triangles:    float32 (N, 3, 3), [triangle, vertex, xyz], world space, finite, non-degenerate
    material_ids: int32 (N,), index into `materials`
    identity:     JSON-able dict naming the scene for recordings, e.g.
                  {"builtin": "city", "size": 100000, "seed": 1} or {"file": "sponza/sponza.obj"}
    animation:    None for a static scene; else f(scene_time) -> float32 (N, 3, 3) triangles in the
                  scene's ORIGINAL (construction) order. Triangle count and materials never change,
                  only positions; `order` maps current slots to original indices (set by reordered),
                  so `triangles_at(t)` is in the current (leaf) order.
    scene_time:   the time `triangles` were evaluated at (seconds); geometry_version counts changes
                  (backends key their per-geometry structures on it).
    """

    name: str
    triangles: np.ndarray
    material_ids: np.ndarray
    materials: list[Material]
    point_lights: list[PointLight] = field(default_factory=list)
    rect_lights: list[RectLight] = field(default_factory=list)
    default_camera: Camera | None = None
    identity: dict = field(default_factory=dict)
    sky_color: np.ndarray = field(default_factory=lambda: np.array([0.55, 0.65, 0.8], np.float32))
    notes: list[str] = field(default_factory=list)  # e.g. "dropped 53627 zero-area triangles"
    auto_lights: bool = False  # lights are the loader's guess: viewer.default_lights checks them by ray casts
    animation: Callable[[float], np.ndarray] | None = None
    order: np.ndarray | None = None  # int (N,): original index of each slot (None: identity)
    scene_time: float = 0.0
    geometry_version: int = 0

    @property
    def animated(self) -> bool:
        return self.animation is not None

    def triangles_at(self, scene_time: float) -> np.ndarray:
        """float32 (N, 3, 3) triangles at `scene_time`, in this scene's current slot order."""
        if self.animation is None:
            return self.triangles
        tris = np.asarray(self.animation(float(scene_time)), np.float32)
        return np.ascontiguousarray(tris if self.order is None else tris[self.order])

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    _bounds: tuple = field(default=(None, None, None), init=False, repr=False, compare=False)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) float32 (3,) over all vertices; cached per triangle array (the renderer asks
        every frame, and a 2M-triangle reduction costs tens of ms)."""
        tris, lo, hi = self._bounds
        if tris is not self.triangles:  # the same array object (a reassigned array is recomputed)
            lo, hi = _vertex_bounds(self.triangles)
            self._bounds = (self.triangles, lo, hi)
        return lo.copy(), hi.copy()

    _gpu_tris: tuple = field(default=(None, None, None), init=False, repr=False, compare=False)

    def gpu_triangles(self) -> np.ndarray:
        """GPU_TRI_DTYPE array of the triangles (viewer.accel.bvh.gpu_triangles), cached per
        triangle and material arrays like `bounds`: the GL scene and the CL frame both upload it
        (at 10 M triangles each packing took 0.8-1 s of the first frame). Read-only for callers."""
        tris, mats, packed = self._gpu_tris
        if tris is not self.triangles or mats is not self.material_ids:
            from viewer.accel.bvh import gpu_triangles

            packed = gpu_triangles(self.triangles, self.material_ids)
            self._gpu_tris = (self.triangles, self.material_ids, packed)
        return packed

    @property
    def diagonal(self) -> float:
        lo, hi = self.bounds
        return float(np.linalg.norm(hi.astype(np.float64) - lo))

    def albedo_table(self) -> np.ndarray:
        """float32 (M, 4): albedo rgb + mirror flag, the GPU material table."""
        table = np.zeros((max(1, len(self.materials)), 4), np.float32)
        for i, m in enumerate(self.materials):
            table[i, :3] = m.albedo
            table[i, 3] = 1.0 if m.mirror else 0.0
        return table

    def reordered(self, order: np.ndarray) -> Scene:
        """The same scene with triangles permuted: new triangle i is old triangle order[i]."""
        composed = order if self.order is None else self.order[order]
        # np.take, not fancy indexing: faster on (N, 3, 3) rows (city 10 M in its BVH's order: 1.05
        # -> 0.95 s cold, 0.40 -> 0.24 s warm; a random order 2.3-3.4 -> 0.6-1.1 s); contiguous results
        return replace(self, triangles=np.take(np.ascontiguousarray(self.triangles), order, axis=0),
                       material_ids=np.take(np.ascontiguousarray(self.material_ids), order),
                       order=np.asarray(composed) if self.animation is not None else None)

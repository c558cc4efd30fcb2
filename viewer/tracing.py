"""Trace arbitrary ray arrays with a GL backend: the entry point for tests and tools.

Convention shared with viewer.reference: t is in units of |direction| (hit = o + t*d), +inf on a
miss; tri is the index into the *input* triangle array, -1 on a miss; only tmin < t < tmax hit;
rays with tmax <= tmin (or non-finite data) are inactive and miss. Triangles no ray can hit (zero
area, decided exactly, or a non-finite vertex: viewer.degenerate) are left out of what the backend
builds, as the scene loader leaves them out: float32 edge functions need not cancel on them.
"""

from __future__ import annotations

import hashlib
import os

import moderngl
import numpy as np

from viewer.accel.builders import build_scene_bvh
from viewer.accel.bvh import BVH
from viewer.backends import DEFAULT_BACKEND, create_backend
from viewer.backends.base import BackendContext
from viewer.degenerate import unhittable
from viewer.effects import RayType
from viewer.gl import io as glio
from viewer.gl.context import shared_context
from viewer.gl.programs import ProgramCache
from viewer.gl.scene import FETCH_ENV, GpuScene
from viewer.profiler import GpuProfiler
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.scene import Material, Scene

_CACHE: dict[str, tuple[Scene, BVH, GpuScene, ProgramCache]] = {}
ROW = 1024  # rays are laid out in a texture ROW wide



def _prepared(ctx: moderngl.Context, triangles: np.ndarray):
    # (the fetch path is chosen when the scene is uploaded: RTWALK_SCENE_FETCH is part of the key)
    key = hashlib.sha1(triangles.tobytes()).hexdigest() + os.environ.get(FETCH_ENV, "")
    hit = _CACHE.get(key)
    if hit is None:
        if len(_CACHE) > 8:
            for _, _, g, _ in _CACHE.values():
                g.release()
            _CACHE.clear()
        bvh = build_scene_bvh(triangles)
        scene = Scene("rays", triangles, np.zeros(len(triangles), np.int32),
                      [Material("grey", np.full(3, 0.7, np.float32))]).reordered(bvh.tri_order)
        hit = (scene, bvh, GpuScene.upload(ctx, scene, bvh), ProgramCache(ctx))
        _CACHE[key] = hit
    return hit


def trace_rays(triangles: np.ndarray, origins, directions, tmin, tmax, any_hit: bool = False,
               backend: str = DEFAULT_BACKEND) -> tuple[np.ndarray, np.ndarray]:
    tris = np.ascontiguousarray(triangles, np.float32).reshape(-1, 3, 3)
    ids = np.flatnonzero(~unhittable(tris)).astype(np.int32)  # built triangle -> input index
    tris = np.ascontiguousarray(tris[ids])
    o = np.asarray(origins, np.float32).reshape(-1, 3)
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    lo = np.asarray(tmin, np.float32).reshape(-1)
    hi = np.asarray(tmax, np.float32).reshape(-1)
    n = len(o)
    t_out = np.full(n, np.inf, np.float32)
    id_out = np.full(n, -1, np.int32)
    if n == 0 or len(tris) == 0:
        return t_out, id_out
    finite = np.isfinite(o).all(1) & np.isfinite(d).all(1) & np.isfinite(lo) & ~np.isnan(hi) & (d != 0).any(1)
    active = finite & (hi > lo)
    ctx = shared_context()
    scene, bvh, gpu_scene, programs = _prepared(ctx, tris)
    width = min(n, ROW)
    height = -(-n // width)
    size = (width, height)
    pad = width * height
    org = np.zeros((pad, 4), np.float32)
    dirs = np.zeros((pad, 4), np.float32)
    dirs[:, 2] = 1.0
    dirs[:, 3] = -1.0
    org[:n, :3] = np.where(finite[:, None], o, 0)
    org[:n, 3] = np.where(active, lo, 0)
    dirs[:n, :3] = np.where(finite[:, None], d, 1)
    dirs[:n, 3] = np.where(active, np.minimum(hi, np.float32(3.4e38)), -1.0)
    rays = RayBatch(ctx, size)
    hits = HitBuffer(ctx, size)
    try:
        glio.write(rays.origin, org.tobytes())
        glio.write(rays.direction, dirs.tobytes())
        bc = BackendContext(ctx, programs, GpuProfiler(ctx, enabled=False), gpu_scene, scene, bvh)
        be = create_backend(backend, bc)
        be.begin_frame(0)
        be.trace(rays, PassInfo(RayType.SHADOW if any_hit else RayType.PRIMARY), hits)
        be.release()
        t, slot = hits.read()
    finally:
        rays.release()
        hits.release()
    t, slot = t[:n], slot[:n]
    hit = (slot >= 0) & active
    t_out[hit] = t[hit]
    id_out[hit] = ids[bvh.tri_order[slot[hit]]]
    return t_out, id_out

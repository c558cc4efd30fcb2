"""Which BVH builder a scene load uses: the CPU binned SAH build (viewer.accel.bvh, the quality
reference) or the OpenCL build (viewer.accel.bvh_device, Morton + PLOC).

Per-frame rebuilds (the dynamic-scene studies) use `per_frame_builder()`.

Choice on scene load: `--bvh-builder` (scene commands), else the environment variable RTWALK_BVH_BUILDER, else
"auto": the device build for scenes of at least AUTO_DEVICE_MIN triangles when an OpenCL device
is there (it is many times faster and its SAH cost stays within about 10% of the SAH build on the
study scenes, see docs/bvh-device.md), the SAH build below (where it takes well under a second).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from viewer.accel.bvh import BVH, build_bvh
from viewer.errors import RtwalkError

BUILDERS = ("auto", "sah", "device")
ENV = "RTWALK_BVH_BUILDER"
AUTO_DEVICE_MIN = 500_000


def check_builder(name: str | None, source: str = "--bvh-builder") -> str | None:
    """The name if it is a builder (or None); RtwalkError otherwise."""
    if name is None or name == "":
        return None
    if name not in BUILDERS:
        raise RtwalkError(f"{source}: unknown BVH builder {name!r} (choose from {', '.join(BUILDERS)})")
    return name


def resolve_builder(name: str | None, n_triangles: int) -> str:
    """"sah" or "device" for a scene of n_triangles (see the module docstring)."""
    name = check_builder(name) or check_builder(os.environ.get(ENV), ENV) or "auto"
    if name == "auto":
        if n_triangles < AUTO_DEVICE_MIN:
            return "sah"
        from viewer.cl import cl_available

        return "device" if cl_available() is None else "sah"
    if name == "device":
        from viewer.cl import cl_available

        reason = cl_available()
        if reason is not None:
            raise RtwalkError(f"the device BVH builder needs an OpenCL device: {reason}")
    return name


def per_frame_builder() -> str:
    """The builder for per-frame rebuilds of animated scenes: the fastest one whose trees keep the
    trace within 10% of the SAH build's, i.e. the device build when OpenCL is there (SAH cost
    0.80-1.07x the SAH build's on the study scenes, docs/bvh-device.md), else the SAH build.
    RTWALK_BVH_BUILDER=sah|device overrides it."""
    env = check_builder(os.environ.get(ENV), ENV)
    if env in ("sah", "device"):
        return resolve_builder(env, 0)
    from viewer.cl import cl_available

    return "device" if cl_available() is None else "sah"


def build_scene_bvh(triangles: np.ndarray, builder: str | None = None,
                    progress: Callable[[int, int], None] | None = None) -> BVH:
    """The scene's BVH with the chosen builder (progress: SAH build only, once per level)."""
    if resolve_builder(builder, len(triangles)) == "device":
        from viewer.accel.bvh_device import build_bvh_device

        return build_bvh_device(triangles)
    return build_bvh(triangles, progress=progress)

"""Setting the camera/light uniforms shared by several shaders (only those a program uses)."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.camera import Camera
from viewer.scene import Scene

MAX_POINT_LIGHTS = 8
MAX_RECT_LIGHTS = 4


def set_uniform(prog: moderngl.Program, name: str, value) -> None:
    if name in prog:
        prog[name].value = value


def _vec3(v) -> tuple[float, float, float]:
    return tuple(float(x) for x in np.asarray(v, np.float64)[:3])


def camera_uniforms(camera: Camera, size: tuple[int, int]) -> dict:
    r = camera.rotation
    return {"camPos": _vec3(camera.position), "camRight": _vec3(r[:, 0]), "camUp": _vec3(r[:, 1]),
            "camForward": _vec3(-r[:, 2]), "tanHalfFov": float(np.tan(np.radians(camera.fov_y) / 2)),
            "viewport": (float(size[0]), float(size[1]))}


def light_uniforms(scene: Scene, ambient: float) -> dict:
    pls = scene.point_lights[:MAX_POINT_LIGHTS]
    rls = scene.rect_lights[:MAX_RECT_LIGHTS]

    def pad(items, n):
        items = [_vec3(x) for x in items]
        return items + [(0.0, 0.0, 0.0)] * (n - len(items))

    return {
        "numPointLights": len(pls),
        "pointPos": pad([p.position for p in pls], MAX_POINT_LIGHTS),
        "pointIntensity": pad([p.intensity for p in pls], MAX_POINT_LIGHTS),
        "numRectLights": len(rls),
        "rectCorner": pad([r.corner for r in rls], MAX_RECT_LIGHTS),
        "rectU": pad([r.edge_u for r in rls], MAX_RECT_LIGHTS),
        "rectV": pad([r.edge_v for r in rls], MAX_RECT_LIGHTS),
        "rectRadiance": pad([r.radiance for r in rls], MAX_RECT_LIGHTS),
        "skyColor": _vec3(scene.sky_color),
        "ambient": float(ambient),
        "lightRadius": float(0.01 * scene.diagonal),
    }


def apply(prog: moderngl.Program, values: dict) -> None:
    for k, v in values.items():
        set_uniform(prog, k, v)

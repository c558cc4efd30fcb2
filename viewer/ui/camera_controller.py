"""Flying walkthrough camera driven by keys and mouse deltas. Pure Python: no window, no GL.

Conventions follow `viewer.camera`: yaw turns about world +Y (0 = looking down -Z, positive =
turning left), pitch about the camera's X (positive = looking up), clamped to +-89 degrees.
Movement is linear in dt (no smoothing), so the path does not depend on the frame rate.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from viewer.camera import Camera, yaw_pitch_to_quat

#: Base speed as a fraction of the scene diagonal per second (street level in the city: ~12 m/s).
SPEED_FRACTION = 0.02
#: Speed factor per mouse-wheel notch.
WHEEL_FACTOR = 1.25
#: Shift multiplies the speed by this.
FAST_FACTOR = 5.0
#: Radians of yaw/pitch per pixel of mouse drag.
LOOK_SENSITIVITY = 0.004
PITCH_LIMIT = math.radians(89.0)
#: Wheel scaling is limited to WHEEL_FACTOR**(+-SCALE_NOTCHES).
SCALE_NOTCHES = 30

# Movement actions: name -> (axis, sign); axes are 'forward', 'right' (camera) and 'up' (world Y).
ACTIONS = {
    "forward": ("forward", 1.0), "back": ("forward", -1.0),
    "right": ("right", 1.0), "left": ("right", -1.0),
    "up": ("up", 1.0), "down": ("up", -1.0),
}


def yaw_pitch_of(camera: Camera) -> tuple[float, float]:
    """Yaw and pitch (radians) that reproduce the camera's viewing direction (roll is dropped)."""
    f = camera.forward
    pitch = math.asin(float(np.clip(f[1], -1.0, 1.0)))
    if math.hypot(f[0], f[2]) < 1e-12:  # looking straight up/down: take the yaw from the up vector
        u = camera.up * (-1.0 if f[1] > 0 else 1.0)
        yaw = math.atan2(-u[0], -u[2])
    else:
        yaw = math.atan2(-f[0], -f[2])
    return yaw, pitch


@dataclass
class FlyCamera:
    position: np.ndarray
    yaw: float = 0.0
    pitch: float = 0.0
    fov_y: float = 60.0
    base_speed: float = 1.0  # scene units per second at speed_scale 1, without shift
    speed_scale: float = 1.0
    sensitivity: float = LOOK_SENSITIVITY

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, np.float64).reshape(3).copy()
        self.pitch = float(np.clip(self.pitch, -PITCH_LIMIT, PITCH_LIMIT))

    @staticmethod
    def from_camera(camera: Camera, scene_diagonal: float, speed_fraction: float = SPEED_FRACTION) -> FlyCamera:
        fc = FlyCamera(np.asarray(camera.position, np.float64), fov_y=float(camera.fov_y),
                       base_speed=max(float(scene_diagonal), 1e-6) * speed_fraction)
        fc.set_camera(camera)
        return fc

    # -- state -----------------------------------------------------------------------------------
    def set_camera(self, camera: Camera) -> None:
        """Take over a pose (e.g. where a playback stopped); the speed settings are kept."""
        self.position = np.asarray(camera.position, np.float64).reshape(3).copy()
        yaw, pitch = yaw_pitch_of(camera)
        self.yaw = yaw
        self.pitch = float(np.clip(pitch, -PITCH_LIMIT, PITCH_LIMIT))
        self.fov_y = float(camera.fov_y)

    @property
    def orientation(self) -> np.ndarray:
        return yaw_pitch_to_quat(self.yaw, self.pitch)

    def camera(self) -> Camera:
        return Camera(self.position.copy(), self.orientation, self.fov_y)

    @property
    def speed(self) -> float:
        """Current speed without shift, scene units per second."""
        return self.base_speed * self.speed_scale

    def axes(self) -> dict[str, np.ndarray]:
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        cy, sy = math.cos(self.yaw), math.sin(self.yaw)
        return {"forward": np.array([-cp * sy, sp, -cp * cy]),
                "right": np.array([cy, 0.0, -sy]),
                "up": np.array([0.0, 1.0, 0.0])}

    # -- input -----------------------------------------------------------------------------------
    def look(self, dx: float, dy: float) -> None:
        """Mouse drag by (dx, dy) pixels, y downwards: right turns right, down looks down."""
        self.yaw = math.remainder(self.yaw - dx * self.sensitivity, 2 * math.pi)
        self.pitch = float(np.clip(self.pitch - dy * self.sensitivity, -PITCH_LIMIT, PITCH_LIMIT))

    def scroll(self, notches: float) -> None:
        """Mouse wheel: each notch up multiplies the speed by WHEEL_FACTOR (down divides)."""
        lo, hi = WHEEL_FACTOR ** -SCALE_NOTCHES, WHEEL_FACTOR ** SCALE_NOTCHES
        self.speed_scale = float(np.clip(self.speed_scale * WHEEL_FACTOR ** float(notches), lo, hi))

    def velocity(self, actions: Iterable[str], fast: bool = False) -> np.ndarray:
        axes = self.axes()
        v = np.zeros(3)
        for a in set(actions):
            if a in ACTIONS:
                axis, sign = ACTIONS[a]
                v += sign * axes[axis]
        n = float(np.linalg.norm(v))
        if n < 1e-12:
            return np.zeros(3)
        # diagonal moves are no faster than straight ones
        return v / n * self.speed * (FAST_FACTOR if fast else 1.0)

    def update(self, dt: float, actions: Iterable[str], fast: bool = False) -> None:
        """Advance by dt seconds with the given movement actions held (see ACTIONS)."""
        if not dt > 0 or not math.isfinite(dt):
            return
        self.position = self.position + self.velocity(actions, fast) * float(dt)

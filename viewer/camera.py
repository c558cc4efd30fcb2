"""Pinhole camera. Convention (OpenGL): the camera looks down its local -Z, +Y is up.

Pixel (x, y) has its centre at ((x + 0.5) / W, (y + 0.5) / H) in [0,1]^2 with y = 0 at the
*bottom* row (GL texture order); images are flipped only when written to PNG. The rasterizer,
the ray generator and the reference tracers all use this same mapping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n == 0.0:
        raise ValueError("quaternion has zero or non-finite length")
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3x3, float64) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quat_normalize(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method, stable)."""
    m = np.asarray(m, np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return quat_normalize(q if q[0] >= 0 else -q)


def yaw_pitch_to_quat(yaw: float, pitch: float) -> np.ndarray:
    """Orientation from yaw (about +Y, radians, 0 = looking down -Z) and pitch (about local X)."""
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    q_yaw = np.array([cy, 0.0, sy, 0.0])
    q_pitch = np.array([cp, sp, 0.0, 0.0])
    return quat_normalize(quat_mul(q_yaw, q_pitch))


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


@dataclass
class Camera:
    position: np.ndarray  # float64 (3,)
    orientation: np.ndarray  # float64 (4,), unit quaternion (w, x, y, z), camera-to-world
    fov_y: float = 60.0  # vertical field of view, degrees

    @staticmethod
    def look_at(eye, target, up=(0.0, 1.0, 0.0), fov_y: float = 60.0) -> Camera:
        eye = np.asarray(eye, np.float64)
        fwd = np.asarray(target, np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, np.float64))
        if np.linalg.norm(right) < 1e-9:  # looking straight up/down: pick any right vector
            right = np.cross(fwd, [1.0, 0.0, 0.0]) if abs(fwd[0]) < 0.9 else np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        m = np.stack([right, true_up, -fwd], axis=1)
        return Camera(eye, matrix_to_quat(m), float(fov_y))

    @property
    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.orientation)

    @property
    def forward(self) -> np.ndarray:
        return -self.rotation[:, 2]

    @property
    def right(self) -> np.ndarray:
        return self.rotation[:, 0]

    @property
    def up(self) -> np.ndarray:
        return self.rotation[:, 1]

    def view_matrix(self) -> np.ndarray:
        """World-to-camera 4x4 (float64, column vectors: p_cam = V @ p_world)."""
        r = self.rotation
        v = np.eye(4)
        v[:3, :3] = r.T
        v[:3, 3] = -r.T @ np.asarray(self.position, np.float64)
        return v

    def projection_matrix(self, aspect: float, near: float, far: float) -> np.ndarray:
        """Standard OpenGL perspective projection (float64, column vectors)."""
        f = 1.0 / np.tan(np.radians(self.fov_y) / 2)
        p = np.zeros((4, 4))
        p[0, 0] = f / aspect
        p[1, 1] = f
        p[2, 2] = (far + near) / (near - far)
        p[2, 3] = 2 * far * near / (near - far)
        p[3, 2] = -1.0
        return p

    def primary_rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions through pixel centres, float64 (H, W, 3), row 0 = bottom."""
        tan_half = np.tan(np.radians(self.fov_y) / 2)
        aspect = width / height
        xs = ((np.arange(width) + 0.5) / width * 2 - 1) * tan_half * aspect
        ys = ((np.arange(height) + 0.5) / height * 2 - 1) * tan_half
        gx, gy = np.meshgrid(xs, ys)
        d_cam = np.stack([gx, gy, -np.ones_like(gx)], axis=-1)
        d = d_cam @ self.rotation.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(np.asarray(self.position, np.float64), d.shape).copy()
        return o, d

    def to_dict(self) -> dict:
        return {"position": [float(v) for v in self.position],
                "orientation": [float(v) for v in self.orientation], "fov_y": float(self.fov_y)}

"""Regenerates the shipped camera paths (run from the repo root: python recordings/make_paths.py).

Paths are look-at keyframes designed from the scene layouts: the city's street grid
(`viewer.procedural.city_layout`) and the bounds/floor heights of the shared benchmark scenes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from viewer.camera import Camera
from viewer.procedural import city_layout
from viewer.recording import Keyframe, Recording, save_recording

HERE = Path(__file__).resolve().parent
RES = (1280, 720)


def path(scene: dict, points: list[tuple], seconds: float, fov: float = 60.0) -> Recording:
    """points: (eye, target) pairs, evenly spaced in time over `seconds`."""
    times = np.linspace(0.0, seconds, len(points))
    keys = [Keyframe.from_camera(float(t), Camera.look_at(e, g, fov_y=fov))
            for t, (e, g) in zip(times, points, strict=True)]
    return Recording(scene, RES, 30.0, keys)


def city_near() -> Recording:
    lay = city_layout(150_000, 1)
    p = lay["pitch"]
    y = 1.7
    # walk north down the street x = 0, turn east at the crossing z = p, walk along it
    pts = [((0.0, y, 150.0), (0.0, y, 100.0)), ((0.0, y, 125.0), (0.5, y, 75.0)),
           ((0.0, y, 100.0), (1.0, y, 50.0)), ((0.0, y, 75.0), (0.5, y, 25.0)),
           ((0.0, y, 55.0), (12.0, y, 20.0)), ((2.0, y, p), (50.0, y, p)),
           ((25.0, y, p), (75.0, y, p + 1.0)), ((50.0, y, p), (100.0, y, p + 2.0)),
           ((75.0, y, p), (125.0, y, p + 6.0)), ((100.0, y, p), (150.0, y, p + 10.0))]
    return path({"builtin": "city", "size": 150_000, "seed": 1}, pts, 12.0)


def city_far() -> Recording:
    lay = city_layout(150_000, 1)
    h = lay["half_extent"]
    height = 1.5 * h
    pts = []
    for a in np.linspace(0.0, 1.5 * np.pi, 10):
        eye = (1.3 * h * np.cos(a), height, 1.3 * h * np.sin(a))
        pts.append((eye, (0.2 * h * np.cos(a + 1.0), 0.0, 0.2 * h * np.sin(a + 1.0))))
    return path({"builtin": "city", "size": 150_000, "seed": 1}, pts, 12.0)


def sponza_walk() -> Recording:
    y = 1.8  # floor at y ~ -0.08
    pts = [((-13.0, y, 0.0), (-3.0, y + 0.5, 0.0)), ((-9.0, y, 0.3), (1.0, y + 1.0, -1.0)),
           ((-5.0, y, 0.6), (5.0, y + 2.0, 0.0)), ((-1.0, y, 0.3), (9.0, y + 3.0, 2.0)),
           ((3.0, y, -0.3), (10.0, y + 1.0, -4.0)), ((7.0, y, -0.6), (12.0, y, 2.0)),
           ((10.0, y, 0.0), (4.0, y + 2.0, 4.0)), ((8.0, y, 1.0), (-2.0, y + 4.0, 0.0)),
           ((4.0, y + 1.0, 0.5), (-8.0, y + 6.0, 0.0))]
    return path({"file": "sponza-dabrovic/sponza.obj"}, pts, 12.0)


def sibenik_walk() -> Recording:
    y = -13.5  # nave floor at y = -15.3 (chancel steps start at x ~ 2.5, so the walk stops at x = 0.5)
    pts = [((-18.0, y, 0.0), (0.0, y + 1.0, 0.0)), ((-16.0, y, 0.3), (2.0, y + 2.0, 0.5)),
           ((-14.0, y, 0.6), (0.0, y + 6.0, -3.0)), ((-12.0, y, 0.7), (-6.0, y + 10.0, 0.0)),
           ((-10.0, y, 0.5), (2.0, y + 5.0, 2.0)), ((-8.0, y, 0.0), (-4.0, y + 1.0, 6.0)),
           ((-6.0, y, -0.5), (6.0, y + 2.0, -2.0)), ((-4.0, y, -0.6), (10.0, y + 3.0, 0.0)),
           ((-2.0, y, -0.3), (10.0, y + 2.5, 0.0)), ((-0.2, y, 0.0), (0.5, y + 2.0, -8.0)),
           ((0.5, y, 0.3), (-12.0, y + 3.0, 0.0))]
    return path({"file": "sibenik/sibenik.obj"}, pts, 12.5)


def conference_walk() -> Recording:
    y = 360.0  # floor ~ -1.6, table top ~180-210, chair backs < 230, ceiling ~640
    c = np.array([490.0, 0.0, -135.0])  # table + chairs span x -40..1020, z -390..120
    pts = []
    for a in np.linspace(0.1 * np.pi, 1.75 * np.pi, 10):
        eye = np.array([c[0] + 780.0 * np.cos(a), y, c[2] + 420.0 * np.sin(a)])
        tangent = np.array([-780.0 * np.sin(a), 0.0, 420.0 * np.cos(a)])
        pts.append((tuple(eye), tuple(c + (0, 120.0, 0) + 0.35 * tangent)))
    return path({"file": "conference/conference.ply"}, pts, 12.0)


def room_anim_walk() -> Recording:
    """A slow walk through the animated room (`room-anim`) watching the objects fall, with scene
    time: the scene clock runs with the camera to 3 s, slows down (4.25 at 4.5 s, 5.0 at 6 s: a cube
    bouncing in slow motion), then runs with the camera again (8.0 at 9 s). The camera stays inside
    the room (x, z in [-5, 5], y in [0, 5])."""
    y = 1.9
    pts = [((0.0, y, 4.4), (0.0, 1.2, -2.0)), ((1.2, y, 4.0), (2.0, 0.8, 1.0)),
           ((2.4, y + 0.3, 3.2), (0.4, 0.6, -1.4)), ((2.6, y + 0.5, 1.6), (-3.0, 1.0, 2.5)),
           ((1.0, y + 0.6, 0.6), (-3.3, 0.6, -0.2)), ((-0.8, y + 0.4, 1.2), (0.0, 3.4, -2.0)),
           ((-2.0, y, 2.6), (2.7, 0.5, 2.9))]
    rec = path({"builtin": "room-anim", "size": 1, "seed": 1}, pts, 9.0)
    for k in rec.keyframes:
        t = k.time
        k.scene_time = t if t <= 4.0 else (4.0 + 0.5 * (t - 4.0) if t <= 6.0 else 5.0 + (t - 6.0))
    return rec


def main() -> None:
    for name, make in [("city-near", city_near), ("city-far", city_far), ("sponza-walk", sponza_walk),
                       ("sibenik-walk", sibenik_walk), ("conference-walk", conference_walk),
                       ("room-anim-walk", room_anim_walk)]:
        out = save_recording(make(), HERE / f"{name}.json")
        print(out)


if __name__ == "__main__":
    main()

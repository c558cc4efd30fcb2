"""Default lights for a scene file without any: placed by ray casts once the BVH exists.

The loader's guess (viewer.scene_io.default_lights: under the ceiling of the largest vertical gap
above the centre) suits interiors, but lands inside closed objects (a sphere, a box, a watertight
scan). Here candidates (the guess, key-light positions around the default camera, points in the air
between the camera and what it sees) are kept only with a small clearance from every surface, and
scored by the share of the camera's visible surface samples they light (facing normal towards the
light, shadow ray unoccluded): a light inside a solid lights none of them. The guess is kept
unless a candidate lights clearly more. Rays go through viewer.accel.raycast (CPU, NumPy): a few
thousand per scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from viewer.accel.bvh import BVH
from viewer.accel.raycast import cast_rays
from viewer.scene import PointLight, RectLight, Scene

GRID = (32, 18)  # camera rays for the visible samples
KEEP_GUESS = 0.85  # the loader's guess stays if it lights this share of the best candidate's samples
PATH_GRID = (16, 9)  # camera rays per camera of a walk (place_set)
MAX_SET_LIGHTS = 4  # lights for a walk: each costs one shadow pass (the shade pass takes up to 8)
MAX_RECT = 4  # the rect lights the shaders take (lighting.glsl MAX_RECT_LIGHTS)
SET_TARGET = 0.6  # a camera's lit pixel share beyond which more light on it scores nothing more
SET_MIN_GAIN = 0.01  # per camera: a light adding less than this to the capped score is not added
PATH_CAMERA_STEP = 30  # frames between the recording cameras lights are chosen for
SUBSET = 384  # place_set stage 1: samples every candidate is tried on
SHORTLIST = 24  # place_set stage 2: candidates tried on every sample (greedy set choice)


@dataclass
class Placement:
    position: np.ndarray  # float64 (3,)
    lit: float  # share of the visible samples lit
    clearance: float  # distance to the nearest surface among the free-space rays
    target: np.ndarray  # float64 (3,), mean of the lit samples (where a rect light faces)
    reach: float  # median distance to the lit samples


def _directions26() -> np.ndarray:
    g = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                 np.float64)
    g += 1e-3 * np.array([0.31, 0.17, 0.23])  # off the axes: no ray along a mesh's edge lines
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _normals(tris: np.ndarray, ids: np.ndarray) -> np.ndarray:
    t = tris[ids].astype(np.float64)
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def visible_samples(scene: Scene, bvh: BVH, camera, grid: tuple[int, int] = GRID
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (K, 3), normals facing the camera (K, 3), ray directions (K, 3)) on a coarse grid."""
    o, d = camera.primary_rays(*grid)
    o = np.broadcast_to(np.asarray(o, np.float64).reshape(-1, 3), (grid[0] * grid[1], 3))
    d = np.asarray(d, np.float64).reshape(-1, 3)
    t, ids = cast_rays(bvh, scene.triangles, o, d)
    hit = ids >= 0
    p = o[hit] + t[hit, None] * d[hit]
    n = _normals(scene.triangles, ids[hit])
    n[np.einsum("ij,ij->i", n, d[hit]) > 0] *= -1
    return p, n, d[hit]


def clearance(scene: Scene, bvh: BVH, points: np.ndarray) -> np.ndarray:
    """Distance (P,) from each point to the nearest surface hit by 26 rays around it.

    Whether a point is in free space *on the camera's side* needs no winding convention (scans and
    some interiors wind outwards): a light that reaches a sample the camera sees, along an
    unoccluded segment from the sample's camera-facing side, is in the camera's free region; inside
    a closed solid it reaches none (lit_share is 0 there)."""
    dirs = _directions26()
    k = len(dirs)
    o = np.repeat(points, k, axis=0)
    d = np.tile(dirs, (len(points), 1))
    t, _ = cast_rays(bvh, scene.triangles, o, d)
    return t.reshape(-1, k).min(1)


def lit_share(scene: Scene, bvh: BVH, lights: np.ndarray, p: np.ndarray, n: np.ndarray,
              eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(share (L,), lit mask (L, K)) of the samples each light reaches (cos > 0, unoccluded)."""
    li = np.repeat(lights, len(p), axis=0)
    pi = np.tile(p, (len(lights), 1))
    ni = np.tile(n, (len(lights), 1))
    to_l = li - pi
    facing = np.einsum("ij,ij->i", to_l, ni) > 0
    lit = np.zeros(len(li), bool)
    sel = np.flatnonzero(facing)
    if len(sel):
        _, ids = cast_rays(bvh, scene.triangles, pi[sel] + eps * ni[sel], to_l[sel], 0.0, 1.0 - 1e-6,
                           any_hit=True)
        lit[sel] = ids < 0
    lit = lit.reshape(len(lights), len(p))
    return lit.mean(1), lit


def candidates(scene: Scene, camera, guess: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The guess, key-light spots around the camera, and points in the air towards what it sees."""
    eye = np.asarray(camera.position, np.float64)
    fwd, right, up = (np.asarray(v, np.float64) for v in (camera.forward, camera.right, camera.up))
    world_up = np.array([0.0, 1.0, 0.0])
    dist = float(np.median(np.linalg.norm(p - eye, axis=1))) if len(p) else 0.5 * scene.diagonal
    out = [guess]
    for s_up, s_right, s_fwd in ((0.8, 0.6, 0.2), (0.8, -0.6, 0.2), (1.2, 0.0, 0.0), (0.5, 0.3, 0.5),
                                 (0.5, -0.3, 0.5), (0.3, 0.0, 0.3), (1.5, 1.0, -0.3), (1.5, -1.0, -0.3)):
        out.append(eye + dist * (s_up * (0.5 * up + 0.5 * world_up) + s_right * right + s_fwd * fwd))
    if len(p):
        upper = p[(p - eye) @ up >= np.median((p - eye) @ up)]  # what the upper half of the image sees
        for f in (0.35, 0.65):
            for q in upper[:: max(len(upper) // 6, 1)][:6]:
                out.append(eye + f * (q - eye))
    return np.array(out, np.float64)


def place(scene: Scene, bvh: BVH, guess: np.ndarray) -> Placement | None:
    """The best free-space light position for the default camera, or None (nothing visible)."""
    camera = scene.default_camera
    p, n, _ = visible_samples(scene, bvh, camera)
    if len(p) == 0:
        return None
    diag = max(scene.diagonal, 1e-12)
    cand = candidates(scene, camera, np.asarray(guess, np.float64), p)
    nearest = clearance(scene, bvh, cand)
    free = nearest > 0.01 * diag  # not on a surface
    if not free.any():
        return None
    idx = np.flatnonzero(free)
    share, lit = lit_share(scene, bvh, cand[idx], p, n, 1e-4 * diag)
    best = int(np.argmax(share))
    if share[best] <= 0:
        return None
    if free[0] and share[0] >= KEEP_GUESS * share[best]:  # idx[0] == 0: the guess
        best = 0
    pos = cand[idx[best]]
    sel = lit[best] if lit[best].any() else np.ones(len(p), bool)
    dists = np.linalg.norm(p[sel] - pos, axis=1)
    return Placement(pos, float(share[best]), float(nearest[idx[best]]), p[sel].mean(0), float(np.median(dists)))


def place_set(scene: Scene, bvh: BVH, guess: np.ndarray, cameras: list,
              max_lights: int = MAX_SET_LIGHTS) -> list[Placement]:
    """A few free-space lights that together light what every camera of a walk sees.

    One light placed for the first camera leaves the rest of a walk (conference-walk: the far end
    of the room, the corridor) in the dark. Here every camera contributes its visible samples
    (PATH_GRID rays, misses included, so a camera's share is a share of its pixels) and its own
    candidates (tried on a sample subset first, the SHORTLIST best then on all samples: a few
    hundred thousand shadow rays in all); lights are then chosen greedily, each maximising sum over cameras of
    min(share of that camera's pixels lit by the chosen set, SET_TARGET): the cap makes a light that
    lifts a dark camera worth more than one that brightens a lit one. Stops at `max_lights` or when
    no light adds SET_MIN_GAIN."""
    diag = max(scene.diagonal, 1e-12)
    pts, nrm, owner, cand = [], [], [], [np.asarray(guess, np.float64)[None]]
    rays_per_camera = PATH_GRID[0] * PATH_GRID[1]
    for c, cam in enumerate(cameras):
        p, n, _ = visible_samples(scene, bvh, cam, PATH_GRID)
        pts.append(p)
        nrm.append(n)
        owner.append(np.full(len(p), c))
        if len(p):
            cand.append(candidates(scene, cam, np.asarray(guess, np.float64), p)[1:])
    p, n, owner = np.concatenate(pts), np.concatenate(nrm), np.concatenate(owner)
    if len(p) == 0:
        return []
    cand = np.concatenate(cand)
    nearest = clearance(scene, bvh, cand)
    idx = np.flatnonzero(nearest > 0.01 * diag)
    if len(idx) == 0:
        return []
    onehot = np.zeros((len(p), len(cameras)))
    onehot[np.arange(len(p)), owner] = 1.0 / rays_per_camera
    if len(idx) > SHORTLIST:  # stage 1: every candidate on a sample subset, keep the best few
        sub = np.random.default_rng(0).choice(len(p), min(SUBSET, len(p)), replace=False)
        _, lit_sub = lit_share(scene, bvh, cand[idx], p[sub], n[sub], 1e-4 * diag)
        rough = np.minimum(lit_sub.astype(np.float64) @ onehot[sub] * (len(p) / len(sub)), SET_TARGET).sum(1)
        idx = idx[np.argsort(-rough, kind="stable")[:SHORTLIST]]
    _, lit = lit_share(scene, bvh, cand[idx], p, n, 1e-4 * diag)
    per_cam = lit.astype(np.float64) @ onehot  # (L, C): share of each camera's pixels each light lights
    covered = np.zeros(len(p), bool)
    chosen: list[Placement] = []
    score = 0.0
    for _ in range(max_lights):
        gain_lit = (lit & ~covered).astype(np.float64) @ onehot + (covered.astype(np.float64) @ onehot)[None]
        scores = np.minimum(gain_lit, SET_TARGET).sum(1) + 1e-3 * per_cam.sum(1)
        best = int(np.argmax(scores))
        if scores[best] - score < SET_MIN_GAIN * len(cameras):
            break
        new = lit[best] & ~covered
        sel = new if new.any() else lit[best]
        pos = cand[idx[best]]
        dists = np.linalg.norm(p[sel] - pos, axis=1)
        chosen.append(Placement(pos, float(lit[best].mean()), float(nearest[idx[best]]), p[sel].mean(0),
                                float(np.median(dists))))
        covered |= lit[best]
        score = float(scores[best])
    return chosen


def _rect_light(scene: Scene, pl: Placement) -> RectLight:
    """A small rect light at the placement, facing its lit samples, power matched to the point light."""
    reach = max(pl.reach, 1e-9)
    w = pl.target - pl.position
    w /= max(np.linalg.norm(w), 1e-300)
    helper = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(w, helper)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)  # cross(u, v) = w: emits towards the samples
    lo, hi = scene.bounds
    side = min(0.1 * float(max(hi[0] - lo[0], hi[2] - lo[2], 1e-6)), pl.clearance)
    corner = pl.position - 0.5 * side * (u + v)
    return RectLight(corner.astype(np.float32), (side * u).astype(np.float32), (side * v).astype(np.float32),
                     np.full(3, reach ** 2 / (side * side), np.float32))


def _point_light(pl: Placement) -> PointLight:
    reach = max(pl.reach, 1e-9)
    return PointLight(pl.position.astype(np.float32), np.full(3, reach ** 2, np.float32))


def apply(scene: Scene, bvh: BVH, cameras: list | None = None) -> Placement | None:
    """Replace the loader's guessed lights (scene.auto_lights) by the ray-cast placement. The point
    light gives irradiance ~1 at the median distance of the samples it lights; the rect light (soft
    shadows) sits at the same spot, facing them, small enough to stay in free space.

    `cameras` (a recording's cameras along its path): a small set of lights (place_set) lighting
    what every one of them sees, each with its point and rect light; None: one light for the
    default camera. Returns the first placement (None: the guess kept)."""
    if not scene.auto_lights or not scene.point_lights:
        return None
    guess = np.asarray(scene.point_lights[0].position, np.float64)
    if cameras:
        placed = place_set(scene, bvh, guess, list(cameras))
        if placed:
            scene.point_lights = [_point_light(pl) for pl in placed]
            scene.rect_lights = [_rect_light(scene, pl) for pl in placed[:MAX_RECT]]
            return placed[0]
    pl = place(scene, bvh, guess)
    if pl is None or np.array_equal(pl.position, guess):
        return pl
    scene.point_lights = [_point_light(pl)]
    scene.rect_lights = [_rect_light(scene, pl)]
    return pl

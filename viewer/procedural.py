"""Procedural built-in scenes: ``city`` (a street grid in the spirit of the City-10/City-200 models
of the CHC+RT paper) and ``room`` (a closed Cornell-like room with a mirror).

Everything is deterministic for a seed (``np.random.default_rng(seed)``) and vectorised: all boxes
are generated as ``lo``/``hi`` arrays and turned into 12 triangles each by one gather.

City layout (scene units, Y up, ground plane at y = 0, city centred on x = z = 0)
---------------------------------------------------------------------------------
::

    pitch            P = 40          (block + street)
    street width     W = 10
    block side       B = P - W = 30  (a sidewalk plinth, y in [-0.5, 0.15], covers the whole block)
    blocks_per_side  n = max(1, round(sqrt(target_triangles) / 48))
    half_extent      H = n * P / 2   (the city's buildings lie inside |x|, |z| <= H - W/2)
    block (i, j), 0 <= i, j < n:  x in [-H + i*P + W/2, -H + (i+1)*P - W/2], z likewise with j
    street centre lines:          x = -H + k*P and z = -H + k*P for k = 0..n
                                  (k = 0 and k = n are the ring road around the city)
    ground:                       a grid of P x P cells covering |x|, |z| <= H + P

For the default city (150_000 triangles, seed 1): n = 8, H = 160, streets at x, z in
{-160, -120, ..., 120, 160}; see ``city_layout`` for the exact numbers (including max_height).
Streets are empty (nothing but the ground) between the plinths, 10 units wide, from the ground up.

Each block is split into k x k lots (k in {1, 2, 3}, random), one building per lot: a box (heights
mostly 8..40, towers 60..120 more likely near the centre), towers and some tall buildings with a
setback (a narrower upper box), rooftop boxes (antennas on towers), and facade relief: horizontal
ledge slabs wrapped around the building and vertical pilasters on all four facades. The relief
count is distributed over buildings (by facade area) so the total triangle count matches the target
to within a few dozen triangles (for targets >= ~2000).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from viewer.camera import Camera
from viewer.scene import Material, PointLight, RectLight, Scene

PITCH = 40.0
STREET_WIDTH = 10.0
BLOCK_SIZE = PITCH - STREET_WIDTH
SIDEWALK = 1.5  # border between the plinth edge and the lots
PLINTH_TOP = 0.15
PLINTH_BOTTOM = -0.5
BUILDING_BOTTOM = -0.2  # sunk into the plinth: no coplanar faces
LEDGE_DEPTH = 0.35
PILASTER_DEPTH = 0.2

# ----------------------------------------------------------------------------------------------
# boxes -> triangles


def _box_template() -> np.ndarray:
    """(12, 3) corner indices of a box with outward winding; corner i = (i&1, (i>>1)&1, (i>>2)&1)."""
    corners = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)
    tris = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            def idx(ub, uc, axis=axis, b=b, c=c, side=side):
                bits = [0, 0, 0]
                bits[axis], bits[b], bits[c] = side, ub, uc
                return bits[0] | (bits[1] << 1) | (bits[2] << 2)
            quad = [idx(0, 0), idx(1, 0), idx(1, 1), idx(0, 1)]
            for t in ([quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]):
                n = np.cross(corners[t[1]] - corners[t[0]], corners[t[2]] - corners[t[0]])
                want = 1.0 if side else -1.0
                if n[axis] * want < 0:
                    t = [t[0], t[2], t[1]]
                tris.append(t)
    return np.array(tris, np.int64)


BOX_TRIS = _box_template()
_CORNER_BITS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
#: column of (lo, hi) (M, 6) that each of a box's 108 triangle floats comes from
_BOX_COLUMNS = (_CORNER_BITS[BOX_TRIS].astype(np.int64) * 3 + np.arange(3)).reshape(-1)


def boxes_to_triangles(lo: np.ndarray, hi: np.ndarray, out: np.ndarray | None = None,
                       chunk: int = 200_000) -> np.ndarray:
    """Axis-aligned boxes (M, 3) lo/hi -> float32 (12*M, 3, 3) triangles, outward-facing."""
    lo = np.asarray(lo, np.float32)
    hi = np.asarray(hi, np.float32)
    m = lo.shape[0]
    if out is None:
        out = np.empty((12 * m, 3, 3), np.float32)
    # every output float is one column of (lo, hi): a column gather straight into `out` (twice as
    # fast as gathering corners, then triangles: 1.3 s -> 0.6 s for a 10 M-triangle city)
    view = out.reshape(m, 108)
    for s in range(0, m, chunk):
        e = min(m, s + chunk)
        np.take(np.concatenate([lo[s:e], hi[s:e]], axis=1), _BOX_COLUMNS, axis=1, out=view[s:e])
    return out


def _quad_grid(origin, u, v, nu: int, nv: int) -> np.ndarray:
    """A parallelogram origin + s*u + t*v tessellated into 2*nu*nv triangles, normal along u x v."""
    origin, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    s = np.arange(nu + 1) / nu
    t = np.arange(nv + 1) / nv
    p = origin + s[:, None, None] * u + t[None, :, None] * v  # (nu+1, nv+1, 3)
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]
    t1 = np.stack([a, b, c], axis=2).reshape(-1, 3, 3)
    t2 = np.stack([a, c, d], axis=2).reshape(-1, 3, 3)
    return np.concatenate([t1, t2]).astype(np.float32)


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For per-item counts: (item index repeated count times, local index 0..count-1)."""
    counts = np.asarray(counts, np.int64)
    owner = np.repeat(np.arange(counts.size), counts)
    starts = np.cumsum(counts) - counts
    local = np.arange(owner.size) - starts[owner]
    return owner, local


def _distribute(total: int, weights: np.ndarray) -> np.ndarray:
    """Integer counts summing to `total`, proportional to weights (largest remainder)."""
    if total <= 0 or weights.size == 0:
        return np.zeros(weights.size, np.int64)
    q = total * weights / weights.sum()
    c = np.floor(q).astype(np.int64)
    rem = int(total - c.sum())
    if rem > 0:
        order = np.argsort(-(q - c), kind="stable")
        c[order[:rem]] += 1
    return c


# ----------------------------------------------------------------------------------------------
# city

CITY_MATERIALS = [
    ("asphalt", (0.22, 0.22, 0.23), False),
    ("sidewalk", (0.55, 0.54, 0.52), False),
    ("facade_brick", (0.55, 0.30, 0.22), False),
    ("facade_sand", (0.76, 0.68, 0.52), False),
    ("facade_grey", (0.58, 0.58, 0.60), False),
    ("facade_white", (0.82, 0.80, 0.76), False),
    ("facade_blue", (0.36, 0.46, 0.60), False),
    ("trim", (0.85, 0.83, 0.80), False),
    ("roof", (0.30, 0.28, 0.27), False),
    ("glass_mirror", (0.90, 0.92, 0.95), True),
    ("mullion", (0.15, 0.16, 0.18), False),
]
M_ASPHALT, M_SIDEWALK, M_FACADE0, M_TRIM, M_ROOF, M_GLASS, M_MULLION = 0, 1, 2, 7, 8, 9, 10
N_FACADES = 5


def blocks_per_side(target_triangles: int) -> int:
    return max(1, int(round(math.sqrt(max(1, target_triangles)) / 48.0)))


@dataclass
class _Buildings:
    n: int
    half: float
    fp: np.ndarray  # (nb, 4) lower footprint x0, z0, x1, z1
    up: np.ndarray  # (nb, 4) upper footprint (== fp without setback)
    h: np.ndarray  # (nb,) total height
    h1: np.ndarray  # (nb,) height of the lower part (== h without setback)
    setback: np.ndarray  # (nb,) bool
    tower: np.ndarray  # (nb,) bool
    material: np.ndarray  # (nb,) body material
    roof_rand: np.ndarray  # (nb, 4, 5) uniform randoms for up to 4 rooftop boxes


def _city_buildings(target_triangles: int, seed: int) -> _Buildings:
    rng = np.random.default_rng(seed)
    n = blocks_per_side(target_triangles)
    half = n * PITCH / 2
    bi, bj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    bx0 = -half + bi.ravel() * PITCH + STREET_WIDTH / 2
    bz0 = -half + bj.ravel() * PITCH + STREET_WIDTH / 2
    nblocks = n * n

    k = rng.choice(np.array([1, 2, 3]), size=nblocks, p=[0.15, 0.5, 0.35])
    blk, local = _expand(k * k)
    kk = k[blk]
    lot = (BLOCK_SIZE - 2 * SIDEWALK) / kk
    lx0 = bx0[blk] + SIDEWALK + (local % kk) * lot
    lz0 = bz0[blk] + SIDEWALK + (local // kk) * lot
    nb = blk.size

    ins = rng.uniform(0.4, 1.0, size=(nb, 4)) * np.maximum(0.4, 0.18 * lot)[:, None]
    fp = np.stack([lx0 + ins[:, 0], lz0 + ins[:, 1], lx0 + lot - ins[:, 2], lz0 + lot - ins[:, 3]], axis=1)

    cx = (fp[:, 0] + fp[:, 2]) / 2
    cz = (fp[:, 1] + fp[:, 3]) / 2
    r = np.hypot(cx, cz)
    centre = np.exp(-((r / (0.45 * half + 40.0)) ** 2))
    h = 8.0 + 32.0 * rng.beta(1.6, 2.6, size=nb) * (0.55 + 0.45 * centre)
    p_tower = (0.015 + 0.12 * centre) * np.choose(kk - 1, [2.0, 1.0, 0.4])
    tower = rng.random(nb) < p_tower
    if not tower.any():
        tower[np.argmin(r)] = True
    h_tower = rng.uniform(60.0, 120.0, size=nb)
    h = np.where(tower, h_tower, h)

    sb_rand = rng.random(nb)
    setback = np.where(tower, sb_rand < 0.6, (h > 25.0) & (sb_rand < 0.25))
    h1_frac = np.where(tower, rng.uniform(0.45, 0.7, size=nb), rng.uniform(0.6, 0.8, size=nb))
    h1 = np.where(setback, h * h1_frac, h)
    sb_ins = rng.uniform(0.15, 0.25, size=(nb, 4))
    w = fp[:, 2] - fp[:, 0]
    d = fp[:, 3] - fp[:, 1]
    up_fp = np.stack([fp[:, 0] + sb_ins[:, 0] * w, fp[:, 1] + sb_ins[:, 1] * d,
                      fp[:, 2] - sb_ins[:, 2] * w, fp[:, 3] - sb_ins[:, 3] * d], axis=1)
    up_fp = np.where(setback[:, None], up_fp, fp)

    facade = M_FACADE0 + rng.integers(0, N_FACADES, size=nb)
    glass = tower & (rng.random(nb) < 0.5)
    if not glass.any():
        glass[np.argmax(np.where(tower, h, -1.0))] = True
    material = np.where(glass, M_GLASS, facade)
    roof_rand = rng.random((nb, 4, 5))
    return _Buildings(n, half, fp, up_fp, h, h1, setback, tower, material, roof_rand)


def city_layout(target_triangles: int = 150_000, seed: int = 1) -> dict:
    """Street layout of `make_city(target_triangles, seed)` (see the module docstring).

    max_height is the top of the geometry (antennas included; it builds the city to find it),
    max_building_height the tallest building body.
    """
    b = _city_buildings(target_triangles, seed)
    n, half = b.n, b.half
    top = float(make_city(target_triangles, seed).triangles[..., 1].max())
    streets = [float(-half + k * PITCH) for k in range(n + 1)]
    cam_pos, cam_target = _city_camera(n, half)
    return {
        "pitch": PITCH,
        "street_width": STREET_WIDTH,
        "block_size": BLOCK_SIZE,
        "blocks_per_side": n,
        "half_extent": half,
        "ground_half_extent": half + PITCH,
        "street_centres": streets,
        "block_ranges": [(s + STREET_WIDTH / 2, s + PITCH - STREET_WIDTH / 2) for s in streets[:-1]],
        "sidewalk_top": PLINTH_TOP,
        "max_height": top,
        "max_building_height": float(b.h.max()),
        "building_count": int(b.h.size),
        "default_camera": {"position": cam_pos, "target": cam_target, "fov_y": 60.0},
    }


def _city_camera(n: int, half: float) -> tuple[list[float], list[float]]:
    x = -half + (n // 2) * PITCH
    return [x, 1.7, half], [x, 1.7, -half]


def make_city(target_triangles: int = 150_000, seed: int = 1) -> Scene:
    b = _city_buildings(target_triangles, seed)
    n, half, nb = b.n, b.half, b.h.size
    g = n + 2
    ground_tris = 2 * g * g

    los, his, mats = [], [], []

    def add(lo, hi, mat):
        los.append(np.asarray(lo, np.float64))
        his.append(np.asarray(hi, np.float64))
        mats.append(np.broadcast_to(np.asarray(mat, np.int32), (los[-1].shape[0],)))

    # sidewalk plinths
    bi, bj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    bx0 = -half + bi.ravel() * PITCH + STREET_WIDTH / 2
    bz0 = -half + bj.ravel() * PITCH + STREET_WIDTH / 2
    add(np.stack([bx0, np.full_like(bx0, PLINTH_BOTTOM), bz0], 1),
        np.stack([bx0 + BLOCK_SIZE, np.full_like(bx0, PLINTH_TOP), bz0 + BLOCK_SIZE], 1), M_SIDEWALK)

    fp, up = b.fp, b.up
    # lower bodies
    add(np.stack([fp[:, 0], np.full(nb, BUILDING_BOTTOM), fp[:, 1]], 1),
        np.stack([fp[:, 2], b.h1, fp[:, 3]], 1), b.material)
    # upper bodies (setbacks)
    s = b.setback
    add(np.stack([up[s, 0], b.h1[s] - 0.1, up[s, 1]], 1), np.stack([up[s, 2], b.h[s], up[s, 3]], 1),
        b.material[s])

    base_boxes = n * n + nb + int(s.sum()) + nb  # + one rooftop box per building
    relief = max(0, int(round((target_triangles - ground_tris) / 12)) - base_boxes)
    w_fp = fp[:, 2] - fp[:, 0]
    d_fp = fp[:, 3] - fp[:, 1]
    weight = b.h * 2 * (w_fp + d_fp)
    c = _distribute(relief, weight)
    n_ledge = (c + 1) // 2
    n_pil = (c - n_ledge) // 4  # per face
    n_roof = 1 + (c - n_ledge - 4 * n_pil)  # 1..4
    trim_mat = np.where(b.material == M_GLASS, M_MULLION, M_TRIM).astype(np.int32)

    # rooftop boxes on the (upper) roof; towers get a thin antenna as their first one
    own, j = _expand(n_roof)
    rr = b.roof_rand[own, j]
    ux0, uz0, ux1, uz1 = up[own].T
    uw, ud = ux1 - ux0, uz1 - uz0
    sx = (0.15 + 0.2 * rr[:, 0]) * uw
    sz = (0.15 + 0.2 * rr[:, 1]) * ud
    rh = 1.0 + 2.5 * rr[:, 2]
    antenna = b.tower[own] & (j == 0)
    sx = np.where(antenna, 0.6, sx)
    sz = np.where(antenna, 0.6, sz)
    rh = np.where(antenna, 8.0 + 12.0 * rr[:, 2], rh)
    px = ux0 + 0.05 * uw + rr[:, 3] * (0.9 * uw - sx)
    pz = uz0 + 0.05 * ud + rr[:, 4] * (0.9 * ud - sz)
    top = b.h[own]
    add(np.stack([px, top - 0.1, pz], 1), np.stack([px + sx, top + rh, pz + sz], 1),
        np.where(antenna, M_MULLION, M_ROOF))

    # ledges: slabs wrapped around the building at evenly spaced heights
    own, j = _expand(n_ledge)
    a = n_ledge[own]
    hh = b.h[own]
    y = hh * (j + 1) / (a + 1)
    t = np.minimum(0.35, 0.3 * hh / (a + 1))
    foot = np.where((y > b.h1[own])[:, None], up[own], fp[own])
    add(np.stack([foot[:, 0] - LEDGE_DEPTH, y - t / 2, foot[:, 1] - LEDGE_DEPTH], 1),
        np.stack([foot[:, 2] + LEDGE_DEPTH, y + t / 2, foot[:, 3] + LEDGE_DEPTH], 1), trim_mat[own])

    # pilasters: vertical strips on the four facades of the lower part
    own, j = _expand(4 * n_pil)
    m = n_pil[own]
    face = j // np.maximum(m, 1)
    kidx = j % np.maximum(m, 1)
    x0, z0, x1, z1 = fp[own].T
    along_x = face < 2  # faces 0/1: the -z/+z facades (strip varies in x); 2/3: -x/+x
    span = np.where(along_x, x1 - x0, z1 - z0)
    start = np.where(along_x, x0, z0)
    centre = start + span * (kidx + 1) / (m + 1)
    pw = np.minimum(0.8, 0.35 * span / (m + 1))
    lo_a, hi_a = centre - pw / 2, centre + pw / 2
    out_lo = np.choose(face, [z0 - PILASTER_DEPTH, z1 - 0.05, x0 - PILASTER_DEPTH, x1 - 0.05])
    out_hi = np.choose(face, [z0 + 0.05, z1 + PILASTER_DEPTH, x0 + 0.05, x1 + PILASTER_DEPTH])
    ytop = b.h1[own] + 0.25
    lo = np.stack([np.where(along_x, lo_a, out_lo), np.full(own.size, BUILDING_BOTTOM),
                   np.where(along_x, out_lo, lo_a)], 1)
    hi = np.stack([np.where(along_x, hi_a, out_hi), ytop, np.where(along_x, out_hi, hi_a)], 1)
    add(lo, hi, trim_mat[own])

    lo = np.concatenate(los)
    hi = np.concatenate(his)
    box_mat = np.concatenate(mats).astype(np.int32)

    total = ground_tris + 12 * lo.shape[0]
    tris = np.empty((total, 3, 3), np.float32)
    gx = -half - PITCH + PITCH * np.arange(g + 1)
    tris[:ground_tris] = _ground_grid(gx)
    boxes_to_triangles(lo, hi, out=tris[ground_tris:])
    mids = np.empty(total, np.int32)
    mids[:ground_tris] = M_ASPHALT
    mids[ground_tris:] = np.repeat(box_mat, 12)

    materials = [Material(nm, np.array(col, np.float32), mirror) for nm, col, mirror in CITY_MATERIALS]
    max_h = float(b.h.max())
    # "sun": high above, offset diagonally; irradiance ~1.5 on the ground at the city centre
    sun_h = max(3.0 * max_h, 1.2 * half)
    sun = np.array([0.35 * half, sun_h, 0.25 * half])
    dist = float(np.linalg.norm(sun))
    intensity = 1.5 * dist**2 / (sun_h / dist)
    point = PointLight(sun.astype(np.float32), np.array([1.0, 0.96, 0.9], np.float32) * np.float32(intensity))
    side = 0.1 * 2 * half
    rc = np.array([-0.3 * half, 0.9 * sun_h, -0.2 * half])
    rect = _down_facing_rect(rc, side, intensity, (0.85, 0.9, 1.0))
    cam_pos, cam_target = _city_camera(n, half)
    return Scene(
        name="city",
        triangles=tris,
        material_ids=mids,
        materials=materials,
        point_lights=[point],
        rect_lights=[rect],
        default_camera=Camera.look_at(cam_pos, cam_target, fov_y=60.0),
        identity={"builtin": "city", "size": int(target_triangles), "seed": int(seed)},
        sky_color=np.array([0.55, 0.65, 0.8], np.float32),
    )


def _ground_grid(coords: np.ndarray) -> np.ndarray:
    """Ground y = 0 as a grid of quads (2 triangles each, normal +Y) over coords x coords."""
    x0, z0 = np.meshgrid(coords[:-1], coords[:-1], indexing="ij")
    x1, z1 = np.meshgrid(coords[1:], coords[1:], indexing="ij")
    x0, z0, x1, z1 = (a.ravel() for a in (x0, z0, x1, z1))
    zero = np.zeros_like(x0)
    p00 = np.stack([x0, zero, z0], 1)
    p01 = np.stack([x0, zero, z1], 1)
    p11 = np.stack([x1, zero, z1], 1)
    p10 = np.stack([x1, zero, z0], 1)
    t1 = np.stack([p00, p01, p11], 1)
    t2 = np.stack([p00, p11, p10], 1)
    return np.concatenate([t1, t2]).astype(np.float32)


def _down_facing_rect(centre, side: float, on_axis_intensity: float, colour) -> RectLight:
    """Square light of the given side centred at `centre`, emitting towards -Y.

    Radiance L = I / A, so that straight below it gives the same irradiance as a point light of
    intensity I at its centre (its power, pi * I, is then a quarter of that point light's 4 pi I).
    """
    centre = np.asarray(centre, np.float64)
    eu = np.array([side, 0.0, 0.0])
    ev = np.array([0.0, 0.0, side])  # cross(+X, +Z) = -Y
    radiance = on_axis_intensity / (side * side)
    return RectLight(
        corner=(centre - eu / 2 - ev / 2).astype(np.float32),
        edge_u=eu.astype(np.float32),
        edge_v=ev.astype(np.float32),
        radiance=(np.asarray(colour, np.float64) * radiance).astype(np.float32),
    )


# ----------------------------------------------------------------------------------------------
# room

ROOM_HALF = 5.0
ROOM_HEIGHT = 5.0


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _placed_box(size, centre, angle: float) -> np.ndarray:
    """Box of `size` (x, y, z), rotated about Y by angle, with its centre at `centre`."""
    size = np.asarray(size, np.float64)
    t = boxes_to_triangles(-size[None] / 2, size[None] / 2).astype(np.float64)
    return (t @ _rot_y(angle).T + np.asarray(centre, np.float64)).astype(np.float32)


def _icosphere(subdivisions: int, radius: float, centre) -> np.ndarray:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return (np.asarray(mesh.triangles, np.float64) + np.asarray(centre, np.float64)).astype(np.float32)


def _cylinder_y(radius: float, y0: float, y1: float, x: float, z: float, sections: int) -> np.ndarray:
    ang = 2 * np.pi * np.arange(sections + 1) / sections
    cx, cz = radius * np.cos(ang), radius * np.sin(ang)
    a0 = np.stack([cx[:-1], np.full(sections, y0), cz[:-1]], 1)
    a1 = np.stack([cx[1:], np.full(sections, y0), cz[1:]], 1)
    b0 = a0.copy()
    b0[:, 1] = y1
    b1 = a1.copy()
    b1[:, 1] = y1
    # outward winding: angle increases from +x towards +z, i.e. clockwise seen from above (+Y)
    side1 = np.stack([a0, b1, a1], 1)
    side2 = np.stack([a0, b0, b1], 1)
    c0 = np.broadcast_to(np.array([0.0, y0, 0.0]), a0.shape)
    c1 = np.broadcast_to(np.array([0.0, y1, 0.0]), a0.shape)
    bottom = np.stack([c0, a0, a1], 1)
    top = np.stack([c1, b1, b0], 1)
    t = np.concatenate([side1, side2, bottom, top])
    return (t + np.array([x, 0.0, z])).astype(np.float32)


def room_triangle_count(detail: int) -> int:
    return int(make_room(1, detail).triangle_count)


def make_room(seed: int = 1, detail: int = 1) -> Scene:
    """A closed 10 x 5 x 10 room (x, z in [-5, 5], y in [0, 5]) with a red left wall (x = -5), a
    green right wall (x = +5), boxes, two spheres, a column and a mirror panel on the back wall."""
    detail = int(detail)
    if detail < 1:
        raise ValueError("detail must be >= 1")
    rng = np.random.default_rng(seed)
    mats = [
        Material("floor", np.array([0.72, 0.70, 0.66], np.float32)),
        Material("ceiling", np.array([0.80, 0.80, 0.80], np.float32)),
        Material("red_wall", np.array([0.63, 0.065, 0.05], np.float32)),
        Material("green_wall", np.array([0.14, 0.45, 0.091], np.float32)),
        Material("white_wall", np.array([0.73, 0.73, 0.73], np.float32)),
        Material("box_white", np.array([0.75, 0.74, 0.70], np.float32)),
        Material("box_blue", np.array([0.20, 0.30, 0.65], np.float32)),
        Material("sphere_yellow", np.array([0.80, 0.65, 0.15], np.float32)),
        Material("sphere_white", np.array([0.85, 0.85, 0.85], np.float32)),
        Material("column", np.array([0.60, 0.55, 0.50], np.float32)),
        Material("mirror", np.array([0.95, 0.95, 0.95], np.float32), mirror=True),
        Material("frame", np.array([0.25, 0.18, 0.12], np.float32)),
    ]
    ids = {m.name: i for i, m in enumerate(mats)}
    parts: list[tuple[np.ndarray, int]] = []
    r, hgt = ROOM_HALF, ROOM_HEIGHT
    g = 8 * detail
    # shell, every face wound so that its normal points into the room
    parts.append((_quad_grid((-r, 0, -r), (0, 0, 2 * r), (2 * r, 0, 0), g, g), ids["floor"]))  # +Y
    parts.append((_quad_grid((-r, hgt, -r), (2 * r, 0, 0), (0, 0, 2 * r), g, g), ids["ceiling"]))  # -Y
    parts.append((_quad_grid((-r, 0, -r), (0, hgt, 0), (0, 0, 2 * r), g, g), ids["red_wall"]))  # +X
    parts.append((_quad_grid((r, 0, -r), (0, 0, 2 * r), (0, hgt, 0), g, g), ids["green_wall"]))  # -X
    parts.append((_quad_grid((-r, 0, -r), (2 * r, 0, 0), (0, hgt, 0), g, g), ids["white_wall"]))  # +Z
    parts.append((_quad_grid((-r, 0, r), (0, hgt, 0), (2 * r, 0, 0), g, g), ids["white_wall"]))  # -Z

    j = rng.uniform(-1.0, 1.0, size=8)
    tall = (1.3, 2.6, 1.3)
    parts.append((_placed_box(tall, (-2.2 + 0.2 * j[0], tall[1] / 2 - 0.01, -1.6 + 0.2 * j[1]),
                              0.35 + 0.15 * j[2]), ids["box_white"]))
    short = (1.4, 1.4, 1.4)
    sx, sz = 1.9 + 0.2 * j[3], 0.6 + 0.2 * j[4]
    parts.append((_placed_box(short, (sx, short[1] / 2 - 0.01, sz), -0.3 + 0.15 * j[5]), ids["box_blue"]))
    sub = min(2 + detail, 7)
    parts.append((_icosphere(sub, 0.55, (sx, short[1] + 0.54, sz)), ids["sphere_white"]))
    parts.append((_icosphere(sub, 0.75, (-0.6 + 0.2 * j[6], 0.75, 1.8 + 0.2 * j[7])), ids["sphere_yellow"]))
    parts.append((_cylinder_y(0.35, -0.05, hgt + 0.05, 3.8, -3.8, 24 * detail), ids["column"]))
    # mirror panel on the back wall, turned a little towards the room centre, with a frame
    ang = -0.18
    parts.append((_placed_box((2.4, 3.0, 0.06), (0.9, 1.9, -4.78), ang), ids["mirror"]))
    parts.append((_placed_box((2.6, 3.2, 0.05), (0.9, 1.9, -4.83), ang), ids["frame"]))

    tris = np.concatenate([p for p, _ in parts]).astype(np.float32)
    mids = np.concatenate([np.full(p.shape[0], m, np.int32) for p, m in parts])
    i_point = 18.0
    point = PointLight(np.array([1.5, 4.3, 1.0], np.float32), np.array([1.0, 0.95, 0.88], np.float32) * i_point)
    rect = _down_facing_rect((0.0, hgt - 0.02, 0.0), 1.5, i_point, (1.0, 0.97, 0.92))
    return Scene(
        name="room",
        triangles=tris,
        material_ids=mids,
        materials=mats,
        point_lights=[point],
        rect_lights=[rect],
        default_camera=Camera.look_at((0.0, 2.0, 4.6), (0.0, 1.6, -5.0), fov_y=60.0),
        identity={"builtin": "room", "size": int(detail), "seed": int(seed)},
        sky_color=np.array([0.35, 0.35, 0.38], np.float32),  # ambient stand-in for indirect light
    )


# ----------------------------------------------------------------------------------------------
# room-anim: the room with moving objects (thesis Figure 5.7 in spirit: objects falling inside a room)

ANIM_FALL_PERIOD = 2.4  # seconds per fall (drop, bounce, rest), then the object is lifted again
ANIM_GRAVITY = 9.81


def _rot_xyz(ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations: about X by ax, then about Y by ay (vectorised over K objects)."""
    cx, sx, cy, sy = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay)
    one, zero = np.ones_like(ax), np.zeros_like(ax)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cx, -sx], -1),
                   np.stack([zero, sx, cx], -1)], -2)
    ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1),
                   np.stack([-sy, zero, cy], -1)], -2)
    return ry @ rx


@dataclass(frozen=True)
class RoomAnimation:
    """Rigid objects moving inside the room; positions are a pure function of the scene time.

    static:  float32 (S, 3, 3) triangles that never move (the room), first in the triangle array
    local:   float64 (D, 3, 3) triangles of the moving objects in object space (centred on 0)
    owner:   int (D,) object of each moving triangle
    kind:    per object 0 = falls from `height` to `rest` (bounces, tumbles, lifted again each
             period), 1 = spins about Y in place, 2 = orbits the room centre at `height`
    """

    static: np.ndarray
    local: np.ndarray
    owner: np.ndarray
    kind: np.ndarray
    anchor: np.ndarray  # float64 (K, 3): x, z of the path, y unused
    height: np.ndarray  # float64 (K,) start / orbit height
    rest: np.ndarray  # float64 (K,) centre height when resting on the floor
    phase: np.ndarray  # float64 (K,) time offset (s)
    rate: np.ndarray  # float64 (K,) spin (rad/s) for kinds 0 and 1, angular speed for kind 2

    def poses(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3, 3) rotations and (K, 3) centres at time t."""
        k = len(self.kind)
        tt = t + self.phase
        centre = np.empty((k, 3))
        centre[:, 0], centre[:, 2] = self.anchor[:, 0], self.anchor[:, 2]
        # falling: free fall from height, one damped bounce, rest; restart every period
        s = np.mod(tt, ANIM_FALL_PERIOD)
        drop = self.height - self.rest
        t_hit = np.sqrt(2 * np.maximum(drop, 0) / ANIM_GRAVITY)
        v_up = 0.35 * ANIM_GRAVITY * t_hit  # bounce with restitution 0.35
        sb = s - t_hit
        y_fall = np.where(s < t_hit, self.height - 0.5 * ANIM_GRAVITY * s * s,
                          self.rest + np.maximum(v_up * sb - 0.5 * ANIM_GRAVITY * sb * sb, 0.0))
        t_stop = t_hit + 2 * v_up / ANIM_GRAVITY
        moving = np.minimum(s, t_stop)  # spinning stops once at rest
        ang = np.where(self.kind == 0, self.rate * moving, self.rate * tt)
        orbit = self.kind == 2
        centre[:, 1] = np.where(self.kind == 0, y_fall, self.height)
        r = np.hypot(self.anchor[:, 0], self.anchor[:, 2])
        a0 = np.arctan2(self.anchor[:, 2], self.anchor[:, 0])
        centre[orbit, 0] = (r * np.cos(a0 + ang))[orbit]
        centre[orbit, 2] = (r * np.sin(a0 + ang))[orbit]
        # tumble about X while in the air, back to 0 at rest (the cube lands flat on the floor)
        tilt = np.where(self.kind == 0, 0.6 * np.sin(np.pi * moving / np.maximum(t_stop, 1e-9)), 0.0)
        return _rot_xyz(tilt, ang), centre

    def __call__(self, t: float) -> np.ndarray:
        rot, centre = self.poses(t)
        # one gather per object, then one batched product over all moving vertices
        moved = np.einsum("dij,dvj->dvi", rot[self.owner], self.local) + centre[self.owner][:, None, :]
        return np.concatenate([self.static, moved.astype(np.float32)])


def make_room_anim(seed: int = 1, detail: int = 1) -> Scene:
    """`room` plus six moving objects: three cubes falling onto the floor (tumbling, bouncing,
    lifted again every ANIM_FALL_PERIOD s, staggered), a box spinning on the floor and two spheres
    orbiting under the ceiling. Deterministic from the scene time (seconds); triangle count,
    order and materials never change. Resting cubes sink 1 cm into the floor (no coplanar faces)."""
    base = make_room(seed, detail)
    mats = list(base.materials) + [
        Material("anim_orange", np.array([0.85, 0.40, 0.10], np.float32)),
        Material("anim_teal", np.array([0.10, 0.55, 0.55], np.float32)),
        Material("anim_purple", np.array([0.45, 0.20, 0.60], np.float32)),
    ]
    m0 = len(base.materials)
    sub = min(1 + detail, 5)
    cube = boxes_to_triangles(np.full((1, 3), -0.3), np.full((1, 3), 0.3)).astype(np.float64)
    slab = boxes_to_triangles(np.array([[-0.6, -0.25, -0.2]]), np.array([[0.6, 0.25, 0.2]])).astype(np.float64)
    ball = _icosphere(sub, 0.35, (0.0, 0.0, 0.0)).astype(np.float64)
    objs = [  # (local triangles, material, kind, anchor x, z, height, rest, phase, rate)
        (cube, m0, 0, 2.7, 2.9, 4.2, 0.29, 0.0, 2.5),
        (cube, m0 + 1, 0, -3.3, 3.0, 4.4, 0.29, 0.8, -2.0),
        (cube, m0 + 2, 0, 0.4, -1.4, 4.0, 0.29, 1.6, 3.0),
        (slab, m0, 1, -3.4, -0.2, 0.24, 0.24, 0.0, 1.3),
        (ball, m0 + 1, 2, 1.6, 0.0, 3.6, 3.6, 0.0, 0.7),
        (ball, m0 + 2, 2, -2.2, 0.4, 3.1, 3.1, 0.0, -0.5),
    ]
    local = np.concatenate([o[0] for o in objs])
    owner = np.concatenate([np.full(len(o[0]), i) for i, o in enumerate(objs)])
    col = np.array([o[2:] for o in objs], np.float64)
    anim = RoomAnimation(
        static=base.triangles, local=local, owner=owner, kind=col[:, 0].astype(np.int64),
        anchor=np.stack([col[:, 1], np.zeros(len(objs)), col[:, 2]], 1),
        height=col[:, 3], rest=col[:, 4], phase=col[:, 5], rate=col[:, 6])
    mids = np.concatenate([base.material_ids] + [np.full(len(o[0]), o[1], np.int32) for o in objs])
    return Scene(
        name="room-anim",
        triangles=anim(0.0),
        material_ids=mids.astype(np.int32),
        materials=mats,
        point_lights=base.point_lights,
        rect_lights=base.rect_lights,
        default_camera=base.default_camera,
        identity={"builtin": "room-anim", "size": int(detail), "seed": int(seed)},
        sky_color=base.sky_color,
        animation=anim,
    )


# ----------------------------------------------------------------------------------------------
# registry


@dataclass(frozen=True)
class Builtin:
    """A built-in scene: make(size, seed) -> Scene; `size` is what --scene-size means for it."""

    make: Callable[[int, int], Scene]
    default_size: int
    min_size: int
    max_size: int
    size_meaning: str
    bytes_per_size: float = 0.0  # peak memory of loading + BVH build per unit of size (measured)
    fixed_bytes: float = 64 * 2**20

    def memory_estimate(self, size: int) -> float:
        """Peak bytes (above the interpreter) that `prepare_scene` needs at this size."""
        return self.fixed_bytes + self.bytes_per_size * size


# city: peak RSS of prepare_scene("city", n) was 138 / 434 / 819 MB at n = 0.25M / 1M / 2M on
# x86-64 (about 395 bytes per triangle: float32 triangles, bounds, SAH build arrays, leaf-order
# copy); 420 keeps a margin
BUILTIN_SCENES: dict[str, Builtin] = {
    "city": Builtin(lambda size, seed: make_city(size, seed), 150_000, 1_000, 40_000_000,
                    "target triangle count", bytes_per_size=420.0),
    "room": Builtin(lambda size, seed: make_room(seed, size), 1, 1, 6, "detail level"),
    "room-anim": Builtin(lambda size, seed: make_room_anim(seed, size), 1, 1, 6, "detail level (animated)"),
}

"""Point-centred grid: angular tiles x distance slabs around a point every ray of a pass goes
through (a point light for shadow rays, the eye for primary rays), with the rays sorted into
chunks per tile. After Guntury & Narayanan (EGPGV 2010, per-light spherical grids) and Patidar &
Narayanan (ICVGIP 2008, perspective grids); built per pass on the OpenCL device with no host
round trip: the frame, the placement, the buffer sizes and the trace's launch size never come
back to the host.

Build (kernels in pointgrid.cl beside this file, primitives from viewer.cl.primitives):
 1. frame: forward axis = mean direction from the centre of a strided sample of the rays (so the
    rays lie away from the poles of the spherical mapping), up/right orthogonal to it (pg_frame,
    one work-group; choose_frame is its float64 reference).
 2. rays: per ray, its direction u from the centre and an upper bound of how far (in angle) its
    segment strays from u where it could meet geometry: h / max(nearest along-ray distance,
    sqrt(d0^2 - h^2)), h = distance of the ray's line from the centre, d0 = distance from the
    centre to the scene box (computed in double; a ray leaving from the centre itself is 0 at
    once). Rays above `margin` ("outside": other origins, segments through the centre) are
    appended to a list and traced another way; the grid's margin is the largest bound of the rays
    it keeps, so rays that meet exactly in the centre (the eye) or lights outside the scene box
    cost no margin. The angles come from a polynomial atan2 (RAY_ANGLE_ERR is added to the
    margin). Counts and reductions are done in the same kernel (work-group reduction, one
    atomic per group and value, into a small statistics buffer `st` that stays on the device).
 3. angular rectangle of the rays, grown by the margin; tiles over it (~tile_rays rays per tile,
    `tiles` on the longer side, or tiles of `tile_angle` radians); slabs by distance from the
    centre: pg_place, one work-item reading `st` (placement_reference is its float64
    reference). The cell buffers are sized by tiles_bound, the most tiles it can choose.
 4. (tile, ray) pairs radix-sorted; segments cut into chunks of at most `chunk` rays.
 5. triangles: culled when two vertices are equal (never hit: far from the origin float32 snaps
    small meshes onto a coarse lattice, 91% of the dragon at 1e6) or, with `backface`, facing away
    from the centre (double); else a conservative (alpha, theta) box of the triangle itself
    (pointgrid.cl: azimuths at the vertices, elevations bounded through the triangle's distance
    from the pole axis; full azimuth when it surrounds or nears the pole axis or crosses the
    seam: "widened"; a projection that is a point or a segment on a line through the pole axis
    is judged by its distance from the axis, not as "around" it; a small triangle, bounding
    sphere under a quarter of its distance, is boxed through that sphere: two atan2 instead of
    five), grown by the margin; stored per triangle (tri_box: the trace tests each ray's angles
    against it before the triangle, the tile test at full resolution); clipped
    to the rays' rectangle (triangles outside it are culled: frustum culling for the eye); one
    slab from a lower bound d of the triangle's distance to the centre. (cell = tile * slabs +
    slab, triangle) pairs counted, scanned, written with key (cell << level_bits) | level(d)
    (a log-like distance level from the float bits, pg_levels), sorted; per-cell counts from the
    segments, then an exclusive scan gives cell_start (ncells + 1 entries), so a tile's triangles
    are contiguous, in slab order and nearest first within a cell (the trace's in-cell stop).

Sizes without waits: every count the later kernels need stays on the device (the primitives'
device-count variants). The pair buffers are sized from the last pass of the same key (a light,
a ray type; +25%): when a pass needs more, nothing is written, pg_ray_keys sends every ray of the
grid to the outside list (so the pass stays exact: the caller traces that list another way) and
the next pass gets room. The trace is launched with `launch_groups` persistent work-groups (the
key's last chunk count + 1/8) that loop over the chunk count on the device. The counters
(`stats`) are copied without a wait and reported by the key's next pass. A key's first pass (or
exact=True: tests, studies) waits twice instead, so its buffers fit and its counters are its own.

Asynchronous host writes (`_async`) do not wait: viewer.cl.io keeps their events until the
queue next waits (a dropped pyopencl event of a non-blocking host copy would wait for the copy,
a hidden host sync that stalled each build three times).

Layouts: header PGRID_DTYPE (112 bytes: float4 centre (w = margin), fwd (w = 1: back-face
culling), up (w = distance level bits), right, rect (alpha0, theta0, tiles per radian in alpha
and theta), slab (width, 1 / width, tan(margin), d0 = distance from the centre to the scene box,
where slab 0 starts); int4 res (tiles alpha, tiles theta, slabs, cells)); cell_start uint32
(ncells + 1,); keys uint32 (pairs,) sorted pair keys and refs uint32 (pairs,) triangle slots;
levels float4 (dnear, shift, 0, 0); tri_box float4 (n_tris,) angular boxes (alpha min, max,
theta min, max); chunks: viewer.cl.primitives.Chunks over the sorted ray keys (key = tile,
ntiles for rays outside the grid, ntiles + 1 for inactive rays: neither is traced here, so the
caller writes misses first), ray_vals uint32 (n,) ray indices in that order.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer.cl import io as clio
from viewer.cl.limits import pair_cap
from viewer.cl.pool import BufferPool

KERNEL = Path(__file__).resolve().parent / "pointgrid.cl"
WG = 64
MAX_PAIRS = 2**26
PAIR_BYTES = 28  # keys, refs, radix scratch (8), segments (12)
MAX_TILES_AXIS = 1024

PGRID_DTYPE = np.dtype([("centre", "<f4", 4), ("fwd", "<f4", 4), ("up", "<f4", 4), ("right", "<f4", 4),
                        ("rect", "<f4", 4), ("slab", "<f4", 4), ("res", "<i4", 4)])
assert PGRID_DTYPE.itemsize == 112


@dataclass
class PointGridSpec:
    chunk: int = 64  # rays per chunk (one work-group each)
    tile_rays: int = 64  # automatic tiling: about this many rays per tile
    tiles: int = 0  # >0: tiles along the longer side of the angular rectangle instead
    tile_angle: float = 0.0  # >0: tiles of this many radians (a fixed angular resolution) instead
    slabs: int = 16
    margin: float = 0.004  # radians
    backface: bool = False  # cull triangles facing away from the centre (exact only for closed, outward-facing
    # geometry seen from outside it: the eye of a primary pass, see PgridBackend._backface)


@dataclass
class PointGridStats:
    tiles: tuple[int, int]
    slabs: int
    rays: int
    in_grid: int
    outside: int
    inactive: int
    chunks: int
    pairs: int
    culled: int
    widened: int
    build_ms: float
    rearrange_ms: float = 0.0
    culled_backface: int = 0  # among `culled`
    overflow: bool = False  # the pairs overflowed their buffers: every ray went the other way

    def as_dict(self, chunk: int) -> dict[str, float]:
        return {"pairs": float(self.pairs), "chunks": float(self.chunks),
                "chunk_occupancy": self.in_grid / max(self.chunks * chunk, 1), "culled": float(self.culled),
                "culled_backface": float(self.culled_backface),
                "widened": float(self.widened), "outside_rays": float(self.outside),
                "inactive_rays": float(self.inactive), "grid_rays": float(self.in_grid),
                "tiles": float(self.tiles[0] * self.tiles[1]), "grid_build_ms": self.build_ms,
                "rearrange_ms": self.rearrange_ms}


RAY_ANGLE_ERR = 3e-6  # radians: pg_angles' error (2e-6 from pg_atan2_fast, plus float rounding of u)
ST_CULLED = 7  # pointgrid.cl PG_ST_*: outside, inactive, deviation, alpha min/max, theta min/max, culled, widened
ST_INIT = np.array([0, 0, 0, 0xFFFFFFFF, 0, 0xFFFFFFFF, 0, 0, 0, 0, 0xFFFFFFFF, 0], np.uint32)
LEVEL_BITS = 8  # at least this many distance level bits (pointgrid.cl pg_levels) where the cell ids leave
# room, rounded up to fill the radix sort's last 8-bit digit (no extra pass): the closest-hit trace stops a
# ray at the first staged block whose level bound lies beyond its hit, so finer levels are free up to there
# (the mixed scene: 15 cell bits + 9 level bits; 12 bits, a fourth sort pass, traced no faster)


# -- float64 references of the device's placement (pg_frame, pg_place; tests compare them) --------


def level_bits(cell_bits: int) -> int:
    """Distance level bits of the pair keys: LEVEL_BITS, rounded up to fill the radix sort's last
    8-bit digit, within 32 key bits."""
    total = min(32, -(-(cell_bits + LEVEL_BITS) // 8) * 8)
    return max(0, total - cell_bits)


def decode_ord(keys: np.ndarray) -> np.ndarray:
    """float32 values of pg_ord keys (pointgrid.cl: the order-preserving float -> uint map)."""
    k = np.asarray(keys, np.uint32)
    bits = np.where(k & np.uint32(0x80000000), k & np.uint32(0x7FFFFFFF), ~k)
    return bits.astype(np.uint32).view(np.float32)


def choose_frame(centre: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, ...]:
    """(fwd, up, right) unit vectors: fwd = mean direction from `centre` of the sampled rays
    ((k, 4) origin + tmin and direction + tmax rows; inactive rows ignored)."""
    o, d = origins.astype(np.float64), dirs.astype(np.float64)
    act = (d[:, 3] > o[:, 3]) & np.isfinite(o).all(1) & np.isfinite(d[:, :3]).all(1)
    fwd = np.array([0.0, 0.0, -1.0])
    if act.any():
        o, d = o[act], d[act]
        dn = d[:, :3] / np.maximum(np.linalg.norm(d[:, :3], axis=1, keepdims=True), 1e-300)
        p = o[:, :3] + o[:, 3:4] * d[:, :3] - centre  # segment start seen from the centre
        lam = (p * dn).sum(1)
        u = np.where((lam >= 0)[:, None], dn, -dn)
        m = u.sum(0)
        if np.linalg.norm(m) > 1e-9 * len(u):
            fwd = m / np.linalg.norm(m)
    axis = np.eye(3)[int(np.argmin(np.abs(fwd)))]
    up = axis - fwd * float(axis @ fwd)
    up /= np.linalg.norm(up)
    right = np.cross(up, fwd)
    return fwd, up, right


def tile_counts(span_a: float, span_t: float, rays: int, spec: PointGridSpec) -> tuple[int, int]:
    """Tiles in azimuth and elevation over an angular rectangle span_a x span_t (radians)."""
    span_a, span_t = max(span_a, 1e-9), max(span_t, 1e-9)
    if spec.tile_angle > 0:
        k = 1.0 / spec.tile_angle
    elif spec.tiles > 0:
        k = spec.tiles / max(span_a, span_t)
    else:
        k = np.sqrt(max(rays, 1) / max(spec.tile_rays, 1) / (span_a * span_t))
    na = int(np.clip(round(span_a * k), 1, MAX_TILES_AXIS))
    nt = int(np.clip(round(span_t * k), 1, MAX_TILES_AXIS))
    return na, nt


def placement_reference(st: np.ndarray, n: int, spec: PointGridSpec) -> tuple[float, tuple[float, ...], int, int]:
    """pg_place in float64 from pg_classify's statistics `st` (uint32, ST_INIT's layout) for n rays:
    (margin, (alpha0, theta0, alpha1, theta1), tiles in alpha, tiles in theta)."""
    in_grid = n - int(st[0]) - int(st[1])
    red = decode_ord(st[2:7]).astype(np.float64)
    m = float(red[0]) * (1 + 1e-4) + 1e-6 if in_grid else spec.margin
    m = min(m, spec.margin) + RAY_ANGLE_ERR
    a0, a1, e0, e1 = (float(x) for x in red[1:]) if in_grid else (0.0, 0.0, 0.0, 0.0)
    a0, a1 = max(a0 - 2 * m, -np.pi), min(a1 + 2 * m, np.pi)
    e0, e1 = max(e0 - 2 * m, -np.pi / 2), min(e1 + 2 * m, np.pi / 2)
    na, nt = tile_counts((a1 - a0) * (np.cos(min(abs(e0), abs(e1))) if e0 * e1 > 0 else 1.0), e1 - e0, in_grid,
                         spec)
    return m, (a0, e0, a1, e1), na, nt


FRAME_SAMPLE = 4096  # rays (strided) pg_frame takes the mean direction of


def tiles_bound(n: int, spec: PointGridSpec) -> int:
    """The most tiles pg_place (pointgrid.cl, the device's tile_counts) can choose for n rays: with
    x, y the unrounded tiles per axis (at most 1024 after clipping), round(x) round(y) <= x y +
    (x + y) / 2 + 1/4 <= rays / tile_rays + 1025; `tiles` gives at most tiles^2, `tile_angle`
    (2 pi / a + 1)(pi / a + 1). The host sizes the cell buffers by it, so they never overflow."""
    cap = MAX_TILES_AXIS * MAX_TILES_AXIS
    if spec.tile_angle > 0:
        cap = min(cap, int((2 * np.pi / spec.tile_angle + 2) * (np.pi / spec.tile_angle + 2)))
    elif spec.tiles > 0:
        cap = min(cap, int(spec.tiles) ** 2)
    else:
        cap = min(cap, -(-max(n, 1) // max(int(spec.tile_rays), 1)) + 1025)
    return max(cap, 1)


@dataclass
class _Late:
    """A pass's counters, copied to the host without a wait: valid once `ready` (the next pass of
    the same key is a frame later, after the frame's own waits)."""

    raw: np.ndarray  # uint32 (16,): pg_classify / pg_tri_count statistics (12), pairs, chunks, tiles alpha, theta
    event: Any
    n: int
    cap: int
    chunk: int  # rays per chunk (0: one chunk per tile)
    slabs: int

    @classmethod
    def read(cls, q: Any, st: Any, pairs: Any, chunks: Any, header: Any, n: int, cap: int, chunk: int,
             slabs: int) -> _Late:
        raw = np.zeros(16, np.uint32)
        clio.copy(q, raw[0:12], st, is_blocking=False)
        clio.copy(q, raw[12:13], pairs, is_blocking=False)
        clio.copy(q, raw[13:14], chunks, is_blocking=False)
        ev = clio.copy(q, raw[14:16], header, src_offset=PGRID_DTYPE.fields["res"][1], is_blocking=False)
        return cls(raw, ev, n, cap, chunk, slabs)

    def ready(self, cl: Any) -> bool:
        """The copies have landed (an in-order queue: the last one's status; no wait). `cl`: pyopencl."""
        return self.event.get_info(cl.event_info.COMMAND_EXECUTION_STATUS) == cl.command_execution_status.COMPLETE

    @property
    def pairs(self) -> int:
        return int(self.raw[12])

    @property
    def chunks(self) -> int:
        return int(self.raw[13])

    @property
    def outside(self) -> int:
        return int(self.raw[0])

    @property
    def inactive(self) -> int:
        return int(self.raw[1])

    def stats(self, build_ms: float, rearrange_ms: float) -> PointGridStats:
        """PointGridStats of that pass (an overflow shows no pairs: every ray went the other way)."""
        st, c = self.raw, self.chunk
        overflow = self.pairs > self.cap
        sentinel = sum((-(-k // c) if c else 1) if k else 0 for k in (self.outside, self.inactive))
        return PointGridStats((int(st[14]), int(st[15])), self.slabs, self.n, self.n - self.outside - self.inactive,
                              self.outside, self.inactive, self.chunks - sentinel, 0 if overflow else self.pairs,
                              int(st[ST_CULLED]), int(st[ST_CULLED + 1]), build_ms, rearrange_ms,
                              culled_backface=int(st[ST_CULLED + 2]), overflow=overflow)


@dataclass
class _Pass:
    """What place() leaves for rearrange()."""

    key: Hashable
    exact: bool
    n: int
    cap: int
    hard_cap: int  # the most pairs the device holds (hard_cap())
    tiles_cap: int
    late: _Late | None
    build_ms: float


class PointGrid:
    """Per-pass point-centred grid on the device (buffers reused across builds)."""

    def __init__(self, ctx: Any = None, prims: Any = None):
        from viewer.cl import build, cl_context
        from viewer.cl.primitives import primitives

        self.ctx = ctx or cl_context()
        self.prims = prims or primitives(self.ctx)
        prog = build(KERNEL, {"WG": WG}, self.ctx)
        self._k = clio.kernels(prog, ("pg_frame", "pg_classify", "pg_place", "pg_ray_keys", "pg_tri_count",
                                      "pg_tri_write", "pg_pairs_clamp", "pg_cell_counts"))
        self._bufs = BufferPool(self.ctx, "light grid")
        self.header_host = np.zeros(1, PGRID_DTYPE)
        self.header = self.buf("header", PGRID_DTYPE.itemsize)
        self.stats: PointGridStats | None = None
        self.chunks = None
        self.launch_groups = 0  # work-groups of the trace launch (persistent: they loop over the chunks)
        self._late: dict[Hashable, _Late] = {}  # pass key -> its last pass's counters (copied without a wait)
        self._pass: _Pass | None = None
        self._capacity = 0  # room for pairs (the pair buffers' size)
        self._told_limit = False
        self._n_hosts: dict[str, tuple[int, int]] = {}  # name -> (n, buffer id) last written

    def buf(self, name: str, nbytes: int) -> Any:
        return self._bufs.get(name, nbytes)

    def _run(self, name: str, n: int, *args: Any) -> None:
        if n:
            self._k[name](self.ctx.queue, (-(-n // WG) * WG,), (WG,), *args)

    def build(self, tris: Any, n_tris: int, scene_lo: np.ndarray, scene_hi: np.ndarray, ray_o: Any, ray_d: Any,
              n: int, centre: np.ndarray, spec: PointGridSpec, key: Hashable = None,
              exact: bool | None = None) -> PointGridStats:
        """Both halves: `place` (frame, ray directions, tiles; triangle pairs) then `rearrange` (rays)."""
        self.place(tris, n_tris, scene_lo, scene_hi, ray_o, ray_d, n, centre, spec, key, exact)
        return self.rearrange(n, spec)

    def hard_cap(self) -> int:
        """The most pairs one build may hold: MAX_PAIRS and the device's memory."""
        return min(MAX_PAIRS, pair_cap(self.ctx, PAIR_BYTES))

    def place(self, tris: Any, n_tris: int, scene_lo: np.ndarray, scene_hi: np.ndarray, ray_o: Any, ray_d: Any,
              n: int, centre: np.ndarray, spec: PointGridSpec, key: Hashable = None, exact: bool | None = None) -> None:
        """The grid around `centre` for the n rays in (ray_o, ray_d) (viewer.cl.transfer layout): steps
        1-3 and 5 of the module docstring (the data-structure build), all on the device.

        `key` names the pass (a light, a ray type): its pair buffers are sized from its last pass
        (+25%, copied without a wait; an overflow sends every ray the other way and the next pass
        gets room), and its counters (`stats`) are that last pass's. The first pass of a key, or
        exact=True, waits twice (the pair total, the chunk count) so its buffers fit and its counters
        are its own."""
        cl, q, u = self.ctx.cl, self.ctx.queue, np.uint32
        p = self.prims
        t0 = time.perf_counter()
        late = self._late.get(key)
        if late is not None and not late.ready(cl):  # not landed yet (no wait since): size as a first pass
            late = None
        exact = late is None or bool(exact)  # exact=False cannot size a pass no earlier one measured
        centre = np.asarray(centre, np.float64)
        d0 = float(np.linalg.norm(centre - np.clip(centre, scene_lo, scene_hi))) * (1 - 1e-6)
        corners = np.array([[x, y, z] for x in (scene_lo[0], scene_hi[0]) for y in (scene_lo[1], scene_hi[1])
                            for z in (scene_lo[2], scene_hi[2])], np.float64)
        dmax = float(np.linalg.norm(corners - centre, axis=1).max()) * 1.0001 + 1e-30
        ns = max(1, int(spec.slabs))
        width = max(dmax - d0, 1e-30) / ns
        h = np.zeros(1, PGRID_DTYPE)
        h["centre"][0, :3], h["centre"][0, 3] = centre, spec.margin
        h["fwd"][0, 3] = 1.0 if spec.backface else 0.0  # the kernels' back-face switch
        h["slab"][0] = (width, 1.0 / width, np.tan(spec.margin), d0)
        h["res"][0] = (1, 1, ns, ns)
        self.header_host = h  # the device completes it (pg_frame, pg_place); header_numpy() reads it back
        self._async(self.header, h)
        alpha, theta = self.buf("alpha", 4 * n), self.buf("theta", 4 * n)
        outside, out_idx = self.buf("outside", 4 * n), self.buf("outside_idx", 4 * n)
        st_buf = self.buf("st", ST_INIT.nbytes)
        self._async(st_buf, ST_INIT)
        if n:  # the frame from a strided sample of the rays (one work-group)
            step = max(1, n // FRAME_SAMPLE)
            self._k["pg_frame"](q, (WG,), (WG,), self.header, ray_o, ray_d, u(step), u(-(-n // step)))
        # the rays' directions and deviations; their counts, rectangle and largest deviation into st
        self._run("pg_classify", n, self.header, ray_o, ray_d, u(n), alpha, theta, outside, st_buf, out_idx)
        tiles_cap = tiles_bound(n, spec)
        cells_cap = tiles_cap * ns
        key_bits = min(32, -(-(max(1, (cells_cap - 1).bit_length()) + LEVEL_BITS) // 8) * 8)
        spec4 = np.array([spec.margin, spec.tile_rays, spec.tiles, spec.tile_angle], np.float32)
        n_cells = self.buf("n_cells", 4)
        self._k["pg_place"](q, (1,), None, self.header, st_buf, u(n), spec4, np.float32(RAY_ANGLE_ERR), u(tiles_cap),
                            u(key_bits), n_cells)
        # triangles: (cell, triangle) pairs
        from viewer.cl.primitives import Chunks

        nt1 = max(n_tris, 1)
        counts, flags = self.buf("tri_counts", 4 * nt1), self.buf("tri_flags", 4 * nt1)
        place, place_slab = self.buf("tri_place", 16 * nt1), self.buf("tri_slab", 4 * nt1)
        dmin, box = self.buf("tri_dmin", 4 * nt1), self.buf("tri_box", 16 * nt1)
        self._run("pg_tri_count", n_tris, self.header, tris, u(n_tris), counts, flags, place, place_slab, dmin,
                  st_buf, box)
        pairs_buf = self.buf("pairs", 4)
        if n_tris:
            p.exclusive_scan_dev(counts, counts, self._n_buf(n_tris, "n_tris"), n_tris, pairs_buf)
        else:
            cl.enqueue_fill_buffer(q, pairs_buf, u(0), 0, 4)
        hard = self.hard_cap()
        if exact:  # one wait: the pair total sizes the buffers
            got = np.zeros(1, np.uint32)
            clio.copy(q, got, pairs_buf)
            cap = min(max(int(got[0]), 1), hard)
        else:
            cap = min(max(self._capacity, -(-late.pairs * 5 // 4) + 1024), hard)
        self._capacity = max(self._capacity, cap)
        keys, refs = self.buf("keys", 4 * cap), self.buf("refs", 4 * cap)
        self._run("pg_tri_write", nt1, self.header, u(n_tris), counts, place, place_slab, flags, dmin, st_buf,
                  self.buf("levels", 16), keys, refs, pairs_buf, u(cap))
        n_eff = self.buf("n_eff", 4)
        self._k["pg_pairs_clamp"](q, (1,), None, pairs_buf, u(cap), n_eff)
        cell_start = self.buf("cell_start", 4 * (cells_cap + 1))
        cl.enqueue_fill_buffer(q, cell_start, u(0), 0, 4 * (cells_cap + 1))
        p.sort_pairs_dev(keys, refs, n_eff, cap, key_bits)
        seg = p.segments_dev(keys, n_eff, cap, None,
                             Chunks(0, self.buf("seg_key", 4 * cap), self.buf("seg_start", 4 * cap),
                                    self.buf("seg_len", 4 * cap)), self.buf("seg_count", 4))
        self._run("pg_cell_counts", cap, self.header, seg.key, seg.length, self._bufs["seg_count"], cell_start)
        p.exclusive_scan_dev(cell_start, cell_start, n_cells, cells_cap + 1, self.buf("cells_total", 4))
        self._pass = _Pass(key, exact, n, cap, hard, tiles_cap, late, (time.perf_counter() - t0) * 1e3)

    def _async(self, buf: Any, host: np.ndarray) -> None:
        """An asynchronous write of `host` to `buf` (viewer.cl.io keeps its event, and so `host`,
        until the queue next waits: no hidden host sync)."""
        clio.copy(self.ctx.queue, buf, host, is_blocking=False)

    def _n_buf(self, n: int, name: str = "n") -> Any:
        """A device uint32 holding n (the count the device-count primitives read); written only
        when n changes."""
        buf = self.buf(name, 4)
        if self._n_hosts.get(name) != (n, id(buf)):
            self._n_hosts[name] = (n, id(buf))
            self._async(buf, np.array([n], np.uint32))
        return buf

    def rearrange(self, n: int, spec: PointGridSpec, balance: bool = True) -> PointGridStats:
        """Step 4: (tile, ray) pairs sorted, chunks of at most spec.chunk rays (balance=False: one
        chunk per tile, whatever its size); the chunk count stays on the device (`chunk_count`),
        and the trace launch gets `launch_groups` persistent work-groups: the last pass's chunk
        count (+1/8), or, on an exact pass, this one's (its second wait)."""
        from viewer.cl.primitives import Chunks

        ps = self._pass
        assert ps is not None and ps.n == n, "place first"
        q, u = self.ctx.queue, np.uint32
        t0 = time.perf_counter()
        st_buf = self._bufs["st"]
        rk, rv = self.buf("ray_keys", 4 * n), self.buf("ray_vals", 4 * n)
        self._run("pg_ray_keys", n, self.header, self._bufs["alpha"], self._bufs["theta"], self._bufs["outside"],
                  u(n), rk, rv, self._bufs["pairs"], u(ps.cap), st_buf, self._bufs["outside_idx"])
        self.prims.sort_pairs(rk, rv, n, key_bits=max(1, (ps.tiles_cap + 1).bit_length()))
        out = Chunks(0, self.buf("ch_key", 4 * n), self.buf("ch_start", 4 * n), self.buf("ch_len", 4 * n))
        self.chunks = self.prims.segments_dev(rk, self._n_buf(n, "n_rays"), n, spec.chunk if balance else None, out,
                                              self.buf("chunk_count", 4))
        bound = min(n, (-(-n // spec.chunk) if balance else 0) + min(ps.tiles_cap, n) + 2)
        # this pass's counters, copied without a wait (the next pass of the key reports them)
        now = _Late.read(q, st_buf, self._bufs["pairs"], self._bufs["chunk_count"], self.header, n, ps.cap,
                         spec.chunk if balance else 0, max(1, int(spec.slabs)))
        self._late[ps.key] = now
        if ps.exact:
            clio.finish(q)
            shown = now
            self.chunks.count = now.chunks
            self.launch_groups = max(now.chunks, 1)
        else:
            shown = ps.late
            self.launch_groups = max(1, min(bound, ps.late.chunks + ps.late.chunks // 8 + 64))
        self.stats = shown.stats(ps.build_ms, (time.perf_counter() - t0) * 1e3)
        if shown.pairs > ps.hard_cap and not self._told_limit:  # said once: the passes stay exact, slower
            self._told_limit = True
            print(f"rtwalk: note: a light grid of {self.stats.tiles} tiles needs {shown.pairs:,} triangle-cell "
                  f"pairs, more than this OpenCL device holds ({ps.hard_cap:,}): its rays take the uniform grid "
                  "(use fewer tiles: tile_rays, tiles or tile_deg)", file=sys.stderr, flush=True)
        return self.stats

    @property
    def chunk_count(self) -> Any:
        """uint32 device buffer: the chunks of the last rearrange (the trace reads it)."""
        return self._bufs["chunk_count"]

    @property
    def outside_counter(self) -> Any:
        """uint32 device buffer whose first value counts the rays listed in outside_index."""
        return self._bufs["st"]

    def header_numpy(self) -> np.ndarray:
        """The header as the device completed it (tests and studies: a wait)."""
        out = np.zeros(1, PGRID_DTYPE)
        clio.copy(self.ctx.queue, out, self.header)
        return out

    @property
    def cell_start(self) -> Any:
        return self._bufs["cell_start"]

    @property
    def keys(self) -> Any:
        """Sorted pair keys (cell << up.w bits | distance level): the trace's in-cell stop."""
        return self._bufs["keys"]

    @property
    def levels(self) -> Any:
        """float4 (dnear, shift, 0, 0) of the distance levels (pointgrid.cl pg_levels; shift < 0: none)."""
        return self._bufs["levels"]

    @property
    def refs(self) -> Any:
        return self._bufs["refs"]

    @property
    def tri_box(self) -> Any:
        """float4 per triangle slot: its angular box (alpha min, max, theta min, max), grown by the
        margin (valid for the binned triangles)."""
        return self._bufs["tri_box"]

    @property
    def ray_angles(self) -> tuple[Any, Any]:
        """float per ray: alpha, theta of its direction u (valid for the rays in the grid)."""
        return self._bufs["alpha"], self._bufs["theta"]

    @property
    def ray_vals(self) -> Any:
        return self._bufs["ray_vals"]

    @property
    def outside_index(self) -> Any:
        return self._bufs["outside_idx"]

    def release(self) -> None:
        self._n_hosts.clear()
        self._bufs.release()

"""Camera perspective grid: image tiles x depth slabs, rebuilt per frame for primary rays
(Patidar & Narayanan, ICVGIP 2008; Guntury & Narayanan, EGPGV 2010 / thesis 2011, Ch. 3).

The camera is taken from the rays themselves (`fit_camera` on the host, the kernel cg_fit on the
device for frames: no wait): the four corner pixel rays of a pinhole image fix the linear map M
with direction(x, y) ~ M (x, y, 1), so the grid needs no camera object and any ray batch that is
not such an image is recognised (its grid stays empty and every ray is "outside"). Per frame on
the OpenCL device (kernels: camgrid_build.cl beside this file, layout and helpers:
viewer/cl/kernels/camgrid.cl):

 1. triangles (one work-item each, in double): back-face culling where enabled; the triangle
    clipped to the frustum grown by `margin` pixels (frustum culling, including large triangles
    with no vertex inside it); the clipped polygon's pixel rectangle gives its tiles, its depth
    range (rounded outwards to float32) its slabs. A polygon that reaches the eye could cover
    any pixel and is listed in every tile ("near_eye").
 2. slabs: placed on the device at quantiles of the visible triangles' nearest depths (a
    strided sample of 2,048 sorted in one work-group; the bounds in a small double buffer), so
    each slab holds about as many triangles: a perspective grid's uniform-in-log slabs
    put a 1e-3 object before a 1e4 wall into one slab; then one pair per (tile, slab) cell the
    triangle overlaps -- not the 4-cell assumption of the 2008 paper.
 3. (cell, triangle) pairs counted, scanned, written, radix-sorted by cell (viewer.cl.primitives);
    cell ranges from the segments.
 4. rays: primary rays are already in image order, so no sort is needed: each ray is checked to
    start at the eye and to pass within margin / 2 pixels of its own tile (else it is "outside":
    compacted into a list the caller traces another way).

Indirect mapping: tiles are k x N pixels (N = work-group side, 8): k > 1 gives k^2 times fewer
tiles and fewer pairs (cheaper sort) at the price of more triangles per tile (more tests per ray);
the trace still uses N x N work-groups, k x k of them per tile.

Layouts: header CGRID_DTYPE (224 bytes: float64 eye, M^-1 rows, screen (W, H, margin, 0), norms
(|rows of M^-1|, 0); int32 tiles (T, tiles x, tiles y, slabs), cells (tiles * (slabs + 1), W, H, flags));
rect float32 (triangles, 4): each triangle's pixel rectangle x0, x1, y0, y1 (grown by the margin
and the float test's reach; rays from the eye outside it cannot meet it); slab bounds float64
(slabs + 1,): slab s holds depths [bounds[s], bounds[s + 1]), slab 0 also
nearer ones, the last farther ones; cells uint32 (ncells, 2) (first ref, count), cell id
(ty * tiles_x + tx) * (slabs + 1) + c, c = 0: the tile's big list (triangles reaching more than
two slabs: tested once, before the slabs), c = s + 1: slab s; keys uint32 (pairs,) the sorted
cell ids of refs; refs uint32 (pairs,) triangle slots; outside_index uint32.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer.cl import io as clio
from viewer.cl.limits import pair_cap
from viewer.cl.pool import BufferPool

KERNEL = Path(__file__).resolve().parent / "camgrid_build.cl"
WG = 64
N = 8  # work-group side in pixels (CN of the trace kernel)
MAX_PAIRS = 2**26
PAIR_BYTES = 28  # keys, refs, radix scratch (8), segments (12)
BOUNDS_WG = 256  # camgrid_build.cl's cg_slab_bounds work-group

CGRID_DTYPE = np.dtype([("eye", "<f8", 4), ("minv", "<f8", (3, 4)), ("screen", "<f8", 4), ("norms", "<f8", 4),
                        ("tiles", "<i4", 4), ("cells", "<i4", 4)])
assert CGRID_DTYPE.itemsize == 224

FLAG_BACK, FLAG_FRUSTUM, FLAG_NEAR_EYE = 1, 2, 4  # per-triangle flags (camgrid_build.cl CG_*)
FLAG_VALID = 2  # header cells.w: a camera fits the rays (CG_VALID)


@dataclass
class CameraGridSpec:
    k: int = 1  # indirect mapping: tiles of k * N pixels
    slabs: int = 16
    margin: float = 0.01  # pixels the triangles' rectangles are grown by
    backface: bool = False  # cull back faces (only exact for closed, outward-facing geometry)


@dataclass
class CameraGridStats:
    tiles: tuple[int, int]
    slabs: int
    triangles: int
    pairs: int
    culled_frustum: int
    culled_backface: int
    near_eye: int
    rays: int
    outside: int
    build_ms: float
    classify_ms: float = 0.0
    overflow: bool = False

    def as_dict(self) -> dict[str, float]:
        return {"pairs": float(self.pairs), "tiles": float(self.tiles[0] * self.tiles[1]),
                "culled": float(self.culled_frustum + self.culled_backface),
                "culled_frustum": float(self.culled_frustum), "culled_backface": float(self.culled_backface),
                "near_eye": float(self.near_eye), "outside_rays": float(self.outside),
                "grid_build_ms": self.build_ms, "rearrange_ms": self.classify_ms}


@dataclass
class PinholeCamera:
    """What the rays say about the camera: eye (float64 (3,), the rays' exact float32 origin) and
    M (3, 3): the direction through pixel point (x, y) is parallel to M @ (x, y, 1)."""

    eye: np.ndarray
    m: np.ndarray
    size: tuple[int, int]

    def project(self, points: np.ndarray) -> np.ndarray:
        """(k, 3) pixel x, pixel y, depth of world points (float64)."""
        q = (np.asarray(points, np.float64) - self.eye) @ np.linalg.inv(self.m).T
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], q[:, 2]], 1)


def fit_camera(corners_o: np.ndarray, corners_d: np.ndarray, size: tuple[int, int]) -> PinholeCamera | None:
    """The pinhole camera of an image of rays from its four corner rays ((4, 4) origin + tmin and
    direction + tmax rows of pixels (0, 0), (W-1, 0), (0, H-1), (W-1, H-1)), or None when they do
    not share an origin or do not span a pinhole image. The un-normalised directions s_k d_k of the
    corners form a parallelogram (the image plane is affine in the pixel coordinates), which fixes
    the scales s (s_00 = 1)."""
    w, h = size
    o, d = np.asarray(corners_o, np.float64), np.asarray(corners_d, np.float64)
    if w < 2 or h < 2 or not (np.isfinite(o).all() and np.isfinite(d[:, :3]).all()):
        return None
    if not (d[:, 3] > o[:, 3]).all() or not (o[:, :3] == o[0, :3]).all():
        return None
    d00, d10, d01, d11 = d[:, :3]
    a = np.stack([d11, -d10, -d01], 1)
    if abs(np.linalg.det(a)) < 1e-12 * np.prod(np.linalg.norm(a, axis=0)):
        return None
    s11, s10, s01 = np.linalg.solve(a, -d00)
    if min(s11, s10, s01) <= 0:
        return None
    p00, p10, p01 = d00, s10 * d10, s01 * d01
    dx, dy = (p10 - p00) / (w - 1), (p01 - p00) / (h - 1)
    c = p00 - 0.5 * dx - 0.5 * dy
    m = np.stack([dx, dy, c], 1)
    if not np.isfinite(m).all() or abs(np.linalg.det(m)) <= 1e-300:
        return None
    return PinholeCamera(o[0, :3].copy(), m, (w, h))


def corner_rays(ray_o: Any, ray_d: Any, size: tuple[int, int], ctx: Any) -> tuple[np.ndarray, np.ndarray]:
    """The (4, 4) origin and direction rows of the corner pixels (only those 8 rows are read)."""
    w, h = size
    idx = [0, w - 1, (h - 1) * w, h * w - 1]
    out = np.empty((2, 4, 4), np.float32)
    for j, buf in enumerate((ray_o, ray_d)):  # eight small copies, one wait
        for k, r in enumerate(idx):
            last = j == 1 and k == 3
            clio.copy(ctx.queue, out[j, k], buf, src_offset=16 * int(r), is_blocking=last)
    return out[0], out[1]


def closed_outward(triangles: np.ndarray) -> bool:
    """True when the triangles (float (n, 3, 3)) close volumes they face out of: every edge shared
    by exactly two triangles with opposite orientation (trimesh, vertices merged) and each connected
    piece of positive signed volume. Then, seen from outside, a back face is never the first hit,
    so back-face culling of primary rays is exact."""
    import trimesh

    tris = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    if len(tris) < 4:
        return False
    mesh = trimesh.Trimesh(**trimesh.triangles.to_kwargs(tris))
    if len(mesh.faces) != len(tris) or not (mesh.is_watertight and mesh.is_winding_consistent):
        return False
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    v = mesh.vertices[mesh.faces]
    signed = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2]))
    return bool((np.bincount(labels, weights=signed) > 0).all())


class CameraGrid:
    """Per-frame camera perspective grid on the device (buffers reused across builds)."""

    def __init__(self, ctx: Any = None, prims: Any = None):
        from viewer.cl import build, cl_context
        from viewer.cl.primitives import primitives

        self.ctx = ctx or cl_context()
        self.prims = prims or primitives(self.ctx)
        prog = build(KERNEL, {"WG": WG}, self.ctx)
        self._k = clio.kernels(prog, ("cg_fit", "cg_tri_clip", "cg_slab_bounds", "cg_tri_count", "cg_pairs_clamp",
                                          "cg_tri_write", "cg_ranges", "cg_classify"))
        self._bufs = BufferPool(self.ctx, "camera grid")
        self.header_host = np.zeros(1, CGRID_DTYPE)
        self.header = self.buf("header", CGRID_DTYPE.itemsize)
        self.stats: CameraGridStats | None = None
        self.camera: PinholeCamera | None = None
        self._late: np.ndarray | None = None  # the last pass's (pairs, culled x3), copied without a wait
        self._capacity = 0  # room for pairs (the pair buffers' size)
        self._prev_capacity = 0

    def buf(self, name: str, nbytes: int) -> Any:
        return self._bufs.get(name, nbytes)

    def _run(self, name: str, n: int, *args: Any) -> None:
        if n:
            self._k[name](self.ctx.queue, (-(-n // WG) * WG,), (WG,), *args)

    def header_for(self, cam: PinholeCamera | None, spec: CameraGridSpec, size: tuple[int, int]) -> np.ndarray:
        """The header (CGRID_DTYPE) for a w x h image; the camera fields from `cam` (valid), or
        zero for cg_fit to fill on the device (cam None)."""
        w, h = size
        t = N * max(1, int(spec.k))
        ntx, nty, ns = -(-w // t), -(-h // t), max(1, int(spec.slabs))
        hd = np.zeros(1, CGRID_DTYPE)
        flags = 0
        if cam is not None:
            hd["eye"][0, :3] = cam.eye
            hd["minv"][0, :, :3] = np.linalg.inv(cam.m)
            hd["norms"][0, :3] = np.linalg.norm(hd["minv"][0, :, :3], axis=1) * (1 + 1e-12)  # rounded up
            flags = FLAG_VALID | (1 if spec.backface else 0)
        hd["screen"][0] = (w, h, spec.margin, 0.0)
        hd["tiles"][0] = (t, ntx, nty, ns)
        hd["cells"][0] = (ntx * nty * (ns + 1), w, h, flags)
        return hd

    def build(self, tris: Any, n_tris: int, cam: PinholeCamera, spec: CameraGridSpec) -> CameraGridStats:
        """Steps 1-3 of the module docstring for a camera known on the host (studies, tests): one
        wait, so the pair buffers fit and the counters are this build's."""
        self.camera = cam
        hd = self.header_for(cam, spec, cam.size)
        self.header_host = hd  # kept alive for the asynchronous write
        clio.copy(self.ctx.queue, self.header, hd, is_blocking=False)
        return self._build(tris, n_tris, hd, wait=True)

    def build_for_rays(self, tris: Any, n_tris: int, ray_o: Any, ray_d: Any, size: tuple[int, int],
                       spec: CameraGridSpec, closed: bool, box: tuple[np.ndarray, np.ndarray]) -> CameraGridStats:
        """Steps 1-3 for the image of rays in (ray_o, ray_d), its camera fitted on the device from
        the four corner rays (cg_fit: no wait). When no pinhole camera fits them the grid is empty
        and classify_device sends every ray the other way. Back faces are culled when `closed`
        (the scene closes volumes it faces out of) and the eye lies outside `box` (decided on the
        device; spec.backface is ignored)."""
        self.camera = None
        hd = self.header_for(None, spec, size)
        self.header_host = hd
        q = self.ctx.queue
        clio.copy(q, self.header, hd, is_blocking=False)
        lo, hi = (np.append(np.asarray(v, np.float32), np.float32(0)) for v in box)
        self._k["cg_fit"](q, (1,), None, self.header, ray_o, ray_d, np.int32(size[0]), np.int32(size[1]),
                          np.int32(bool(closed)), lo, hi)
        return self._build(tris, n_tris, hd)

    def _capacity_for(self) -> int | None:
        """Room for pairs this pass: from the last pass's total (read without a wait, +25%), or
        None when there is no last pass (the first build waits for its exact total)."""
        prev = self._late
        if prev is None:
            return None
        pairs = int(prev[0])
        want = max(self._capacity, -(-pairs * 5 // 4) + 1024)
        return min(want, self.hard_cap())

    def hard_cap(self) -> int:
        """The most pairs one build may hold: MAX_PAIRS and the device's memory."""
        return min(MAX_PAIRS, pair_cap(self.ctx, PAIR_BYTES))

    def _build(self, tris: Any, n_tris: int, hd: np.ndarray, wait: bool = False) -> CameraGridStats:
        """Steps 1-3 on the header already written to the device. The pair buffers are sized from
        the last pass (no wait; an overflow leaves no grid and classify_device sends every ray the
        other way, and the next pass gets room); the first build waits for its exact total. The
        counters come from the previous pass when no wait was made (`late`). wait=True: the exact
        total, this build's counters (one wait)."""
        from viewer.cl.primitives import Chunks

        cl, q, u = self.ctx.cl, self.ctx.queue, np.uint32
        p = self.prims
        t0 = time.perf_counter()
        ntx, nty, ns = (int(x) for x in hd["tiles"][0, 1:])
        ncells = ntx * nty * (ns + 1)  # per tile: the big list and the slabs
        nt = max(n_tris, 1)
        counts, offsets, flags = self.buf("counts", 4 * nt), self.buf("offsets", 4 * nt), self.buf("flags", 4 * nt)
        place, place_slab = self.buf("place", 16 * nt), self.buf("place_slab", 8 * nt)
        zlo, zhi = self.buf("zlo", 4 * nt), self.buf("zhi", 4 * nt)
        rect = self.buf("rect", 16 * nt)
        self._run("cg_tri_clip", n_tris, self.header, tris, u(n_tris), flags, place, rect, zlo, zhi)
        bounds = self.buf("bounds", 8 * (ns + 1))  # placed on the device (no wait)
        self._k["cg_slab_bounds"](q, (BOUNDS_WG,), (BOUNDS_WG,), u(n_tris), np.int32(ns), zlo, bounds)
        self._run("cg_tri_count", n_tris, self.header, u(n_tris), flags, place, zlo, zhi, bounds, counts,
                  place_slab)
        # the pair total and the culled counts (count-only compactions), copied without a wait
        pairs_buf = self.buf("pairs", 4)
        cl.enqueue_fill_buffer(q, pairs_buf, np.uint32(0), 0, 4)
        late = np.zeros(4, np.uint32)
        if n_tris:
            p.exclusive_scan_dev(counts, offsets, self._n_buf(n_tris), n_tris, pairs_buf)
            for k, f in enumerate((FLAG_FRUSTUM, FLAG_BACK, FLAG_NEAR_EYE)):
                cb = self.buf(f"culled{k}", 4)
                p.compact_dev(self._bufs["n"], n_tris, cb, src=flags, predicate=f"x == {f}u")
                clio.copy(q, late[k + 1:k + 2], cb, is_blocking=False)
        clio.copy(q, late[0:1], pairs_buf, is_blocking=False)
        cap = None if wait else self._capacity_for()
        exact = cap is None
        if exact:  # no last pass to size from: one wait for the exact total
            clio.finish(q)
            cap = min(max(int(late[0]), 1), self.hard_cap())
        prev, self._late = self._late, late
        self._capacity = cap
        cells = self.buf("cells", 8 * ncells)
        cl.enqueue_fill_buffer(q, cells, np.uint32(0), 0, 8 * ncells)
        keys, refs = self.buf("keys", 4 * cap), self.buf("refs", 4 * cap)
        n_eff = self.buf("n_eff", 4)
        self._k["cg_pairs_clamp"](q, (1,), None, pairs_buf, u(cap), n_eff)
        self._run("cg_tri_write", n_tris, self.header, u(n_tris), pairs_buf, u(cap), offsets, counts, place,
                  place_slab, keys, refs)
        p.sort_pairs_dev(keys, refs, n_eff, cap, max(1, (ncells - 1).bit_length()))
        seg = p.segments_dev(keys, n_eff, cap, None,
                             Chunks(0, self.buf("seg_key", 4 * cap), self.buf("seg_start", 4 * cap),
                                    self.buf("seg_len", 4 * cap)), self.buf("seg_count", 4))
        self._run("cg_ranges", cap, seg.key, seg.start, seg.length, self._bufs["seg_count"], cells)
        shown = late if exact else prev  # counters: this pass's when waited for, else the last one's
        pairs, frustum, back, near = (int(x) for x in shown)
        overflow = pairs > (cap if exact else self._prev_capacity)
        self._prev_capacity = cap
        self.stats = CameraGridStats((ntx, nty), ns, n_tris, 0 if overflow else pairs, frustum, back, near, 0, 0,
                                     (time.perf_counter() - t0) * 1e3, overflow=overflow)
        return self.stats

    def _n_buf(self, n: int) -> Any:
        """A device uint32 holding n (the count the device-count primitives read)."""
        self._n_host = np.array([n], np.uint32)  # kept alive for the asynchronous write
        buf = self.buf("n", 4)
        clio.copy(self.ctx.queue, buf, self._n_host, is_blocking=False)
        return buf

    def classify(self, ray_o: Any, ray_d: Any, n: int) -> int:
        """Step 4: flag and list the rays the grid cannot trace; returns how many (a wait: tests
        and studies; frames use classify_device)."""
        t0 = time.perf_counter()
        self.classify_device(ray_o, ray_d, n)
        got = np.zeros(1, np.uint32)
        if n:
            clio.copy(self.ctx.queue, got, self.outside_count)
        self.stats.rays, self.stats.outside = n, int(got[0])
        self.stats.classify_ms = (time.perf_counter() - t0) * 1e3
        return int(got[0])

    def classify_device(self, ray_o: Any, ray_d: Any, n: int) -> None:
        """Step 4 without a wait: the outside rays listed in outside_index, their count in the
        device buffer outside_count (a trace kernel reads it)."""
        assert self.stats is not None, "build first"
        outside, idx = self.buf("outside", 4 * max(n, 1)), self.buf("outside_idx", 4 * max(n, 1))
        count = self.buf("outside_count", 4)
        self.ctx.cl.enqueue_fill_buffer(self.ctx.queue, count, np.uint32(0), 0, 4)
        self._run("cg_classify", n, self.header, ray_o, ray_d, np.uint32(n), self._bufs["pairs"],
                  np.uint32(self._capacity), outside)
        if n:
            self.prims.compact_dev(self._n_buf(n), n, count, flags=outside, dst_index=idx)
        self.stats.rays = n

    @property
    def outside_count(self) -> Any:
        return self._bufs["outside_count"]

    @property
    def cells(self) -> Any:
        return self._bufs["cells"]

    @property
    def keys(self) -> Any:
        """uint32 (pairs,) the cell id of each ref (sorted)."""
        return self._bufs["keys"]

    @property
    def rect(self) -> Any:
        """float32 (triangles, 4) pixel rectangles (x0, x1, y0, y1) by triangle slot (the layout above)."""
        return self._bufs["rect"]

    @property
    def bounds(self) -> Any:
        """float64 (slabs + 1,) slab bounds on the device (the layout above)."""
        return self._bufs["bounds"]

    def bounds_numpy(self) -> np.ndarray:
        """The slab bounds (tests and studies: a wait)."""
        out = np.empty(int(self.header_host["tiles"][0, 3]) + 1, np.float64)
        clio.copy(self.ctx.queue, out, self.bounds)
        return out

    @property
    def refs(self) -> Any:
        return self._bufs["refs"]

    @property
    def outside(self) -> Any:
        return self._bufs["outside"]

    @property
    def outside_index(self) -> Any:
        return self._bufs["outside_idx"]

    def to_numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """(cells (ncells, 2), refs (pairs,)) for tests and studies (waits; the device's pair count)."""
        assert self.stats is not None
        ncells = int(self.header_host["cells"][0, 0])
        cells = np.empty((ncells, 2), np.uint32)
        got = np.zeros(1, np.uint32)
        clio.copy(self.ctx.queue, got, self._bufs["n_eff"])
        pairs = int(got[0])
        refs = np.empty(max(pairs, 1), np.uint32)
        clio.copy(self.ctx.queue, cells, self.cells)
        if pairs:
            clio.copy(self.ctx.queue, refs, self.refs)
        return cells, refs[:pairs]

    def header_numpy(self) -> np.ndarray:
        """The header as the device holds it (the camera fitted there; tests and studies: a wait)."""
        out = np.zeros(1, CGRID_DTYPE)
        clio.copy(self.ctx.queue, out, self.header)
        return out

    def release(self) -> None:
        self._bufs.release()

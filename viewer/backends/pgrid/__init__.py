"""pgrid: per-pass grids specialised to the ray type (Guntury & Narayanan, EGPGV 2010 / thesis 2011).

* Primary rays: the camera perspective grid (viewer.accel.camgrid), rebuilt every frame: image
  tiles x depth slabs, frustum culling (triangles clipped to the frustum), back-face culling
  where it is exact (`backface=auto`: the scene is closed and faces outward, and the eye is
  outside the scene box; `on` forces it), one pair per cell a triangle overlaps, radix sort by
  cell; traced with 8 x 8 work-groups (camera.cl beside this file), k x k of them per tile
  (`k`: the indirect mapping), triangles staged in batches across slabs with the slab check. The
  camera is fitted to the rays on the device (their four corner rays; no wait); a batch of
  "primary" rays that is not a pinhole image leaves the grid empty and the uniform grid takes
  them (`primary=angular`: the eye-centred angular grid below, `primary=grid`: the uniform grid).
* Shadow rays (point light `PassInfo.light` of scene.point_lights): a spherical grid around the
  light (viewer.accel.pointgrid), rebuilt every pass: rays sorted into (tile) chunks of at most
  `chunk` rays, one work-group per chunk with the tile's triangles staged in local memory slab by
  slab, any-hit early exit (trace.cl beside this file); slabs from the light outwards, or from the
  surface end when the light is outside the scene box (`order=auto`).
* Both point grids: a ray is tested only against the staged triangles whose angular box holds
  its own direction (the binning test at full resolution: 2.7-3.4 instead of 20.6 triangle tests
  per ray on the mixed scene); closest-hit tiles are staged straight through their slabs, and a
  ray stops at the first staged block whose distance bound lies beyond its hit.
* Soft shadows, AO, diffuse and reflection rays, and any ray a grid cannot take (checked per ray,
  in double): the uniform grid of ugrid (viewer.accel.grid, built once per scene geometry when a
  pass first needs it: primary and shadow passes build it only for rays their grids decline), so
  every ray is traced exactly. Soft-shadow rays end at different points of an area light, so
  they take this way. It is the two-level grid by default (levels=2: dense cells get sub-grids,
  as ugrid's), so rays reaching a small detailed object in a big scene do not test all of its
  triangles in one cell (reflection rays of bench-grids' mixed scene: 8.8 s -> 37 ms).

Parameters: primary (image | angular | grid), k (indirect mapping), backface (auto | on | off),
order (any-hit slab order: auto | light | surface), chunk (rays per work-group: 16..256),
balance (chunks; off: one work-group per tile), tile_rays / tiles / tile_deg (angular tiling),
slabs (both grids), margin (radians, the angular grids), density / resolution / rebuild (the
uniform grid; rebuild: every frame). Counters: pairs, chunks, chunk_occupancy, culled (frustum /
back-face), near-eye and widened (pole/seam) triangles, rays outside the grids, inactive rays,
tests per active ray (with the overlays on).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viewer.accel.camgrid import CameraGrid, CameraGridSpec, closed_outward
from viewer.accel.camgrid import N as CAMERA_N
from viewer.accel.grid import GridSpec, scene_box
from viewer.accel.pointgrid import PointGrid, PointGridSpec
from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.cl_geometry import GeometryBackend
from viewer.backends.interface import BackendInfo, OverlaySpec, param
from viewer.backends.ugrid import GridTracer, top_density
from viewer.cl import io as clio
from viewer.effects import RayType
from viewer.errors import RtwalkError
from viewer.rays import HitBuffer, PassInfo, RayBatch

KERNEL = Path(__file__).resolve().parent / "trace.cl"
CAMERA_KERNEL = Path(__file__).resolve().parent / "camera.cl"
SAMPLE = 4096  # rays sampled (strided) to choose the spherical frame


@dataclass
class PgridParams:
    chunk: int = param(64, "rays per chunk = work-group size")
    tile_rays: int = param(32, "automatic tiling: ~rays per angular tile (32: fewer triangles per tile than 64)")
    tiles: int = param(0, ">0: tiles along the longer side of the angular rectangle")
    tile_deg: float = param(0.0, ">0: light tiles of this many degrees (fixed angular resolution)")
    slabs: int = param(16, "distance slabs per tile")
    margin: float = param(0.004, "angular margin (radians) a ray may deviate from its tile direction")
    primary: str = param("image", "image: camera perspective grid; angular: eye-centred grid; grid: uniform grid")
    k: int = param(1, "camera grid: indirect mapping (tiles of k x 8 pixels)")
    backface: str = param("auto", "camera grid: auto (where exact), on, off")
    order: str = param("auto", "light grid slab order for any hit: light (outward), surface (inward), auto")
    balance: bool = param(True, "cut tiles into chunks of `chunk` rays (False: one work-group per tile)")
    rebuild: bool = param(False, "rebuild the uniform grid every frame (animated scenes; timing studies)")
    density: float = param(0.0, "uniform grid (other ray types): ~cells per triangle (0: ugrid's default for the "
                           "levels)")
    resolution: int = param(0, "uniform grid: cells on the longest axis (0 = from density)")
    levels: int = param(2, "uniform grid: 2: dense cells get sub-grids (ugrid's two-level grid, viewer.accel.grid2: a "
                        "small detailed object in a big scene is not one cell of thousands of triangles); 1: one level")

    def validate(self, source: str) -> None:
        if self.chunk not in (16, 32, 64, 128, 256):
            raise RtwalkError(f"{source}: chunk must be one of 16, 32, 64, 128, 256 (got {self.chunk})")
        if not 1 <= self.tile_rays <= 1 << 20 or not 0 <= self.tiles <= 1024:
            raise RtwalkError(f"{source}: tile_rays must be in 1..1048576 and tiles in 0..1024")
        if not 0 <= self.tile_deg <= 90:
            raise RtwalkError(f"{source}: tile_deg must be in 0..90 degrees (got {self.tile_deg})")
        if not 1 <= self.slabs <= 256:
            raise RtwalkError(f"{source}: slabs must be in 1..256 (got {self.slabs})")
        if not 1e-5 <= self.margin <= 0.1:
            raise RtwalkError(f"{source}: margin must be in 1e-5..0.1 radians (got {self.margin})")
        if self.primary not in ("image", "angular", "grid"):
            raise RtwalkError(f"{source}: primary must be image, angular or grid (got {self.primary})")
        if self.order not in ("auto", "light", "surface"):
            raise RtwalkError(f"{source}: order must be auto, light or surface (got {self.order})")
        if self.backface not in ("auto", "on", "off"):
            raise RtwalkError(f"{source}: backface must be auto, on or off (got {self.backface})")
        if not 1 <= self.k <= 16:
            raise RtwalkError(f"{source}: k must be in 1..16 (got {self.k})")
        if not self.density >= 0 or not 0 <= self.resolution <= 2048:
            raise RtwalkError(f"{source}: density must be >= 0 (0: automatic) and resolution in 0..2048")
        if self.levels not in (1, 2):
            raise RtwalkError(f"{source}: levels must be 1 or 2 (got {self.levels})")

    def point_spec(self) -> PointGridSpec:
        return PointGridSpec(chunk=self.chunk, tile_rays=self.tile_rays, tiles=self.tiles,
                             tile_angle=float(np.radians(self.tile_deg)), slabs=self.slabs,
                             margin=self.margin)


class PgridBackend(GeometryBackend):
    info = BackendInfo(
        "pgrid", "OpenCL: per-pass point-centred grids (light / eye) with rays sorted into chunks; uniform grid for "
        "the other rays", params=PgridParams,
        overlays=(OverlaySpec("triangle_tests", "heat", "triangle_tests", "triangles tested per ray"),
                  OverlaySpec("light_tiles", "ids", "light_chunks", "chunks (colours) and rays per tile",
                              counts="tile_rays")),
        counters=("rays", "pairs", "chunks", "chunk_occupancy", "culled", "culled_frustum", "culled_backface",
                  "near_eye", "widened", "outside_rays", "inactive_rays", "tests_per_ray", "grid_build_ms",
                  "rearrange_ms"),
        device="cl")

    def __init__(self, bc: BackendContext, params: PgridParams | None = None):
        from viewer.cl import PassStages, build

        self._start(bc, params)
        if self.params.levels == 2:
            from viewer.accel.grid2 import TwoLevelGrid

            self.grid.release()
            self.grid = TwoLevelGrid(self.ctx)
        self.tracer = GridTracer(self.ctx, self.grid)
        self.pgrid = PointGrid(self.ctx, self.grid.prims)
        self.camgrid = CameraGrid(self.ctx, self.grid.prims)
        self._kernels, self._camera_kernels = {}, {}
        for count in (False, True):
            extra = {"COUNT_TESTS": None} if count else {}
            prog = build(KERNEL, {"WG": self.params.chunk, **extra}, self.ctx)
            self._kernels[count] = clio.kernel(prog, "pg_trace")
            prog = build(CAMERA_KERNEL, {"CN": CAMERA_N, **extra}, self.ctx)
            self._camera_kernels[count] = clio.kernel(prog, "cg_trace")
        self._closed: tuple[tuple[int, int], bool] | None = None
        self._cam_outside: np.ndarray | None = None  # the last primary pass's outside count (read late)
        self._grid_fresh = False
        self._box = (np.zeros(3), np.ones(3))
        self.stages = PassStages(self.ctx, extras=1)  # + triangle tests per ray
        self._rebuild()

    # -- geometry (viewer.backends.cl_geometry) --------------------------------------------
    def _rebuild(self) -> None:
        """The moved triangles to the device; the uniform grid is rebuilt when a pass needs it."""
        with self.bc.profiler.cl_phase("pgrid:triangles", self.ctx.queue):
            tris = self._upload_triangles("pgrid triangles")
            self._box = scene_box(tris)
            self._n_tris = len(tris)
        self._grid_fresh = False

    def _ensure_grid(self) -> None:
        """Build the uniform grid (rays without a preferred direction, rays a per-pass grid cannot
        take) for the current triangles, once per geometry: passes that do not use it never pay."""
        if self._grid_fresh:
            return
        with self.bc.profiler.cl_phase("pgrid:ugrid_build", self.ctx.queue):
            self.grid.build(self._tris, self._n_tris, *self._box,
                            GridSpec(density=top_density(self.params.density, self.params.levels),
                                     resolution=self.params.resolution))
        self._grid_fresh = True

    # -- tracing --------------------------------------------------------------------------
    def _centre(self, pinfo: PassInfo, rs) -> np.ndarray | None:
        """The centre of a point-grid pass (float64 (3,)), else None. A shadow pass's is its light
        (no read); an angular primary pass's is the eye, the origin of its first active ray in a
        strided sample (one wait: `primary=angular` only)."""
        rt = pinfo.ray_type
        lights = getattr(self.bc.scene, "point_lights", [])
        if rt == RayType.SHADOW and 0 <= pinfo.light < len(lights):
            return np.asarray(lights[pinfo.light].position, np.float64)
        if rt != RayType.PRIMARY or self.params.primary == "grid":
            return None
        step = max(1, rs.n // SAMPLE)
        count = -(-rs.n // step)  # rows 0, step, ... (as o[::step]); only these cross
        so = clio.read_strided(self.ctx.queue, rs.origin, step, count, (4,), np.float32, is_blocking=False)
        sd = clio.read_strided(self.ctx.queue, rs.dir, step, count, (4,), np.float32)  # one wait for both
        act = np.flatnonzero(sd[:, 3] > so[:, 3])
        if len(act) == 0:
            return None
        return so[act[0], :3].astype(np.float64)  # the eye: every primary ray starts there

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        rs, hs, tests = self.stages.get(rays.size)
        with self.bc.profiler.cl_phase("pgrid:upload", self.ctx.queue):
            rs.upload(rays)
        return self._trace(rs, hs, tests, pinfo, rays.size, hits)

    def trace_device(self, rays, pinfo: PassInfo, hits) -> TraceResult:
        """Trace CL ray buffers (viewer.cl.RayStage layout) into CL hit buffers (HitStage): only the
        rays of an angular primary pass cross (a strided sample to find the eye)."""
        return self._trace(rays, hits, None, pinfo, rays.size, None)

    def _trace(self, rs, hs, tests, pinfo: PassInfo, size: tuple[int, int], hits: HitBuffer | None) -> TraceResult:
        """One pass on CL buffers; `hits` (a RayBatch frame) gets the hits written back."""
        prof = self.bc.profiler
        q = self.ctx.queue
        count = bool(self.overlays_enabled) and tests is not None
        label = pinfo.ray_type.label
        rays_size = size
        stats: dict[str, float] = {"rays": float(rs.n)}
        cam = self._camera(pinfo, rs, rays_size) if rs.n else False
        point = self._centre(pinfo, rs) if rs.n and not cam else None
        if cam:
            self._trace_camera(rs, hs, tests if count else None, rays_size, stats, label)
        elif point is None:
            self._ensure_grid()
            with prof.cl_phase(f"trace:{label}", q):
                self.tracer.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit,
                                    tests if count else None)
        else:
            centre = point
            pg = self.pgrid
            spec = self.params.point_spec()
            # primary rays meet in the eye: back faces are culled where that is exact (as the camera grid)
            spec.backface = pinfo.ray_type == RayType.PRIMARY and self._backface(centre)
            key = (label, int(pinfo.light))  # buffers sized from this light's (ray type's) last pass
            with prof.cl_phase(f"pgrid:build:{label}", q):
                pg.place(self._tris, self._n_tris, *self._box, rs.origin, rs.dir, rs.n, centre, spec, key)
            with prof.cl_phase(f"pgrid:rearrange:{label}", q):
                st = pg.rearrange(rs.n, spec, balance=self.params.balance)
            self._ensure_grid()  # once per geometry: the rays outside the grid (a count only the device knows)
            with prof.cl_phase(f"trace:{label}", q):
                # inactive rays are in no chunk and outside no grid: their answer is a miss (and no test)
                self.ctx.cl.enqueue_fill_buffer(q, hs.t, np.float32(np.inf), 0, 4 * rs.n)
                self.ctx.cl.enqueue_fill_buffer(q, hs.tri, np.int32(-1), 0, 4 * rs.n)
                if count:
                    self.ctx.cl.enqueue_fill_buffer(q, tests, np.int32(0), 0, 4 * rs.n)
                ch, wg = pg.chunks, self.params.chunk
                self._kernels[count](q, (pg.launch_groups * wg,), (wg,), pg.header, ch.key, ch.start, ch.length,
                                     pg.ray_vals, pg.cell_start, pg.refs, self._tris, rs.origin, rs.dir, hs.t,
                                     hs.tri, np.int32(pinfo.any_hit), tests, np.int32(self._from_far(centre)),
                                     pg.keys, pg.levels, *pg.ray_angles, pg.tri_box, pg.chunk_count)
                self.tracer.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, pinfo.any_hit,
                                    tests if count else None, index=pg.outside_index, n_device=pg.outside_counter)
            stats.update(st.as_dict(self.params.chunk))
            # the same per ray type (the renderer sums a frame's passes)
            stats.update({f"{k}_{label}": v for k, v in st.as_dict(self.params.chunk).items()})
        if hits is not None:
            with prof.cl_phase("pgrid:download", q):
                hs.download(hits)
        overlays = {}
        if count:
            from viewer.cl import mapped

            with mapped(self.ctx, tests, (rs.n,), np.int32) as a:
                stats["tests_per_ray"] = float(a.sum()) / max(rs.active_count(), 1)  # per active ray
                overlays["triangle_tests"] = self.textures.write("triangle_tests", rays_size, a)
            if point is not None and not cam:
                chunk_of, tile_rays = self._chunk_maps(rs.n)
                overlays["light_chunks"] = self.textures.write("light_chunks", rays_size, chunk_of)
                overlays["tile_rays"] = self.textures.write("tile_rays", rays_size, tile_rays)
        return TraceResult(stats=stats, overlays=overlays)

    def _from_far(self, centre: np.ndarray) -> bool:
        """Any-hit slab order: from the surface end when the light is outside the scene box (the
        slabs near such a light hold the scene's outer layer: roofs, the lit side), else from the
        light (a light inside a room or a lamp is often occluded next to itself)."""
        if self.params.order != "auto":
            return self.params.order == "surface"
        lo, hi = self._box
        return bool(np.any(centre < lo) or np.any(centre > hi))

    def _camera(self, pinfo: PassInfo, rs, size: tuple[int, int]) -> bool:
        """Whether a primary pass goes through the camera grid: its rays fill an image (the camera
        itself is fitted on the device from the corner rays; when none fits, every ray takes the
        uniform grid)."""
        return pinfo.ray_type == RayType.PRIMARY and self.params.primary == "image" and rs.n == size[0] * size[1]

    def _backface(self, eye: np.ndarray) -> bool:
        """Back-face culling for rays from `eye`: exact only when every surface closes a volume it
        faces out of and the eye is outside them (checked: outside the scene box)."""
        mode = self.params.backface
        if mode != "auto":
            return mode == "on"
        lo, hi = self._box
        return self._is_closed() and bool(np.any(eye < lo) or np.any(eye > hi))

    def _is_closed(self) -> bool:
        """The scene closes volumes it faces out of (trimesh; cached per geometry)."""
        key = self._geometry_key()
        if self._closed is None or self._closed[0] != key:
            self._closed = (key, closed_outward(np.asarray(self.bc.scene.triangles, np.float32).reshape(-1, 3, 3)))
        return self._closed[1]

    def _trace_camera(self, rs, hs, tests, size: tuple[int, int], stats: dict[str, float], label: str) -> None:
        """Primary rays through the camera perspective grid (camera fitted on the device, pair
        buffers sized from the last pass: no wait after the first); rays it cannot take through the
        uniform grid."""
        prof, q, cg = self.bc.profiler, self.ctx.queue, self.camgrid
        mode = self.params.backface
        closed = mode == "on" or (mode == "auto" and self._is_closed())
        box = self._box if mode == "auto" else (np.full(3, np.inf), np.full(3, -np.inf))  # on: always outside
        spec = CameraGridSpec(k=self.params.k, slabs=self.params.slabs)
        with prof.cl_phase(f"pgrid:build:{label}", q):
            st = cg.build_for_rays(self._tris, self._n_tris, rs.origin, rs.dir, size, spec, closed, box)
        with prof.cl_phase(f"pgrid:rearrange:{label}", q):
            cg.classify_device(rs.origin, rs.dir, rs.n)  # the outside rays' list and count stay on the device
        self._ensure_grid()  # once per geometry: the outside rays (a count only the device knows)
        with prof.cl_phase(f"trace:{label}", q):
            w, h = size
            gsize = (-(-w // CAMERA_N) * CAMERA_N, -(-h // CAMERA_N) * CAMERA_N)
            dummy = tests if tests is not None else hs.t
            self._camera_kernels[tests is not None](q, gsize, (CAMERA_N, CAMERA_N), cg.header, cg.cells, cg.refs,
                                                    cg.keys, self._tris, rs.origin, rs.dir, cg.outside, hs.t,
                                                    hs.tri, dummy, cg.bounds, cg.rect)
            self.tracer.enqueue(rs.origin, rs.dir, hs.t, hs.tri, rs.n, False, tests, index=cg.outside_index,
                                n_device=cg.outside_count)
            # statistics only: the count is read without a wait and reported by the next frame
            prev, self._cam_outside = self._cam_outside, np.zeros(1, np.uint32)
            clio.copy(q, self._cam_outside, cg.outside_count, is_blocking=False)
            st.outside = int(prev[0]) if prev is not None else 0
        d = st.as_dict()
        stats.update(d)
        stats.update({f"{k}_{label}": v for k, v in d.items()})

    def _chunk_maps(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Per ray: its chunk (-1 outside the grid) and the rays of its tile (0 outside)."""
        import dataclasses

        pg = self.pgrid
        got = np.zeros(1, np.uint32)
        clio.copy(self.ctx.queue, got, pg.chunk_count)  # this pass's (the stats may be the last pass's)
        key, start, length = dataclasses.replace(pg.chunks, count=int(got[0])).to_numpy(self.ctx)
        vals = np.empty(n, np.uint32)
        clio.copy(self.ctx.queue, vals, pg.ray_vals)
        res = pg.header_numpy()["res"][0]
        ntiles = int(res[0]) * int(res[1])
        inside = key < ntiles
        chunk_of = np.full(n, -1, np.int32)
        tile_rays = np.zeros(n, np.int32)
        ch = np.repeat(np.arange(len(key)), length.astype(np.int64))
        pos = vals[: len(ch)]
        keep = inside[ch]
        chunk_of[pos[keep]] = ch[keep]
        per_tile = np.bincount(key[inside].astype(np.int64), weights=length[inside], minlength=ntiles)
        tile_rays[pos[keep]] = per_tile[key[ch[keep]].astype(np.int64)].astype(np.int32)
        return chunk_of, tile_rays

    def release(self) -> None:
        self.pgrid.release()
        self.camgrid.release()
        self._release_own()

"""Grid study: far-from-origin and mixed-scale scenes (issue 18), grids against clbvh.

Scenes (`--scene`):
  dragon        the shared 100k-triangle dragon (../shared/scenes) moved by `--offset` along
                (1, 1, 1): the grids' float32 coordinates there are coarse against the cells
  mixed         a 1e-3-tall detailed mesh (the shared bunny, else an icosphere) standing on a
                2e4-wide ground with a 1e4-tall wall behind it (the teapot-in-a-stadium case)
Primary rays of a pinhole camera framing the small object (`--size`, default 320x180) are traced
by each backend (`--backends`) through Backend.trace (upload, kernel, download) once untimed
(kernel compilation), then in interleaved rounds; reported per backend: the grid's triangle-cell
pairs, its device buffer bytes, the median trace ms, its ratio to clbvh's, and hits that disagree
with clbvh (ties at the same distance excepted). `--rays reflect` traces, instead, those primary
rays mirrored off their first hits (found by clbvh; float32 hit point, tmin 1e-4 of the primary
hit distance; rays that missed stay inactive) as reflection rays (voxelwalk's EC by default).
Peak RSS: one backend per process under /usr/bin/time -v. `--build-only`: the uniform grid alone
(pairs, MiB, RSS), no tracing.

  rtwalk bench-grids --scene dragon --offset 1e6 --backends clbvh,ugrid,pgrid,voxelwalk
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from viewer.bench.partial import keep_partial
from viewer.errors import RtwalkError

HELP = "grids against clbvh far from the origin (--offset) and on a mixed-scale scene: pairs, MiB, trace ms"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="dragon", choices=("dragon", "mixed"),
                   help="dragon: the shared 100k dragon moved by --offset; mixed: a 1e-3 object on a 2e4 ground")
    p.add_argument("--offset", type=float, default=0.0, help="dragon: translation along (1,1,1) (default 0)")
    p.add_argument("--size", default="320x180", help="WxH of the primary rays (default 320x180)")
    p.add_argument("--backends", default="clbvh,ugrid,pgrid,voxelwalk",
                   help="comma list of registered backends to trace (clbvh is the reference for ratios); "
                        "NAME:k=v+k=v traces NAME with those parameters (its --backend-params, '+' for ','), "
                        "e.g. ugrid:levels=1 or voxelwalk:primary=ec")
    p.add_argument("--rays", default="primary", choices=("primary", "reflect"),
                   help="primary: the pinhole rays; reflect: them mirrored off their first hits (clbvh's), "
                        "traced as reflection rays")
    p.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds (default 3)")
    p.add_argument("--scene-dir", default="", help="folder of the shared scenes (default ../shared/scenes)")
    p.add_argument("--json", default="", help="write the rows (with --build-only: the grid's figures) to this "
                                               "file; an existing file is refused without --force")
    p.add_argument("--build-only", action="store_true",
                   help="only build the uniform grid (ugrid's GridSpec) and report its pairs and MiB")


SCENE_DIR: list[str] = [""]


def _mesh(name: str) -> np.ndarray:
    from viewer.paths import SHARED_SCENES
    from viewer.scene_io import load_scene

    path = Path(SCENE_DIR[0] or SHARED_SCENES) / name
    return np.asarray(load_scene(str(path), progress=False).triangles, np.float64).reshape(-1, 3, 3)


def _icosphere() -> np.ndarray:
    from viewer.procedural import _icosphere as ico

    return np.asarray(ico(6, 1.0, (0.0, 0.0, 0.0)), np.float64).reshape(-1, 3, 3)


def scene_dragon(offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(triangles float32, camera position, look-at point), float64 points."""
    tris = _mesh("dragon/dragon_100k.ply")
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    tris = tris - (lo + hi) / 2 + offset
    size = float((hi - lo).max())
    target = np.full(3, offset)
    eye = target + size * np.array([0.2, 0.25, 0.9])
    return tris.astype(np.float32), eye, target


def scene_mixed() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 1e-3-tall object on a 2e4 ground (y = 0) in front of a 1e4-tall wall."""
    try:
        obj = _mesh("bunny/bun_zipper.ply")
    except (RtwalkError, OSError):  # no shared scenes: a procedural sphere
        obj = _icosphere()
    lo, hi = obj.reshape(-1, 3).min(0), obj.reshape(-1, 3).max(0)
    s = 1e-3 / float(hi[1] - lo[1])
    obj = (obj - [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]) * s
    g, w = 1e4, 1e4
    ground = np.array([[[-g, 0, -g], [g, 0, -g], [g, 0, g]], [[-g, 0, -g], [g, 0, g], [-g, 0, g]]])
    wall = np.array([[[-g, 0, -w / 2], [g, 0, -w / 2], [g, w, -w / 2]], [[-g, 0, -w / 2], [g, w, -w / 2],
                                                                         [-g, w, -w / 2]]])
    tris = np.concatenate([obj, ground, wall]).astype(np.float32)
    target = np.array([0.0, 0.5e-3, 0.0])
    eye = np.array([0.4e-3, 1.2e-3, 2.5e-3])
    return tris, eye, target


def primary_rays(eye: np.ndarray, target: np.ndarray, size: tuple[int, int], fov_deg: float = 45.0):
    """Pinhole rays (origins, unit directions) float32, row-major pixels."""
    w, h = size
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    k = np.tan(np.radians(fov_deg) / 2)
    x = (2 * (np.arange(w) + 0.5) / w - 1) * k * w / h
    y = (1 - 2 * (np.arange(h) + 0.5) / h) * k
    X, Y = np.meshgrid(x, y)
    d = f + X[..., None] * r + Y[..., None] * u
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d = d.reshape(-1, 3).astype(np.float32)
    o = np.broadcast_to(eye.astype(np.float32), d.shape).copy()
    return o, d


class Runner:
    """One backend over the scene, tracing the same rays again and again."""

    def __init__(self, name: str, tris: np.ndarray, o: np.ndarray, d: np.ndarray, tmin: np.ndarray | None = None,
                 ray_type: Any = None, image: tuple[int, int] | None = None):
        """`name`: a backend, or "backend:key=value+key=value" (its --backend-params, '+' for ',').
        `tmin`: per ray (default 0; NaN: an inactive ray); `ray_type`: the pass's (default primary);
        `image`: (w, h) when the rays are a pinhole image's pixels, row-major: the batch then has the
        image's shape, as the renderer's primary pass has (pgrid's camera grid needs it)."""
        from viewer.accel.bvh import build_bvh
        from viewer.backends import create_backend
        from viewer.backends.base import BackendContext
        from viewer.effects import RayType
        from viewer.gl.context import shared_context
        from viewer.gl.programs import ProgramCache
        from viewer.gl.scene import GpuScene
        from viewer.profiler import GpuProfiler
        from viewer.rays import HitBuffer, PassInfo, RayBatch
        from viewer.scene import Material, Scene
        from viewer.tracing import ROW

        ctx = shared_context()
        self.bvh = build_bvh(tris)
        scene = Scene("rays", tris, np.zeros(len(tris), np.int32),
                      [Material("grey", np.full(3, 0.7, np.float32))]).reordered(self.bvh.tri_order)
        self.gpu = GpuScene.upload(ctx, scene, self.bvh)
        n = len(o)
        width, height = image if image is not None and image[0] * image[1] == n else (min(n, ROW), -(-n // ROW))
        pad = width * height
        org = np.zeros((pad, 4), np.float32)
        dirs = np.zeros((pad, 4), np.float32)
        dirs[:, 2], dirs[:, 3] = 1.0, -1.0
        org[:n, :3], dirs[:n, :3] = o, d
        dirs[:n, 3] = 3.4e38
        if tmin is not None:
            dead = np.isnan(tmin)
            org[:n, 3] = np.where(dead, 0.0, tmin)
            dirs[:n, 3][dead] = -1.0
        self.rays, self.hits = RayBatch(ctx, (width, height)), HitBuffer(ctx, (width, height))
        self.rays.origin.write(org.tobytes())
        self.rays.direction.write(dirs.tobytes())
        self.n = n
        bc = BackendContext(ctx, ProgramCache(ctx), GpuProfiler(ctx, enabled=False), self.gpu, scene, self.bvh)
        t0 = time.perf_counter()
        backend, _, params = name.partition(":")
        self.be = create_backend(backend, bc, params.replace("+", ",") or None)
        self.be.begin_frame(0)
        self.build_ms = (time.perf_counter() - t0) * 1e3
        self.pinfo = PassInfo(ray_type if ray_type is not None else RayType.PRIMARY)
        # untimed: kernels compile at first enqueue; `stats`: the last trace's counters
        self.stats = self.be.trace(self.rays, self.pinfo, self.hits).stats

    def trace(self) -> tuple[float, np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        self.stats = self.be.trace(self.rays, self.pinfo, self.hits).stats
        t, slot = self.hits.read()
        ms = (time.perf_counter() - t0) * 1e3
        end = getattr(self.be, "end_frame", None)  # counters kept on the device (after the read: no wait)
        if callable(end):
            self.stats = {**self.stats, **{k: self.stats.get(k, 0) + v for k, v in end().items()}}
        slot = np.asarray(slot[: self.n])
        ids = np.where(slot >= 0, self.bvh.tri_order[np.maximum(slot, 0)], -1)
        return ms, ids, np.asarray(t[: self.n])

    def grid_figures(self) -> dict[str, Any]:
        g = getattr(self.be, "grid", None)
        if g is None or getattr(g, "stats", None) is None:
            return {}
        out = {k: v for k, v in g.stats.as_dict().items()}
        out["grid_res"] = list(g.stats.res)
        pool = getattr(g, "_bufs", None)
        if pool is not None:
            out["grid_bytes"] = int(sum(b.size for b in pool.bufs.values()))
        return out

    def release(self) -> None:
        self.be.release()
        self.rays.release()
        self.hits.release()
        self.gpu.release()


def reflect_rays(tris: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays (o, d) mirrored off their first hits (clbvh's): float32 hit points, directions
    mirrored about the hit triangle's plane, tmin 1e-4 of the hit distance (the hit point's
    rounding is relative to it); a ray that missed gets tmin NaN (inactive)."""
    ref = Runner("clbvh", tris, o, d)
    _, ids, t = ref.trace()
    ref.release()
    hit = ids >= 0
    tv = np.where(hit, t, 0.0).astype(np.float64)
    p = (o.astype(np.float64) + tv[:, None] * d).astype(np.float32)
    v = tris[np.maximum(ids, 0)].astype(np.float64)
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    dd = d.astype(np.float64)
    r = dd - 2.0 * (dd * nrm).sum(1, keepdims=True) * nrm
    r = np.where(hit[:, None], r, dd).astype(np.float32)
    tmin = np.where(hit, 1e-4 * tv, np.nan).astype(np.float32)
    return p, r, tmin


def build_only(args, tris: np.ndarray) -> int:
    """The uniform grid alone (the one ugrid, pgrid and voxelwalk build): pairs, MiB, RSS."""
    from viewer.accel.grid import GridSpec, UniformGrid, scene_box, triangles_f4
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    buf = clio.upload(ctx, triangles_f4(tris), what="bench triangles")
    grid = UniformGrid(ctx)
    st = grid.build(buf, len(tris), *scene_box(tris), GridSpec())
    mib = sum(b.size for b in grid._bufs.bufs.values()) / 2**20
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"scene {args.scene} offset {args.offset:g}: res {st.res} pairs {st.pairs:,} grid buffers {mib:.1f} MiB "
          f"build {st.build_ms:.0f} ms peak RSS {rss:.0f} MiB")
    grid.release()
    buf.release()
    _write_json(args.json, {"complete": True, "scene": args.scene, "offset": args.offset, "build_only": {
        "grid_res": [int(v) for v in st.res], "grid_pairs": int(st.pairs), "grid_mib": mib,
        "build_ms": float(st.build_ms), "peak_rss_mib": rss}})
    return 0


MAX_OFFSET = 1e30  # float32 coordinates stay finite (and their squares in float64) well past this


def check_args(args) -> None:
    """What needs no scene, before the scene is made: the offset, the rounds and the --json file
    (refused when it exists unless --force, or when it cannot be written)."""
    from viewer.cli_args import check_at_least, check_output_dir, check_report_free

    if not (math.isfinite(args.offset) and abs(args.offset) <= MAX_OFFSET):
        raise RtwalkError(f"--offset must be a finite number within +-{MAX_OFFSET:g} (got {args.offset})")
    check_at_least(args.rounds, 1, "--rounds")
    if args.json:
        out = Path(args.json).expanduser()
        if out.is_dir() or args.json.endswith(os.sep):
            raise RtwalkError(f"--json {args.json}: is a folder, expected a file name (e.g. out/grids.json)")
        check_output_dir(str(out.parent), "--json")
        check_report_free([out], getattr(args, "force", False), "--json")


def _write_json(path: str, report: dict) -> None:
    if path:
        from viewer.bench.report import write_json

        write_json(Path(path).expanduser(), report)  # whole or not at all (an interrupt during the write)


def run(args) -> int:
    from viewer.cli_args import parse_image_sizes

    size = parse_image_sizes(args.size)[0]
    check_args(args)
    if not args.build_only:  # the rays live in GL targets: a size the device cannot hold was a moderngl traceback
        from viewer.gl.context import shared_context
        from viewer.gl.limits import check_target_size

        check_target_size(shared_context(), size)
    SCENE_DIR[0] = args.scene_dir
    tris, eye, target = scene_dragon(args.offset) if args.scene == "dragon" else scene_mixed()
    if args.build_only:
        return build_only(args, tris)
    o, d = primary_rays(eye, target, size)
    tmin, ray_type = None, None
    if args.rays == "reflect":
        from viewer.effects import RayType

        o, d, tmin = reflect_rays(tris, o, d)
        ray_type = RayType.REFLECT
    names = [b for b in args.backends.split(",") if b]
    runners, rows = {}, {}
    for name in names:
        runners[name] = Runner(name, tris, o, d, tmin, ray_type, image=size if args.rays == "primary" else None)
        rows[name] = {"backend": name, "build_ms": runners[name].build_ms, **runners[name].grid_figures(),
                      "times": []}
    ids_of: dict[str, np.ndarray] = {}
    t_of: dict[str, np.ndarray] = {}

    def report(complete: bool) -> Path | None:  # the rounds every backend finished
        done = min(len(r["times"]) for r in rows.values())
        if done == 0 or not args.json:
            return None
        for r in rows.values():
            del r["times"][done:]
        _summarize(args, names, rows, runners, ids_of, t_of, len(tris), len(o), tmin)
        _write_json(args.json, {"complete": complete, "scene": args.scene, "offset": args.offset, "rounds": done,
                                "rows": list(rows.values())})
        return Path(args.json).expanduser()

    try:
        with keep_partial("bench-grids", defer=True) as part:  # Ctrl-C: stop after the round in hand
            part.keep(report)
            for k in range(args.rounds):
                part.check()
                for name in names:
                    ms, ids, t = runners[name].trace()
                    rows[name]["times"].append(ms)
                    ids_of[name], t_of[name] = ids, t
                print(f"bench-grids: round {k + 1}/{args.rounds} done", file=sys.stderr, flush=True)
        if not report(True):
            _summarize(args, names, rows, runners, ids_of, t_of, len(tris), len(o), tmin)
    finally:
        for r in runners.values():
            r.release()
    return 0


def _summarize(args, names: list[str], rows: dict, runners: dict, ids_of: dict, t_of: dict, n_tris: int,
               n_rays: int, tmin) -> None:
    """Medians, ratios to clbvh and disagreements into `rows`, and the table on stdout."""
    ref = ids_of.get("clbvh")
    base = statistics.median(rows["clbvh"]["times"]) if "clbvh" in rows else None
    active = n_rays if tmin is None else int((~np.isnan(tmin)).sum())
    print(f"scene {args.scene} offset {args.offset:g} triangles {n_tris} rays {n_rays} ({args.rays}, "
          f"{active} active)")
    for name in names:
        r = rows[name]
        r["ms"] = statistics.median(r["times"])
        r["vs_clbvh"] = r["ms"] / base if base else None
        r["hits"] = int((ids_of[name] >= 0).sum())
        st = runners[name].stats  # a per-pass grid's own pairs (pgrid's point grid), where it reports them
        if not r.get("grid_pairs") and "pairs" in st:
            r["grid_pairs"] = st["pairs"]
            r["pass_stats"] = {k: st[k] for k in ("pairs", "culled", "culled_backface", "widened", "tiles")
                               if k in st}
        if ref is not None:  # another triangle at the same distance is a tie, not a disagreement
            t_ref = t_of["clbvh"].astype(np.float64)
            same_t = np.isclose(t_of[name].astype(np.float64), t_ref, rtol=1e-5, atol=0) | \
                ((ids_of[name] < 0) & (ref < 0))
            r["disagree"] = int(((ids_of[name] != ref) & ~same_t).sum())
        else:
            r["disagree"] = None
        mib = r.get("grid_bytes", 0) / 2**20
        sub = f"  sub-grids {int(r['grid2_subgrids'])} sub pairs {int(r['grid2_subpairs'])}" \
            if "grid2_subgrids" in r else ""
        print(f"{name:24s} pairs {int(r.get('grid_pairs', 0)):>10d} res {r.get('grid_res', '-')!s:>16s} "
              f"grid {mib:8.1f} MiB  build {r['build_ms']:8.0f} ms  trace {r['ms']:9.1f} ms "
              f"x{(r['vs_clbvh'] or 0):6.2f}  hits {r['hits']}  disagree {r['disagree']}{sub}"
              + "".join(f"  {k} {int(v)}" for k, v in r.get("pass_stats", {}).items() if k != "pairs"), flush=True)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="rtwalk bench-grids", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except RtwalkError as e:
        print(f"rtwalk: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""`rtwalk bench-voxelwalk`: the voxel-walk studies of Guntury's thesis (2011, chapter 5) on this machine.

Reflection rays are captured once per scene and size (one frame of the glsl backend with the
scene's shipped mirror preset, camera = the recording's middle frame, or the default camera),
then traced again and again on the OpenCL device straight from device buffers, so every
configuration sees exactly the same rays:

- ``table51`` (thesis Table 5.1 / Figure 5.4): grid build, ray-cell pairs, work-groups after
  compaction, EC reorder (enumeration, sort, chunks, resolve), EC trace, EC total, IVW trace,
  IVW/EC speedup (IVW time / EC total), clbvh's trace on the same rays, and the per-frame totals
  of an animated scene (grid rebuilt per frame; clbvh with its per-frame BVH build and collapse).
  Also pairs per ray, rays per cell and tile divergence at the first iteration, and the hit
  agreement of IVW and EC with clbvh (a check, not a timing).
- ``iterations`` (Figures 5.2 and 5.3): % of the rays resolved per iteration (cumulative), the
  distribution of rays per cell at the first iteration (with the tail), and the tile
  divergence (distinct cells per 8x8 pixel tile) per iteration.
- ``resolution``: IVW and EC time against the grid resolution (cells on the longest axis),
  with the automatic choice marked.

Timing: per configuration the median of --repeats runs, runs interleaved between IVW, EC and
clbvh; OpenCL wall time up to a queue finish. Writes <study>.json, <study>.md, <study>.png.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer import iostats
from viewer.bench.common import log, study_scene
from viewer.bench.partial import keep_partial, write_plots
from viewer.bench.plots import figure, finish
from viewer.bench.report import fmt, md_table, size_text, write_study
from viewer.cl import io as clio
from viewer.cli_args import check_output_dir, check_report_free, parse_choices, parse_image_sizes
from viewer.errors import RtwalkError
from viewer.paths import SHARED_SCENES

STUDIES = ("table51", "iterations", "resolution")
SCENES = {"conference": ("conference/conference.ply", "conference-walk.json"),
          "buddha": ("buddha/buddha_100k.obj", None),
          "sibenik": ("sibenik/sibenik.obj", "sibenik-walk.json"),
          "room": ("room", None)}


HELP = "voxel-walk thesis studies: IVW vs EC on reflection rays, with clbvh on the same rays"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--study", default="all", help=f"comma list of {', '.join(STUDIES)} or 'all' (default all)")
    p.add_argument("--scenes", default="conference,buddha,sibenik", help="comma list of " + ", ".join(SCENES))
    p.add_argument("--scene-dir", default=str(SHARED_SCENES), help="folder of the scene files")
    p.add_argument("--sizes", default="640x360", help="comma list of WxH (thesis: 1024x1024,640x360)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per configuration (median; default 3)")
    p.add_argument("--chunk", type=int, default=64, help="EC rays per work-group (default 64)")
    p.add_argument("--resolutions", default="64,96,128,192,256",
                   help="resolution study: cells on the longest axis (the auto choice is added)")
    p.add_argument("--out", default="out/bench-voxelwalk", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def _ints(text: str, what: str) -> list[int]:
    try:
        vals = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise RtwalkError(f"{what}: expected a comma list of whole numbers (got '{text}')") from None
    if not vals or min(vals) < 1 or max(vals) > 1024:
        raise RtwalkError(f"{what}: values must be in 1..1024 (got '{text}')")
    return vals


# ------------------------------------------------------------------------------- rays on the device


@dataclass
class RaySet:
    """One scene's reflection rays of one frame at one size, in device buffers."""

    scene: str
    size: tuple[int, int]
    prep: Any
    stage: Any  # viewer.cl.RayStage holding the rays (row-major pixels)
    hits: Any  # viewer.cl.HitStage
    active: int


def load_scene(args, name: str):
    """(prepared scene, camera): the shipped presets give the mirrors."""
    prep, cam = study_scene(SCENES[name], args.scene_dir)
    if not any(m.mirror for m in prep.scene.materials):
        raise RtwalkError(f"scene {name} has no mirror material (its preset did not apply)")
    return prep, cam


def capture_reflection_rays(ctx, prep, camera, size: tuple[int, int]):
    """The reflection pass's rays of one frame (glsl), as (origin+tmin, dir+tmax) float4 arrays."""
    from viewer.effects import RayType, parse_effects
    from viewer.renderer import Renderer

    r = Renderer(ctx, prep.scene, prep.bvh, size, "glsl", parse_effects("reflections"))
    try:
        rep = r.render(camera, capture=True)
    finally:
        r.release()
    passes = [p for p in rep.captured if p.ray_type == RayType.REFLECT]
    if not passes:
        raise RtwalkError("no reflection pass was traced")
    ra = passes[0].rays
    o4 = np.concatenate([ra.origins, ra.tmin[:, None]], 1).astype(np.float32)
    d4 = np.concatenate([ra.directions, ra.tmax[:, None]], 1).astype(np.float32)
    return o4, d4, int(ra.active.sum())


def _io_delta(c0) -> dict[str, int]:
    """CL launches and host syncs since the viewer.iostats snapshot c0."""
    c1 = iostats.current()
    return {"cl_launches": c1.cl_launches - c0.cl_launches, "host_syncs": c1.host_syncs - c0.host_syncs}


class Device:
    """Triangles, grid, walker and clbvh for one scene on the OpenCL device."""

    def __init__(self, prep, chunk: int):
        from viewer.accel.grid import UniformGrid, scene_box, triangles_f4
        from viewer.backends.clbvh import ClbvhScene
        from viewer.backends.voxelwalk import VoxelWalker
        from viewer.cl import cl_context

        self.ctx = cl_context()
        tris = np.asarray(prep.scene.triangles, np.float32).reshape(-1, 3, 3)
        self.n_tris = len(tris)
        self.box = scene_box(tris)
        self.tris = clio.upload(self.ctx, triangles_f4(tris))
        self.grid = UniformGrid(self.ctx)
        self.walker = VoxelWalker(self.ctx, self.grid, chunk=chunk, window=1)  # EC: iterations in one launch
        self.walker_global = VoxelWalker(self.ctx, self.grid, chunk=chunk, window=1, ec_sort="global")  # the thesis's
        self.walker_all = VoxelWalker(self.ctx, self.grid, chunk=chunk, window=0)  # every pair at once
        self.clbvh = ClbvhScene(prep.scene.triangles, prep.bvh, self.ctx)

    def build(self, resolution: int, repeats: int = 1) -> tuple[Any, float]:
        """Build the grid (0: auto); returns (GridStats, median build ms)."""
        from viewer.accel.grid import GridSpec

        spec = GridSpec(resolution=resolution, max_axis=max(512, resolution))
        ms = []
        for _ in range(max(1, repeats)):
            c0 = iostats.current()
            st = self.grid.build(self.tris, self.n_tris, *self.box, spec)
            self.last_io = _io_delta(c0)
            ms.append(st.build_ms)
        return st, statistics.median(ms)

    def run(self, what: str, rs, stats: bool = False):
        """One trace of the rays of `rs` by 'ivw', 'ec' (iterations in one launch), 'ec_global' (a
        global sort per iteration), 'ec_all' (every ray-cell pair up to tmax in one iteration) or
        'clbvh': (PassStats or None, wall ms)."""
        st, h = rs.stage, rs.hits
        q = self.ctx.queue
        clio.finish(q)
        t0 = time.perf_counter()
        c0 = iostats.current()
        ps = None
        if what == "ivw":
            ps = self.walker.trace_ivw(self.tris, st.origin, st.dir, h.t, h.tri, st.n, False, stats=stats)
        elif what == "ec":
            ps = self.walker.trace_ec(self.tris, st.origin, st.dir, h.t, h.tri, st.n, stats=stats, size=rs.size)
        elif what == "ec_global":
            ps = self.walker_global.trace_ec(self.tris, st.origin, st.dir, h.t, h.tri, st.n, stats=stats,
                                             size=rs.size)
        elif what == "ec_all":
            ps = self.walker_all.trace_ec(self.tris, st.origin, st.dir, h.t, h.tri, st.n, stats=stats, size=rs.size)
        else:
            self.clbvh.enqueue(st.origin, st.dir, h.t, h.tri, st.n, False)
        self.last_io = _io_delta(c0)  # before the timing wait below (the caller's, not the method's)
        clio.finish(q)
        return ps, (time.perf_counter() - t0) * 1e3

    def release(self) -> None:
        self.walker.release()
        self.walker_global.release()
        self.walker_all.release()
        self.grid.release()
        self.clbvh.release()
        self.tris.release()


def _rays_on_device(ctx_gl, dev: Device, prep, cam, name: str, size: tuple[int, int]) -> RaySet:
    from viewer.cl import HitStage, RayStage

    o4, d4, active = capture_reflection_rays(ctx_gl, prep, cam, size)
    stage, hits = RayStage(size, dev.ctx), HitStage(size, dev.ctx)
    stage.upload_arrays(o4, d4)
    return RaySet(name, size, prep, stage, hits, active)


def _agreement(dev: Device, rs: RaySet) -> dict[str, float]:
    """Hit agreement of IVW and EC with clbvh on the same rays (ids equal, or the same t: a tie)."""
    out = {}
    dev.run("clbvh", rs)
    t_ref, id_ref = rs.hits.read()
    for mode in ("ivw", "ec", "ec_global", "ec_all"):
        dev.run(mode, rs)
        t, ids = rs.hits.read()
        same = (ids == id_ref) | ((ids >= 0) & (id_ref >= 0) & (t == t_ref))
        out[mode] = float(same.mean())
    return out


def _timed(dev: Device, rs: RaySet, repeats: int) -> dict[str, Any]:
    """Medians of interleaved runs: IVW, EC (total, reorder, trace) in one launch and with the global
    sort per iteration, EC with every pair at once, clbvh."""
    names = ("ivw", "ec", "ec_global", "ec_all", "clbvh")
    for what in names:  # warm-up (kernels compile on first use)
        dev.run(what, rs)
    runs: dict[str, list[float]] = {k: [] for k in names}
    parts: dict[str, list[Any]] = {k: [] for k in names}
    io = {}
    for _ in range(repeats):
        for what in names:
            ps, ms = dev.run(what, rs)
            runs[what].append(ms)
            parts[what].append(ps)
            io[what] = dev.last_io
    med = statistics.median
    return {"ivw_ms": med(runs["ivw"]), "ec_ms": med(runs["ec"]),
            "ec_reorder_ms": med(p.reorder_ms for p in parts["ec"]),
            "ec_trace_ms": med(p.trace_ms for p in parts["ec"]), "ec_workgroups": parts["ec"][-1].workgroups,
            "ec_iterations": parts["ec"][-1].iterations,
            "ec_global_ms": med(runs["ec_global"]),
            "ec_global_reorder_ms": med(p.reorder_ms for p in parts["ec_global"]),
            "ec_global_trace_ms": med(p.trace_ms for p in parts["ec_global"]),
            "ec_all_ms": med(runs["ec_all"]), "ec_all_pairs": parts["ec_all"][-1].pairs, "clbvh_ms": med(runs["clbvh"]),
            "runs": runs, "io": io}


def _walk_stats(dev: Device, rs: RaySet) -> dict[str, Any]:
    """The statistics run (EC with the global sort and per-iteration statistics; IVW and EC in one
    launch walk the same cells)."""
    ps, _ = dev.run("ec_global", rs, stats=True)
    rpc = ps.rays_per_cell if ps.rays_per_cell is not None else np.zeros(0)
    return {"rays": ps.rays, "pairs": ps.pairs, "workgroups": ps.workgroups, "iterations": ps.iterations,
            "per_iter": ps.per_iter, "resolved": ps.resolved_fraction().tolist(),
            "rays_per_cell": np.sort(rpc)[::-1].tolist(),
            "iters_mean": float(ps.iters[ps.iters > 0].mean()) if (ps.iters > 0).any() else 0.0}


# ----------------------------------------------------------------------------------------- studies


def collect(args, ctx_gl, rows: list[dict] | None = None, part=None) -> list[dict]:
    """Per scene and size: grid (auto), timings, statistics and agreement (table51 and iterations),
    appended to `rows`; `part` (viewer.bench.partial) stops between sizes on Ctrl-C."""
    from viewer.bench.pgrid import bvh_build_ms

    rows = [] if rows is None else rows
    for name in parse_choices(args.scenes, SCENES, "--scenes"):
        prep, cam = load_scene(args, name)
        dev = Device(prep, args.chunk)
        try:
            gs, build_ms = dev.build(0, repeats=args.repeats)
            build_io = dev.last_io
            bvh_ms = bvh_build_ms(prep)["clbvh"]
            for size in parse_image_sizes(args.sizes, "--sizes"):
                if part is not None:
                    part.check()
                log(args, f"bench-voxelwalk: {name} {size_text(size)}: capturing reflection rays")
                rs = _rays_on_device(ctx_gl, dev, prep, cam, name, size)
                try:
                    log(args, f"bench-voxelwalk: {name} {size_text(size)}: {rs.active} reflection rays, grid {gs.res}")
                    row = {"scene": name, "triangles": prep.scene.triangle_count, "size": list(size),
                           "reflection_rays": rs.active, "grid_res": list(gs.res), "grid_pairs": gs.pairs,
                           "build_ms": build_ms, "clbvh_bvh_build_ms": bvh_ms, "build_io": build_io,
                           **_timed(dev, rs, args.repeats), "walk": _walk_stats(dev, rs),
                           "agreement": _agreement(dev, rs)}
                finally:
                    rs.stage.release()
                    rs.hits.release()
                rows.append(row)
        finally:
            dev.release()
    return rows


def study_table51(args, rows: list[dict]) -> dict:
    md = ["# Thesis Table 5.1 analog: reflection rays through the uniform grid, IVW vs EC (ms, medians)", "",
          f"Command: `{args.command_line}`", ""]
    head = ["scene", "size", "refl. rays", "grid", "DS build", "ray-cell pairs", "work-groups (global / one launch)",
            "EC global: reorder", "trace", "total", "EC one launch: total", "IVW trace", "IVW/EC",
            "IVW/EC global", "EC all pairs: pairs / total", "clbvh trace", "frame: build+IVW", "frame: build+EC",
            "frame: BVH build+clbvh"]
    body = []
    for r in rows:
        w = r["walk"]
        body.append([r["scene"], size_text(tuple(r["size"])), f"{r['reflection_rays']:,}",
                     "x".join(str(x) for x in r["grid_res"]), fmt(r["build_ms"]), f"{w['pairs']:,}",
                     f"{w['workgroups']:,} / {r['ec_workgroups']:,}", fmt(r["ec_global_reorder_ms"]),
                     fmt(r["ec_global_trace_ms"]), fmt(r["ec_global_ms"]), fmt(r["ec_ms"]),
                     fmt(r["ivw_ms"]), fmt(r["ivw_ms"] / max(r["ec_ms"], 1e-9), 2),
                     fmt(r["ivw_ms"] / max(r["ec_global_ms"], 1e-9), 2),
                     f"{r['ec_all_pairs']:,} / {fmt(r['ec_all_ms'])}", fmt(r["clbvh_ms"]),
                     fmt(r["build_ms"] + r["ivw_ms"]), fmt(r["build_ms"] + r["ec_ms"]),
                     fmt(r["clbvh_bvh_build_ms"] + r["clbvh_ms"])])
    md.append(md_table(head, body))
    md += ["", "## Launches and host waits per phase (one run each)", ""]
    body = []
    for r in rows:
        io = r.get("io", {})
        for phase, d, ms in (("grid build", r.get("build_io"), r["build_ms"]), ("IVW", io.get("ivw"), r["ivw_ms"]),
                             ("EC one launch", io.get("ec"), r["ec_ms"]),
                             ("EC global sort", io.get("ec_global"), r["ec_global_ms"])):
            if d:
                body.append([r["scene"], size_text(tuple(r["size"])), phase, fmt(ms), str(d["cl_launches"]),
                             str(d["host_syncs"])])
    md.append(md_table(["scene", "size", "phase", "ms", "CL launches", "host syncs"], body))
    md += ["", "## Why: the walk behind the times", ""]
    head = ["scene", "size", "pairs per ray", "iterations per ray", "EC iterations", "rays per cell (1st it.)",
            "max rays per cell", "cells per 8x8 tile (1st it.)", "IVW = clbvh", "EC = clbvh", "EC global = clbvh",
            "EC all = clbvh"]
    body = []
    for r in rows:
        w = r["walk"]
        rpc = np.asarray(w["rays_per_cell"], float)
        first = w["per_iter"][0] if w["per_iter"] else {}
        body.append([r["scene"], size_text(tuple(r["size"])), fmt(w["pairs"] / max(w["rays"], 1), 2),
                     fmt(w["iters_mean"], 2), str(w["iterations"]), fmt(rpc.mean() if len(rpc) else 0, 1),
                     fmt(rpc.max() if len(rpc) else 0, 0), fmt(first.get("tile_cells_mean", float("nan")), 2),
                     f"{100 * r['agreement']['ivw']:.3f}%", f"{100 * r['agreement']['ec']:.3f}%",
                     f"{100 * r['agreement']['ec_global']:.3f}%", f"{100 * r['agreement']['ec_all']:.3f}%"])
    md.append(md_table(head, body))
    md += ["", "EC: one non-empty cell per ray per iteration, rays resolved by the hit-inside-cell rule drop out "
           "(the thesis's iterations). EC global: the thesis's global radix sort of the ray-cell pairs per iteration "
           "(launches grow with the iterations); EC one launch: every iteration on the device, one work-group per "
           "screen-tile partition sorting its rays by cell (ec_tile.cl). "
           "EC all pairs: every (ray, non-empty cell) pair up to tmax enumerated, sorted "
           "and processed at once (no early exit). "
           "IVW/EC > 1: EC faster. 'frame' columns: an animated scene, where the grid (or clbvh's BVH: "
           "binary SAH build + BVH4 collapse on the CPU) is rebuilt every frame before the reflection pass. "
           "Agreement: rays whose IVW / EC hit equals clbvh's (same triangle, or the same distance: a tie)."]
    res = write_study(Path(args.out), "table51", {"rows": rows, "command": args.command_line}, "\n".join(md))
    write_plots(lambda: _plot_table51(rows, Path(args.out) / "table51.png"))  # after the JSON: never loses it
    return res


def _plot_table51(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    fig, ax = figure(size=(10, 0.6 + 0.5 * len(rows) * 3))
    y, labels = 0, []
    for r in rows:
        tag = f"{r['scene']} {size_text(tuple(r['size']))}"
        ax.barh(y, r["build_ms"], color="#bbbbbb", label="grid build" if y == 0 else None)
        ax.barh(y, r["ec_reorder_ms"], left=r["build_ms"], color="#e5c494", label="EC reorder" if y == 0 else None)
        ax.barh(y, r["ec_trace_ms"], left=r["build_ms"] + r["ec_reorder_ms"], color="#b2182b",
                label="EC trace" if y == 0 else None)
        labels.append(f"{tag} EC")
        ax.barh(y + 1, r["build_ms"], color="#bbbbbb")
        ax.barh(y + 1, r["ivw_ms"], left=r["build_ms"], color="#1f4e9c", label="IVW trace" if y == 0 else None)
        labels.append(f"{tag} IVW")
        ax.barh(y + 2, r["clbvh_ms"], color="#4daf4a", label="clbvh trace" if y == 0 else None)
        labels.append(f"{tag} clbvh")
        y += 3
    ax.set_yticks(range(len(labels)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("ms (reflection pass; grey: grid build)")
    ax.legend(fontsize=7)
    finish(fig, path, "Table 5.1 analog: EC vs IVW vs clbvh on the same reflection rays")


def study_iterations(args, rows: list[dict]) -> dict:
    md = ["# Thesis Figures 5.2 / 5.3 analog: rays resolved per iteration, rays per cell, tile divergence", "",
          f"Command: `{args.command_line}`", ""]
    head = ["scene", "size", "resolved after 1 / 2 / 4 / 8 / 16 it. (%)", "iterations (EC)",
            "rays per cell p50 / p90 / p99 / max", "cells per 8x8 tile it. 1 / 2 / 4 / 8"]
    body = []
    for r in rows:
        w = r["walk"]
        cum = np.cumsum(w["resolved"]) * 100
        pick = [fmt(cum[min(k, len(cum)) - 1], 1) if len(cum) else "-" for k in (1, 2, 4, 8, 16)]
        rpc = np.asarray(w["rays_per_cell"], float)
        q = [fmt(np.percentile(rpc, p), 0) for p in (50, 90, 99)] + [fmt(rpc.max(), 0)] if len(rpc) else ["-"]
        div = [fmt(w["per_iter"][k - 1].get("tile_cells_mean", float("nan")), 2) if len(w["per_iter"]) >= k else "-"
               for k in (1, 2, 4, 8)]
        body.append([r["scene"], size_text(tuple(r["size"])), " / ".join(pick), str(w["iterations"]),
                     " / ".join(q), " / ".join(div)])
    md.append(md_table(head, body))
    md += ["", "Iteration k: the k-th non-empty cell along each ray (IVW and EC visit the same cells). Resolved: "
           "% of the active reflection rays whose walk ended by iteration k (cumulative)."]
    summary = [{k: r[k] for k in ("scene", "size", "walk")} for r in rows]
    res = write_study(Path(args.out), "iterations", {"rows": summary, "command": args.command_line}, "\n".join(md))
    write_plots(lambda: _plot_iterations(rows, Path(args.out) / "iterations.png"))
    return res


def _plot_iterations(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    fig, axes = figure(1, 3, size=(14, 4.2))
    for r in rows:
        w = r["walk"]
        tag = f"{r['scene']} {size_text(tuple(r['size']))}"
        cum = np.cumsum(w["resolved"]) * 100
        axes[0].plot(np.arange(1, len(cum) + 1), cum, marker=".", label=tag)
        rpc = np.asarray(w["rays_per_cell"], float)
        if len(rpc):
            axes[1].loglog(np.arange(1, len(rpc) + 1), rpc, label=tag)
        div = [p.get("tile_cells_mean", np.nan) for p in w["per_iter"]]
        axes[2].plot(np.arange(1, len(div) + 1), div, marker=".", label=tag)
    axes[0].set(xlabel="iteration", ylabel="% rays resolved (cumulative)", title="Fig. 5.2: rays resolved")
    axes[0].set_xscale("log")
    axes[1].set(xlabel="cell rank", ylabel="rays in the cell", title="Fig. 5.3 top: rays per cell, 1st iteration")
    axes[2].set(xlabel="iteration", ylabel="distinct cells per 8x8 tile", title="Fig. 5.3 bottom: tile divergence")
    axes[2].set_xscale("log")
    for ax in axes:
        ax.legend(fontsize=7)
    finish(fig, path, "Reflection rays through the uniform grid")


def study_resolution(args, ctx_gl) -> dict:
    size = parse_image_sizes(args.sizes, "--sizes")[0]
    out = []
    for name in parse_choices(args.scenes, SCENES, "--scenes"):
        prep, cam = load_scene(args, name)
        dev = Device(prep, args.chunk)
        rs = None
        try:
            auto, _ = dev.build(0)
            rs = _rays_on_device(ctx_gl, dev, prep, cam, name, size)
            pts = []
            fixed = [r for r in _ints(args.resolutions, "--resolutions") if r != max(auto.res)]
            for res in sorted([*fixed, 0], key=lambda r: r or max(auto.res)):  # 0: the automatic choice
                gs, build_ms = dev.build(res, repeats=args.repeats)
                log(args, f"bench-voxelwalk: resolution {name} {res or 'auto'}: grid {gs.res}")
                t = _timed(dev, rs, args.repeats)
                pts.append({"resolution": res or max(gs.res), "grid_res": list(gs.res), "grid_pairs": gs.pairs,
                            "build_ms": build_ms, "auto": res == 0,
                            **{k: t[k] for k in ("ivw_ms", "ec_ms", "ec_reorder_ms", "ec_trace_ms", "clbvh_ms")}})
            out.append({"scene": name, "size": list(size), "auto_res": list(auto.res), "reflection_rays": rs.active,
                        "points": pts})
        finally:
            if rs is not None:
                rs.stage.release()
                rs.hits.release()
            dev.release()
    md = ["# Reflection-pass time against the grid resolution (ms, medians)", "", f"Command: `{args.command_line}`", ""]
    head = ["scene", "cells (longest axis)", "grid", "tri-cell pairs", "build", "IVW", "EC total", "EC trace",
            "clbvh"]
    body = []
    for s in out:
        for p in s["points"]:
            body.append([s["scene"], f"{p['resolution']}{' (auto)' if p['auto'] else ''}",
                         "x".join(str(x) for x in p["grid_res"]), f"{p['grid_pairs']:,}", fmt(p["build_ms"]),
                         fmt(p["ivw_ms"]), fmt(p["ec_ms"]), fmt(p["ec_trace_ms"]), fmt(p["clbvh_ms"])])
    md.append(md_table(head, body))
    _plot_resolution(out, Path(args.out) / "resolution.png")
    return write_study(Path(args.out), "resolution", {"scenes": out, "command": args.command_line}, "\n".join(md))


def _plot_resolution(out: list[dict], path: Path) -> None:
    if not out:
        return
    fig, axes = figure(1, len(out), size=(4.5 * len(out), 4), squeeze=False)
    for ax, s in zip(axes[0], out, strict=True):
        xs = [p["resolution"] for p in s["points"]]
        for key, lab in (("ivw_ms", "IVW"), ("ec_ms", "EC total"), ("build_ms", "grid build")):
            ax.plot(xs, [p[key] for p in s["points"]], marker="o", label=lab)
        ax.axhline(statistics.median(p["clbvh_ms"] for p in s["points"]), color="#4daf4a", ls="--",
                   label="clbvh (median)")
        for p in s["points"]:
            if p["auto"]:
                ax.axvline(p["resolution"], color="grey", ls=":", label=f"auto ({p['resolution']})")
        ax.set(xlabel="cells on the longest axis", ylabel="ms", title=f"{s['scene']} {size_text(tuple(s['size']))}")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    finish(fig, path, "Time against grid resolution")


# ---------------------------------------------------------------------------------------------- run


def run(args) -> int:
    from viewer.cl import cl_context
    from viewer.gl.context import shared_context

    studies = parse_choices(args.study, STUDIES, "--study")
    parse_choices(args.scenes, SCENES, "--scenes")
    parse_image_sizes(args.sizes, "--sizes")
    _ints(args.resolutions, "--resolutions")
    if args.repeats < 1:
        raise RtwalkError("--repeats must be >= 1")
    if args.chunk not in (16, 32, 64, 128, 256):
        raise RtwalkError(f"--chunk must be one of 16, 32, 64, 128, 256 (got {args.chunk})")
    check_output_dir(args.out, "--out")
    check_report_free([Path(args.out) / f"{s}.json" for s in studies], getattr(args, "force", False))
    cl_context()
    ctx = shared_context()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    row_studies = [s for s in studies if s in ("table51", "iterations")]

    def rows_so_far(complete: bool) -> list[Path]:  # collect interrupted: its studies from the rows done
        return [STUDY_OF_ROWS[s](args, rows)["json"] for s in row_studies] if rows else []

    with keep_partial("bench-voxelwalk", defer=True) as part:  # Ctrl-C: stop after the size in hand
        if row_studies:
            part.keep(rows_so_far)
            collect(args, ctx, rows, part)
            part.keep(lambda complete: None)
        for s in studies:
            part.started(s)
            res = STUDY_OF_ROWS[s](args, rows) if s in STUDY_OF_ROWS else study_resolution(args, ctx)
            part.finished(res["json"])
            print(res["markdown"], flush=True)
    return 0


STUDY_OF_ROWS = {"table51": study_table51, "iterations": study_iterations}

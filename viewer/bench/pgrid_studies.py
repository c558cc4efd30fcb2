"""More of `rtwalk bench-pgrid`'s studies (thesis Figures 3.6 and 4.7, and the animated scene).

- ``pairs`` (Figure 3.6): triangle-cell pairs of the uniform grid against the camera perspective
  grid, with frustum culling alone and with back-face culling too, for indirect-mapping factors
  k = 1, 2, 4; with the build time of each (median of --frames builds) and the culled counts.
  Back-face culling is counted on every scene, and the table says where it would be exact
  (closed, outward-facing geometry seen from outside); the renderer only culls there.
- ``rearrange`` (Figure 4.7): from table41's rows, the data-rearrangement time per scene and size
  (sorting the shadow rays into light-tile chunks), beside the primary rays' classification
  (image-order rays need no sort) and the rays and chunks behind them. Needs table41 in the run.
- ``anim``: the animated built-in scene (room-anim, its recording) with every structure rebuilt
  per frame: per backend, the per-frame median of each build phase (animation, BVH refit, GPU
  upload, BVH4 collapse, uniform grid, camera grid, light grid, shadow-ray rearrangement) and of
  the traversal, frames interleaved between the backends (viewer.bench.harness).
"""

from __future__ import annotations

import statistics
import time
from functools import partial
from pathlib import Path

import numpy as np

from viewer.bench.plots import bars, figure, finish, stacked
from viewer.bench.report import fmt, md_table, size_text, write_study

KS = (1, 2, 4)
ANIM_RECORDING = "room-anim-walk.json"
ANIM_BACKENDS = ("pgrid", "ugrid", "clbvh", "glsl")


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def study_pairs(args, load_scene, sizes, scenes) -> dict:
    """Figure 3.6 analog (module docstring)."""
    from viewer.accel.camgrid import CameraGrid, CameraGridSpec, closed_outward, fit_camera
    from viewer.accel.grid import GridSpec, UniformGrid, scene_box, triangles_f4
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    rows = []
    for name in scenes:
        prep, cam = load_scene(args, name)
        tris = np.asarray(prep.scene.triangles, np.float32).reshape(-1, 3, 3)
        f4 = triangles_f4(tris)
        buf = clio.upload(ctx, f4)
        ug, cg = UniformGrid(ctx), CameraGrid(ctx)
        try:
            box = scene_box(tris)
            ug_ms = _median_ms(partial(ug.build, buf, len(tris), *box, GridSpec()), args.frames)
            ug_pairs = ug.stats.pairs
            closed = closed_outward(tris)
            for size in sizes:
                if getattr(args, "partial_run", None) is not None:
                    args.partial_run.check()
                o, d = cam.primary_rays(*size)
                w, h = size
                flat_o, flat_d = o.reshape(-1, 3), d.reshape(-1, 3)
                idx = [0, w - 1, (h - 1) * w, h * w - 1]
                pc = fit_camera(np.c_[flat_o[idx], np.zeros(4)], np.c_[flat_d[idx], np.ones(4)], size)
                row = {"scene": name, "triangles": len(tris), "size": list(size), "ugrid_pairs": ug_pairs,
                       "ugrid_build_ms": ug_ms, "closed": closed, "camera": {}}
                for k in KS:
                    for back in (False, True):
                        spec = CameraGridSpec(k=k, backface=back)
                        ms = _median_ms(partial(cg.build, buf, len(tris), pc, spec), args.frames)
                        st = cg.stats
                        row["camera"][f"k={k},{'back' if back else 'frustum'}"] = {
                            "pairs": st.pairs, "build_ms": ms, "tiles": st.tiles[0] * st.tiles[1],
                            "culled_frustum": st.culled_frustum, "culled_backface": st.culled_backface,
                            "near_eye": st.near_eye}
                rows.append(row)
        finally:
            ug.release()
            cg.release()
            buf.release()
    md = ["# Thesis Figure 3.6 analog: triangle-cell pairs, uniform vs camera perspective grid", "",
          f"Command: `{args.command_line}`", "",
          "Camera grid: 8k x 8k-pixel tiles x 16 slabs; 'frustum': frustum culling only, '+back': back-face "
          "culling too (exact only on closed scenes, column 'closed'); build = the whole per-frame build "
          f"(clip, count, scan, write, sort, ranges), median of {args.frames}.", ""]
    head = ["scene", "size", "closed", "ugrid pairs", "ugrid build ms"]
    for k in KS:
        head += [f"k={k} pairs", f"k={k} +back pairs", f"k={k} build ms"]
    head += ["frustum-culled", "back-culled"]
    body = []
    for r in rows:
        c = r["camera"]
        line = [r["scene"], size_text(tuple(r["size"])), "yes" if r["closed"] else "no", fmt(r["ugrid_pairs"], 0),
                fmt(r["ugrid_build_ms"])]
        for k in KS:
            line += [fmt(c[f"k={k},frustum"]["pairs"], 0), fmt(c[f"k={k},back"]["pairs"], 0),
                     fmt(c[f"k={k},frustum"]["build_ms"])]
        line += [fmt(c["k=1,frustum"]["culled_frustum"], 0), fmt(c["k=1,back"]["culled_backface"], 0)]
        body.append(line)
    md.append(md_table(head, body))
    fig, ax = figure(size=(10, 4.5))
    labels = [f"{r['scene']}\n{size_text(tuple(r['size']))}" for r in rows]
    series = {"uniform grid": [r["ugrid_pairs"] for r in rows]}
    for k in KS:
        series[f"camera k={k}"] = [r["camera"][f"k={k},frustum"]["pairs"] for r in rows]
        series[f"camera k={k} +back"] = [r["camera"][f"k={k},back"]["pairs"] for r in rows]
    bars(ax, labels, series, ylabel="triangle-cell pairs", log=True, legend_cols=2)
    finish(fig, Path(args.out) / "pairs.png", "Figure 3.6 analog: triangle-cell pairs")
    return write_study(Path(args.out), "pairs", {"rows": rows, "command": args.command_line}, "\n".join(md))


def study_rearrange(args, table41: dict) -> dict:
    """Figure 4.7 analog from table41's rows (module docstring)."""
    rows = []
    for r in table41["rows"]:
        ph, st = r["phases"]["pgrid"], r["stats"]["pgrid"]
        rows.append({"scene": r["scene"], "size": r["size"], "rearrange_ms": ph.get("pgrid:rearrange:shadows", 0.0),
                     "classify_primary_ms": ph.get("pgrid:rearrange:primary", 0.0),
                     "shadow_rays": st.get("grid_rays_shadows", float("nan")),
                     "chunks": st.get("chunks_shadows", float("nan")), "tiles": st.get("tiles_shadows", float("nan"))})
    md = ["# Thesis Figure 4.7 analog: data rearrangement per scene (ms, medians)", "",
          f"Command: `{args.command_line}`", "",
          "Shadow rays: (light tile, ray) pairs radix-sorted, segments cut into chunks, compacted. Primary "
          "rays are in image order already: their step is only the per-ray check against the tile.", "",
          md_table(["scene", "size", "shadow rearrangement", "shadow rays in the grid", "light tiles", "chunks",
                    "primary classification"],
                   [[r["scene"], size_text(tuple(r["size"])), fmt(r["rearrange_ms"]), fmt(r["shadow_rays"], 0),
                     fmt(r["tiles"], 0), fmt(r["chunks"], 0), fmt(r["classify_primary_ms"])] for r in rows])]
    fig, ax = figure(size=(8, 4))
    bars(ax, [f"{r['scene']}\n{size_text(tuple(r['size']))}" for r in rows],
         {"shadow rearrangement": [r["rearrange_ms"] for r in rows],
          "primary classification": [r["classify_primary_ms"] for r in rows]}, ylabel="ms")
    finish(fig, Path(args.out) / "rearrange.png", "Figure 4.7 analog: data rearrangement")
    return write_study(Path(args.out), "rearrange", {"rows": rows, "command": args.command_line}, "\n".join(md))


def _is_build(phase: str) -> bool:
    return phase.startswith("build:") or phase.endswith(("_build", ":build")) or phase.startswith("pgrid:build:") \
        or phase.startswith("pgrid:rearrange:") or phase == "pgrid:triangles"


def study_anim(args) -> dict:
    """Per-frame build and trace times on the animated scene (module docstring)."""
    from viewer.bench.harness import Harness, RunSpec
    from viewer.paths import RECORDINGS

    path = RECORDINGS / ANIM_RECORDING
    size = args.anim_size
    h = Harness(frames=args.anim_frames, first_frame=0, quiet=args.quiet)
    h.interrupt = getattr(args, "partial_run", None)  # a deferred Ctrl-C stops before the comparison
    h.progress("anim", len(ANIM_BACKENDS) * args.anim_frames)
    try:
        res = h.run_many(path, size, [RunSpec(b, "primary,shadows", b) for b in ANIM_BACKENDS])
    finally:
        h.done()
    rows = []
    for r in res:
        timed = [f for f in r.frames[1:]] or r.frames
        keys = sorted({k for f in timed for k in f["gpu_ms"]})
        med = {k: statistics.median(f["gpu_ms"].get(k, 0.0) for f in timed) for k in keys}
        builds = {k: v for k, v in med.items() if _is_build(k)}
        trace = sum(v for k, v in med.items() if k.startswith("trace:"))
        rows.append({"backend": r.label, "builds_ms": builds, "build_ms": sum(builds.values()), "trace_ms": trace,
                     "frame_ms": statistics.median(f["wall_ms"] for f in timed),
                     "stats": timed[-1].get("backend_stats", {}), "frames": len(timed)})
    md = [f"# Animated scene: per-frame builds ({path.stem}, {size_text(size)}, primary + shadows, ms, medians)",
          "", f"Command: `{args.command_line}`", "",
          "Every frame moves the geometry. Shared by all: build:animate (evaluate the animation), build:bvh "
          "(binary BVH refit, not rebuilt: topology and leaf order kept, so triangle ids stay valid), "
          "build:upload (GPU scene). Then each backend's own: build:bvh4 (clbvh collapse), ugrid:build, "
          "pgrid:triangles (upload), pgrid:build:primary (camera grid), pgrid:build:shadows (light grid), "
          "pgrid:rearrange:* (rays into tiles / chunks).", ""]
    phases = sorted({k for r in rows for k in r["builds_ms"]})
    md.append(md_table(["backend"] + phases + ["all builds", "traversal", "frame (wall)"],
                       [[r["backend"]] + [fmt(r["builds_ms"].get(p, 0.0), 2) for p in phases]
                        + [fmt(r["build_ms"], 2), fmt(r["trace_ms"], 2), fmt(r["frame_ms"], 1)] for r in rows]))
    fig, ax = figure(size=(8, 4))
    layers = {p: [r["builds_ms"].get(p, 0.0) for r in rows] for p in phases}
    layers["traversal"] = [r["trace_ms"] for r in rows]
    stacked(ax, list(range(len(rows))), layers, ylabel="ms per frame")
    ax.set_xticks(range(len(rows)), [r["backend"] for r in rows])
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    finish(fig, Path(args.out) / "anim.png", f"Per-frame builds on {path.stem}")
    return write_study(Path(args.out), "anim", {"rows": rows, "command": args.command_line,
                                                "size": list(size)}, "\n".join(md))

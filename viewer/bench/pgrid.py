"""`rtwalk bench-pgrid`: the perspective-grid studies of Guntury's thesis (2011) on this machine.

Studies (``--study``, comma list or ``all``):

- ``table41`` (thesis Table 4.1): per scene and size, one point light, effects primary + shadows
  (+ one diffuse pass for the cost model, one soft-shadow pass for what area lights cost):
  pgrid's primary data-structure build (camera grid and the rays' tile check), primary
  traversal, shadow data-structure build (light grid), data rearrangement (shadow-ray sort into
  chunks), shadow traversal, total and fps; the uniform grid (ugrid, rebuilt every frame) and
  clbvh / glsl on the same frames, with and without a per-frame BVH build (the per-frame builder,
  viewer.accel.builders.per_frame_builder, plus the BVH4 collapse for clbvh, timed on the scene).
  Also the counters behind the times (triangle-cell pairs of each grid, culled triangles, chunks
  and their occupancy, rays outside the grids).
- ``lightdist`` (thesis Figure 4.9): shadow time (build + rearrangement + traversal) as the light
  moves away from the model along the line from its centre through the scene's light, for chunk
  sizes 64/128/256 and without load balancing, at a fixed angular resolution (--light-tile-deg) so
  tiles fill up as the light recedes; clbvh's any-hit time on the same rays beside it.
- ``model`` (thesis Figures 4.10 / 5.5): the cost-model totals from the measured terms of
  table41 (per-frame BVH build + traversals vs per-pass grids) as functions of the number of
  lights and of secondary passes, and the break-even counts. Needs table41 in the same run.
- ``pairs`` (Figure 3.6), ``rearrange`` (Figure 4.7, needs table41) and ``anim`` (per-frame
  builds on the animated scene): viewer.bench.pgrid_studies.

Timing: each configuration has its own Renderer; frames are interleaved between them (one
warm-up frame each first: OpenCL kernels compile on first use), and per-phase times are the
medians over the timed frames. Phases are the backends' profiler phases (OpenCL phases are wall
time up to a queue finish). Writes <study>.json, <study>.md and <study>.png into --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time
from pathlib import Path

import numpy as np

from viewer.bench.common import log, study_scene
from viewer.bench.partial import keep_partial
from viewer.bench.pgrid_studies import study_anim, study_pairs, study_rearrange
from viewer.bench.plots import figure, finish
from viewer.bench.report import fmt, md_table, size_text, write_study
from viewer.cli_args import check_output_dir, check_report_free, parse_choices, parse_image_sizes
from viewer.errors import RtwalkError
from viewer.paths import SHARED_SCENES

STUDIES = ("table41", "lightdist", "model", "pairs", "rearrange", "anim")
SCENES = {"sibenik": ("sibenik/sibenik.obj", "sibenik-walk.json"),
          "conference": ("conference/conference.ply", "conference-walk.json"),
          "buddha": ("buddha/buddha_100k.obj", None), "city": ("city", "city-near.json")}
BACKENDS = ("pgrid", "ugrid", "clbvh", "glsl")


HELP = "perspective-grid thesis studies: pgrid vs uniform grid vs BVH"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--study", default="all", help=f"comma list of {', '.join(STUDIES)} or 'all' (default all)")
    p.add_argument("--scenes", default="sibenik,conference,buddha,city",
                   help="comma list of " + ", ".join(SCENES) + " (default all four)")
    p.add_argument("--scene-dir", default=str(SHARED_SCENES), help="folder of the scene files")
    p.add_argument("--city-size", type=int, default=100_000, help="triangles of the built-in city (default 100000)")
    p.add_argument("--sizes", default="640x360", help="comma list of WxH (thesis: 1024x1024,640x360)")
    p.add_argument("--frames", type=int, default=3, help="timed frames per configuration (default 3)")
    p.add_argument("--light-scene", default="buddha", help="scene of the lightdist study (default buddha)")
    p.add_argument("--light-tile-deg", type=float, default=2.0,
                   help="lightdist: light-grid tile size in degrees, fixed at every distance (default 2)")
    p.add_argument("--distances", default="0.25,0.5,1,2,4",
                   help="lightdist: light distance from the model centre in scene diagonals")
    p.add_argument("--anim-frames", type=int, default=8, help="anim: timed frames of the animated walk (default 8)")
    p.add_argument("--anim-size", default="640x360", help="anim: image size WxH (default 640x360)")
    p.add_argument("--pgrid-params", default="", help="extra pgrid parameters for every run (key=value,...)")
    p.add_argument("--out", default="out/bench-pgrid", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def load_scene(args, name: str):
    """(prepared scene, camera) for a study scene; the camera is a recording's middle frame."""
    prep, cam = study_scene(SCENES[name], args.scene_dir, builtin_size=args.city_size)
    if not prep.scene.point_lights:
        raise RtwalkError(f"scene {name} has no point light")
    return prep, cam


def bvh_build_ms(prep) -> dict[str, float]:
    """Per-frame BVH cost of a dynamic scene: the binary build (glsl) with the per-frame builder
    (viewer.accel.builders.per_frame_builder: the device build when OpenCL is there), plus the BVH4
    collapse and leaf packing (clbvh). Median of three."""
    from viewer.accel.builders import build_scene_bvh, per_frame_builder
    from viewer.accel.bvh4 import build_bvh4
    from viewer.backends.clbvh import pack_leaves

    tris = prep.scene.triangles
    builder = per_frame_builder()
    b, c = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        bvh = build_scene_bvh(tris, builder)
        t1 = time.perf_counter()
        b4 = build_bvh4(bvh)
        pack_leaves(b4.nodes, bvh.triangles_in_leaf_order(tris))
        t2 = time.perf_counter()
        b.append((t1 - t0) * 1e3)
        c.append((t2 - t1) * 1e3)
    return {"glsl": statistics.median(b), "clbvh": statistics.median(b) + statistics.median(c)}


def interrupt_check(args):
    """The running command's `check` (viewer.bench.partial), set by `run`; None outside it."""
    part = getattr(args, "partial_run", None)
    return part.check if part is not None else None


def run_interleaved(ctx, prep, camera, size, effects: str, configs: dict[str, tuple[str, str]], frames: int,
                    scene=None, check=None) -> dict[str, dict]:
    """configs: label -> (backend, params). Returns label -> {"phases": {phase: median ms},
    "stats": last frame's counters, "phase_io": last frame's launches and host syncs per phase,
    "io": last frame's viewer.iostats counts}. `check` runs between frames (a deferred Ctrl-C
    stops there: viewer.bench.partial)."""
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer

    scene = scene or prep.scene
    renderers = {}
    try:
        for label, (backend, params) in configs.items():
            renderers[label] = Renderer(ctx, scene, prep.bvh, size, backend, parse_effects(effects),
                                        backend_options={backend: params} if params else None)
        samples: dict[str, list[dict]] = {k: [] for k in configs}
        stats: dict[str, dict] = {}
        phase_io: dict[str, dict] = {}
        io: dict[str, dict] = {}
        for f in range(frames + 1):
            if check is not None:
                check()
            for label, r in renderers.items():
                rep = r.render(camera)
                if f > 0:
                    samples[label].append(dict(rep.gpu_ms))
                    stats[label] = dict(rep.backend_stats)
                    phase_io[label] = dict(rep.phase_io)
                    io[label] = rep.io.as_dict()
    finally:
        for r in renderers.values():
            r.release()
    out = {}
    for label, frames_ms in samples.items():
        keys = sorted({k for s in frames_ms for k in s})
        out[label] = {"phases": {k: statistics.median(s.get(k, 0.0) for s in frames_ms) for k in keys},
                      "stats": stats.get(label, {}), "phase_io": phase_io.get(label, {}), "io": io.get(label, {})}
    return out


# ------------------------------------------------------------------------------------------ table41


def _terms(res: dict, builds: dict[str, float]) -> dict[str, dict[str, float]]:
    """Thesis Table 4.1 terms per backend (ms)."""
    ph = {k: v["phases"] for k, v in res.items()}
    g = lambda b, k: float(ph[b].get(k, 0.0))  # noqa: E731
    t = {
        "pgrid": {"primary_build": g("pgrid", "pgrid:build:primary") + g("pgrid", "pgrid:rearrange:primary"),
                  "primary_trace": g("pgrid", "trace:primary"), "shadow_build": g("pgrid", "pgrid:build:shadows"),
                  "rearrange": g("pgrid", "pgrid:rearrange:shadows"), "shadow_trace": g("pgrid", "trace:shadows"),
                  "secondary_build": g("ugrid", "ugrid:build"), "secondary_trace": g("pgrid", "trace:diffuse"),
                  "soft_trace": g("pgrid", "trace:soft")},
        "ugrid": {"primary_build": g("ugrid", "ugrid:build"), "primary_trace": g("ugrid", "trace:primary"),
                  "shadow_build": 0.0, "rearrange": 0.0, "shadow_trace": g("ugrid", "trace:shadows"),
                  "secondary_build": 0.0, "secondary_trace": g("ugrid", "trace:diffuse")},
    }
    for b in ("clbvh", "glsl"):
        t[b] = {"primary_build": builds[b], "primary_trace": g(b, "trace:primary"), "shadow_build": 0.0,
                "rearrange": 0.0, "shadow_trace": g(b, "trace:shadows"), "secondary_build": 0.0,
                "secondary_trace": g(b, "trace:diffuse")}
    for v in t.values():
        v["total"] = sum(v[k] for k in ("primary_build", "primary_trace", "shadow_build", "rearrange", "shadow_trace"))
    return t


def study_table41(args, ctx) -> dict:
    rows = []
    for name in parse_choices(args.scenes, SCENES, "--scenes"):
        prep, cam = load_scene(args, name)
        builds = bvh_build_ms(prep)
        for size in parse_image_sizes(args.sizes, "--sizes"):
            log(args, f"bench-pgrid: table41 {name} {size_text(size)}")
            extra = args.pgrid_params
            configs = {"pgrid": ("pgrid", ",".join(x for x in ("rebuild=false", extra) if x)),
                       "ugrid": ("ugrid", "rebuild=true"), "clbvh": ("clbvh", ""), "glsl": ("glsl", "")}
            res = run_interleaved(ctx, prep, cam, size, "primary,shadows,soft:1,diffuse:1", configs, args.frames,
                                  check=interrupt_check(args))
            rows.append({"scene": name, "triangles": prep.scene.triangle_count, "size": list(size),
                         "terms": _terms(res, builds), "phases": {k: v["phases"] for k, v in res.items()},
                         "stats": {k: v["stats"] for k, v in res.items()}, "bvh_build_ms": builds,
                         "phase_io": {k: v["phase_io"] for k, v in res.items()},
                         "io": {k: v["io"] for k, v in res.items()}})
    md = ["# Thesis Table 4.1 analog: primary + shadow rays, one point light (ms per frame, medians)", "",
          f"Command: `{args.command_line}`", ""]
    head = ["scene", "size", "backend", "prim. DS build", "prim. trace", "shadow DS build", "rearrange",
            "shadow trace", "total", "fps", "total w/o build"]
    body = []
    for r in rows:
        for b in BACKENDS:
            t = r["terms"][b]
            no_build = t["total"] - t["primary_build"] if b in ("clbvh", "glsl") else t["total"]
            body.append([r["scene"], size_text(tuple(r["size"])), b, fmt(t["primary_build"]), fmt(t["primary_trace"]),
                         fmt(t["shadow_build"]), fmt(t["rearrange"]), fmt(t["shadow_trace"]), fmt(t["total"]),
                         fmt(1e3 / t["total"] if t["total"] > 0 else float("nan"), 2), fmt(no_build)])
    md.append(md_table(head, body))
    md += ["", "DS build of clbvh / glsl: the per-frame BVH build a dynamic scene needs (binary SAH build; clbvh "
           "adds the BVH4 collapse), measured on the CPU apart from the frames; 'total w/o build' leaves it out.",
           "", "## Ratios and counters", ""]
    head = ["scene", "size", "ugrid/pgrid total", "pgrid shadow trace / clbvh", "ugrid pairs", "camera-grid pairs",
            "light-grid pairs", "culled (camera)", "chunks (shadow)", "chunk occupancy", "shadow rays outside",
            "hard pass (light grid)", "soft pass (uniform grid)"]
    body = []
    for r in rows:
        t, st = r["terms"], r["stats"]
        ps = st.get("pgrid", {})
        nan = float("nan")
        body.append([r["scene"], size_text(tuple(r["size"])),
                     fmt(t["ugrid"]["total"] / max(t["pgrid"]["total"], 1e-9), 2),
                     fmt(t["pgrid"]["shadow_trace"] / max(t["clbvh"]["shadow_trace"], 1e-9), 2),
                     fmt(st.get("ugrid", {}).get("grid_pairs", nan), 0),
                     fmt(ps.get("pairs_primary", nan), 0), fmt(ps.get("pairs_shadows", nan), 0),
                     fmt(ps.get("culled_primary", nan), 0), fmt(ps.get("chunks_shadows", nan), 0),
                     fmt(ps.get("chunk_occupancy_shadows", nan), 2), fmt(ps.get("outside_rays_shadows", nan), 0),
                     fmt(t["pgrid"]["shadow_build"] + t["pgrid"]["rearrange"] + t["pgrid"]["shadow_trace"]),
                     fmt(t["pgrid"]["soft_trace"])])
    md.append(md_table(head, body))
    md += ["", "Hard pass: pgrid's light grid (build + rearrangement + trace) for the point light; soft pass: one "
           "area-light sample pass, which pgrid traces through its uniform grid (the rays do not meet in one point)."]
    md += ["", "## Build phases: time, launches and host waits (last frame)", ""]
    md.append(md_table(["scene", "size", "backend", "phase", "ms", "CL launches", "host syncs"],
                       build_phase_rows(rows)))
    md += ["", "Per-frame build and rearrangement phases of the grid backends: OpenCL kernel launches and host "
           "synchronisations issued inside each (viewer.iostats, counted by the profiler per phase), and the "
           "frame's totals ('frame')."]
    _plot_table41(rows, Path(args.out) / "table41.png")
    res = write_study(Path(args.out), "table41", {"rows": rows, "command": args.command_line}, "\n".join(md))
    res["rows"] = rows
    return res


def _is_build_phase(phase: str) -> bool:
    return any(t in phase for t in (":build", ":rearrange"))


def build_phase_rows(rows: list[dict]) -> list[list[str]]:
    """Table rows: per scene, size and grid backend, each build phase's ms, launches and syncs,
    then the frame's totals."""
    body = []
    for r in rows:
        for b in ("pgrid", "ugrid"):
            pio, ph = r.get("phase_io", {}).get(b, {}), r["phases"].get(b, {})
            for phase in sorted(k for k in pio if _is_build_phase(k)):
                body.append([r["scene"], size_text(tuple(r["size"])), b, phase, fmt(ph.get(phase, 0.0), 2),
                             str(pio[phase]["cl_launches"]), str(pio[phase]["host_syncs"])])
            io = r.get("io", {}).get(b)
            if io:
                body.append([r["scene"], size_text(tuple(r["size"])), b, "frame", "", str(io["cl_launches"]),
                             str(io["host_syncs"])])
    return body


def _plot_table41(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    fig, ax = figure(size=(10, 0.5 + 0.45 * len(rows) * len(BACKENDS)))
    labels, y = [], 0
    colors = {"primary_build": "#8da0cb", "primary_trace": "#1f4e9c", "shadow_build": "#fc8d62", "rearrange": "#e5c494",
              "shadow_trace": "#b2182b"}
    for r in rows:
        for b in BACKENDS:
            left = 0.0
            for k, c in colors.items():
                v = r["terms"][b][k]
                ax.barh(y, v, left=left, color=c, label=k if y == 0 else None)
                left += v
            labels.append(f"{r['scene']} {size_text(tuple(r['size']))} {b}")
            y += 1
    ax.set_yticks(range(len(labels)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("ms per frame")
    ax.legend(fontsize=7)
    finish(fig, path, "Table 4.1 analog: primary + shadow frame terms")


# ---------------------------------------------------------------------------------------- lightdist


def study_lightdist(args, ctx) -> dict:
    from viewer.scene import PointLight

    name = args.light_scene
    if name not in SCENES:
        raise RtwalkError(f"--light-scene: unknown {name} (choose from {', '.join(SCENES)})")
    prep, cam = load_scene(args, name)
    lo, hi = prep.scene.bounds
    centre = (lo.astype(np.float64) + hi) / 2
    diag = prep.scene.diagonal
    l0 = prep.scene.point_lights[0]
    axis = l0.position.astype(np.float64) - centre
    axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0 else np.array([0.0, 1.0, 0.0])
    dists = parse_distances(args.distances)
    size = parse_image_sizes(args.sizes, "--sizes")[0]
    extra = args.pgrid_params
    # a fixed angular resolution (as the thesis's grid): tiles fill up as the light recedes, which is
    # what chunking is for (automatic tiling would keep ~tile_rays rays per tile at every distance)
    fixed = f"tile_deg={args.light_tile_deg}"
    configs = {f"chunk={c}": ("pgrid", ",".join(x for x in (f"chunk={c}", fixed, extra) if x)) for c in (64, 128, 256)}
    configs["no balancing"] = ("pgrid", ",".join(x for x in ("chunk=64,balance=false", fixed, extra) if x))
    configs["clbvh"] = ("clbvh", "")
    rows = []
    for k in dists:
        pos = (centre + axis * k * diag).astype(np.float32)
        scene = dataclasses.replace(prep.scene, point_lights=[PointLight(pos, l0.intensity)])
        log(args, f"bench-pgrid: lightdist {name} distance {k} diagonals")
        res = run_interleaved(ctx, prep, cam, size, "shadows", configs, args.frames, scene=scene,
                              check=interrupt_check(args))
        row = {"distance": k, "light": pos.tolist(), "configs": {}}
        for label, v in res.items():
            ph = v["phases"]
            row["configs"][label] = {"build": ph.get("pgrid:build:shadows", 0.0),
                                     "rearrange": ph.get("pgrid:rearrange:shadows", 0.0),
                                     "trace": ph.get("trace:shadows", 0.0), "stats": v["stats"]}
            row["configs"][label]["total"] = sum(row["configs"][label][x] for x in ("build", "rearrange", "trace"))
        rows.append(row)
    labels = list(configs)
    md = [f"# Thesis Figure 4.9 analog: shadow time vs light distance ({name}, {size_text(size)}, ms, medians)", "",
          f"Command: `{args.command_line}`", "",
          md_table(["distance (diagonals)"] + [f"{lb} total" for lb in labels] + ["chunk=64 trace", "chunk=64 chunks",
                                                                                 "chunk=64 occupancy"],
                   [[fmt(r["distance"], 2)] + [fmt(r["configs"][lb]["total"]) for lb in labels]
                    + [fmt(r["configs"]["chunk=64"]["trace"]),
                       fmt(r["configs"]["chunk=64"]["stats"].get("chunks", float("nan")), 0),
                       fmt(r["configs"]["chunk=64"]["stats"].get("chunk_occupancy", float("nan")), 2)] for r in rows])]
    fig, ax = figure(size=(7, 4))
    for lb in labels:
        ax.plot([r["distance"] for r in rows], [r["configs"][lb]["total"] for r in rows], marker="o", label=lb)
    ax.set_xscale("log")
    ax.set_xlabel("light distance from the model centre (scene diagonals)")
    ax.set_ylabel("shadow ms (build + rearrange + trace)")
    ax.legend(fontsize=8)
    finish(fig, Path(args.out) / "lightdist.png", f"Figure 4.9 analog ({name})")
    return write_study(Path(args.out), "lightdist", {"rows": rows, "command": args.command_line}, "\n".join(md))


# -------------------------------------------------------------------------------------------- model


def model_totals(t: dict[str, dict[str, float]], lights: np.ndarray, passes: np.ndarray) -> dict[str, np.ndarray]:
    """Frame time of each method for L lights and B secondary passes, from the measured terms:
    BVH: build + primary + L shadow + B secondary traversals; uniform grid: build + the same;
    pgrid: camera grid + primary, per light (light grid + rearrangement + shadow traversal), and
    the uniform grid (built once when B > 0) for the secondary passes."""
    out = {}
    for b in ("clbvh", "glsl"):
        v = t[b]
        out[b] = v["primary_build"] + v["primary_trace"] + lights * v["shadow_trace"] + passes * v["secondary_trace"]
    v = t["ugrid"]
    out["ugrid"] = v["primary_build"] + v["primary_trace"] + lights * v["shadow_trace"] + passes * v["secondary_trace"]
    v = t["pgrid"]
    out["pgrid"] = (v["primary_build"] + v["primary_trace"] + lights * (v["shadow_build"] + v["rearrange"]
                    + v["shadow_trace"]) + (passes > 0) * v["secondary_build"] + passes * v["secondary_trace"])
    return out


def study_model(args, table41: dict | None) -> dict:
    if not table41:
        raise RtwalkError("the model study needs table41 in the same run (--study table41,model)")
    rows = table41["rows"]
    lights = np.arange(0, 17, dtype=np.float64)
    md = ["# Thesis Figures 4.10 / 5.5 analog: cost model from the measured terms", "",
          f"Command: `{args.command_line}`", "",
          "Break-even: the smallest number of lights (no secondary pass) and of secondary passes (one light) "
          "at which a per-frame clbvh build + traversal is faster than pgrid's per-pass grids ('-': not within 64).",
          ""]
    body = []
    fig, axes = figure(1, 2, size=(11, 4))
    for r in rows:
        t = r["terms"]
        big = np.arange(0, 65, dtype=np.float64)
        by_l = model_totals(t, big, np.zeros_like(big))
        by_b = model_totals(t, np.ones_like(big), big)
        win_l = np.flatnonzero(by_l["clbvh"] < by_l["pgrid"])
        win_b = np.flatnonzero(by_b["clbvh"] < by_b["pgrid"])
        body.append([r["scene"], size_text(tuple(r["size"])), fmt(t["pgrid"]["total"]), fmt(t["clbvh"]["total"]),
                     str(int(big[win_l[0]])) if len(win_l) else "-", str(int(big[win_b[0]])) if len(win_b) else "-"])
        lab = f"{r['scene']} {size_text(tuple(r['size']))}"
        m = model_totals(t, lights, np.zeros_like(lights))
        axes[0].plot(lights, m["pgrid"], label=f"pgrid {lab}")
        axes[0].plot(lights, m["clbvh"], "--", label=f"clbvh+build {lab}")
        m = model_totals(t, np.ones_like(lights), lights)
        axes[1].plot(lights, m["pgrid"], label=f"pgrid {lab}")
        axes[1].plot(lights, m["clbvh"], "--", label=f"clbvh+build {lab}")
    md.append(md_table(["scene", "size", "pgrid 1 light ms", "clbvh+build 1 light ms", "break-even lights",
                        "break-even secondary passes"], body))
    axes[0].set_xlabel("point lights (no secondary pass)")
    axes[1].set_xlabel("secondary passes (one light)")
    for ax in axes:
        ax.set_ylabel("ms per frame (model)")
        ax.legend(fontsize=6)
    finish(fig, Path(args.out) / "model.png", "Cost model: per-frame BVH vs per-pass grids")
    return write_study(Path(args.out), "model", {"rows": body, "command": args.command_line}, "\n".join(md))


# ---------------------------------------------------------------------------------------------- run


def parse_distances(text: str) -> list[float]:
    """--distances: finite numbers > 0 (scene diagonals), at least one."""
    try:
        dists = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        dists = []
    if not dists or not all(math.isfinite(d) and d > 0 for d in dists):
        raise RtwalkError(f"--distances: expected a comma list of numbers > 0 (got '{text}')")
    return dists


def check_scene_args(args) -> None:
    """The city's size, the light study's scene and distances and --pgrid-params, before any study
    runs (a bad one used to surface only when its study came, after the earlier ones' minutes)."""
    from viewer.backends import check_params
    from viewer.scene_io import check_builtin_size

    check_builtin_size("city", args.city_size, "--city-size")
    if args.light_scene not in SCENES:
        raise RtwalkError(f"--light-scene: unknown {args.light_scene} (choose from {', '.join(SCENES)})")
    parse_distances(args.distances)
    if args.pgrid_params:
        check_params("pgrid", args.pgrid_params, "--pgrid-params")


def run(args) -> int:
    from viewer.cl import cl_context
    from viewer.gl.context import shared_context

    wanted = parse_choices(args.study, STUDIES, "--study")
    studies = [s for s in STUDIES if s in wanted]  # table41 before the studies built on it
    parse_choices(args.scenes, SCENES, "--scenes")
    parse_image_sizes(args.sizes, "--sizes")
    if not 0 < args.light_tile_deg <= 90:
        raise RtwalkError("--light-tile-deg must be in (0, 90]")
    if args.frames < 1 or args.anim_frames < 1:
        raise RtwalkError("--frames and --anim-frames must be >= 1")
    if ("model" in studies or "rearrange" in studies) and "table41" not in studies:
        raise RtwalkError("--study: model and rearrange need table41 in the same run")
    args.anim_size = parse_image_sizes(args.anim_size, "--anim-size")[0]
    check_scene_args(args)
    check_output_dir(args.out, "--out")
    check_report_free([Path(args.out) / f"{s}.json" for s in studies], getattr(args, "force", False))
    cl_context()
    ctx = shared_context()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    t41 = None
    with keep_partial("bench-pgrid", defer=True) as part:  # Ctrl-C: stop between frames, keep the studies done
        args.partial_run = part
        for s in studies:
            part.started(s)
            res = _one_study(args, ctx, s, t41)
            t41 = res if s == "table41" else t41
            part.finished(res["json"])
            print(res["markdown"], flush=True)
    return 0


def _one_study(args, ctx, s: str, t41: dict | None) -> dict:
    """One study of `run` (model and rearrange read table41's result)."""
    if s == "table41":
        return study_table41(args, ctx)
    if s == "lightdist":
        return study_lightdist(args, ctx)
    if s == "model":
        return study_model(args, t41)
    if s == "pairs":
        log(args, "bench-pgrid: pairs")
        return study_pairs(args, load_scene, parse_image_sizes(args.sizes, "--sizes"),
                           parse_choices(args.scenes, SCENES, "--scenes"))
    if s == "rearrange":
        return study_rearrange(args, t41)
    log(args, "bench-pgrid: anim")
    return study_anim(args)

"""Voxel tracing study (Chajdas & Westermann analog): `rtwalk bench-voxels`.

Per scene: one frame's rays are captured with an exact backend (--reference, default clbvh:
primary, shadows, soft, ao with AO length 1/3 of the scene's largest extent, as in the paper).
Per resolution the scene is voxelized (voxels, seconds, MiB) and each structure built (node
sizes, mean leaf depth and its variance, MiB). Then, on the very same rays:

  * time: each structure's trace kernel per ray type over every pass (wall ms around enqueue +
    finish, median over --rounds rounds), for each --stacks size; structures and stacks take
    turns pass by pass (the order rotates) so a change in machine load hits them alike;
  * coherency: the recording kernel writes each ray's steps in order; lockstep.cl reduces them on
    the device to the SIMD lane utilisation of lockstep groups of W = 8, 32, 64 consecutive rays
    (viewer.bench.lockstep defines it), plus restarts (stack overflows) and steps per ray. With
    --record-passes K only K evenly spaced whole passes of each multi-pass ray type are recorded
    (pick_passes; utilisation is a per-pass statistic, so whole passes are an unbiased sample);
    the passes used and the recorded ray count are in the output, nothing is scaled;
  * error (first structure, largest stack, every ray, read from the timed kernel's output):
    hit/miss disagreement with the reference backend, mean |t - t_ref| in voxel widths where both
    hit, the reference's time on the same rays; and the image of a full render with the voxels
    backend against the reference backend's image (mean absolute pixel error, 0..255).

Finished resolutions are written at once (bench_voxels.* with "complete": false) so a late error
loses no finished work. Host memory: the frame's rays live once, in CL buffers.

Output in --out: bench_voxels.json (everything), bench_voxels.md (tables: 1 and 2 analogs,
stack 4 vs 8, structures, voxelization, speed against error) and bench_voxels.png (speed
against error).
"""

from __future__ import annotations

import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from viewer.bench.common import log
from viewer.cl import io as clio
from viewer.errors import RtwalkError
from viewer.paths import SHARED_SCENES

SCENES = {"conference": "conference/conference.ply", "buddha": "buddha/buddha_100k.obj",
          "dragon": "dragon/dragon_100k.ply", "sponza": "sponza-dabrovic/sponza.obj",
          "sibenik": "sibenik/sibenik.obj", "bunny": "bunny/bun_zipper.ply"}
RECORDINGS = {"conference": "conference-walk.json", "sponza": "sponza-walk.json", "sibenik": "sibenik-walk.json"}
WIDTHS = (8, 32, 64)
RAY_TYPES = ("primary", "shadows", "soft", "ao")
CHUNK = 1 << 15  # rays per recording launch (a multiple of every W)


HELP = "voxel BVH / KD-tree / octree: coherency, time, stack 4 vs 8, speed against error"


def add_arguments(p) -> None:
    p.add_argument("--scenes", default="conference,buddha,dragon,sponza",
                   help="comma-separated: conference, buddha, dragon, sponza, sibenik, bunny, room, city, or files")
    p.add_argument("--resolutions", default="64,128,256", help="voxel grid sizes, powers of two")
    p.add_argument("--structures", default="bvh,kd,octree", help="voxel structures to trace (bvh, kd, octree)")
    p.add_argument("--stacks", default="4,8", help="short-stack sizes to compare")
    p.add_argument("--size", default="640x360", help="WxH (the paper: 1280x720)")
    p.add_argument("--effects", default="primary,shadows,soft:4,ao:4",
                   help="ray types and samples per pixel (the paper: soft:36, ao:36)")
    p.add_argument("--reference", default="clbvh", help="exact backend that generates the rays and judges")
    p.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds")
    p.add_argument("--bias", type=float, default=1.5,
                   help="secondary rays start this many voxel widths along the ray (the backend's bias)")
    p.add_argument("--seq-len", type=int, default=1024, help="steps per ray kept for the lockstep model")
    p.add_argument("--record-passes", type=int, default=0, metavar="K",
                   help="coherency (lane utilisation, steps, restarts) from K evenly spaced passes of each "
                        "multi-pass ray type (soft, ao); 0 = every pass. Times and errors always use every pass")
    p.add_argument("--no-image", action="store_true", help="skip the full-render image error")
    p.add_argument("--voxelize-only", action="store_true",
                   help="only voxelize and build the structures per resolution (count, time, memory, depth)")
    p.add_argument("--out", default="out/bench-voxels", help="folder for bench_voxels.json/.md/.png")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _ints(text: str, what: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise RtwalkError(f"--{what}: expected comma-separated integers (got '{text}')") from None


def _scene_spec(name: str) -> tuple[str, str, str | None]:
    if name in ("room", "city"):  # built-in scenes
        return name, name, None
    if name in SCENES:
        path = SHARED_SCENES / SCENES[name]
        if not path.exists():
            raise RtwalkError(f"--scenes: {path} not present")
        return name, str(path), RECORDINGS.get(name)
    if not Path(name).exists():
        raise RtwalkError(f"--scenes: unknown scene '{name}' (choose from {', '.join(SCENES)} or give a file)")
    return Path(name).stem, name, None


class _Rays:
    """One captured pass in CL buffers (active rays only, in pixel order) plus what the error rows
    need of the reference hits: hit or miss, and t for closest-hit rays. `index`: the pass's place
    among the passes of its ray type (capture order)."""

    def __init__(self, ctx, p, ref_hits, index: int):
        a = p.active
        self.label, self.any_hit, self.n, self.index = p.label, p.any_hit, int(a.sum()), index
        self.sample, self.light = p.sample, p.light
        self.o_b = clio.upload(ctx, np.ascontiguousarray(p.origin4.reshape(-1, 4)[a]))
        self.d_b = clio.upload(ctx, np.ascontiguousarray(p.dir4.reshape(-1, 4)[a]))
        self.ref_hit = ref_hits[1][a] >= 0
        self.ref_t = None if self.any_hit else ref_hits[0][a].astype(np.float32)

    def release(self) -> None:
        self.o_b.release()
        self.d_b.release()


def _capture(renderer, camera) -> list:
    """Every pass of one frame with active rays, as texel arrays (time_backend's input); each
    captured pass is dropped once converted, so only one copy of the frame's rays is held."""
    from types import SimpleNamespace

    rep = renderer.render(camera, capture=True)
    w, h = renderer.size
    out = []
    cap = rep.captured
    cap.reverse()
    while cap:
        cp = cap.pop()
        r = cp.rays
        active = r.active & np.isfinite(r.origins).all(1) & np.isfinite(r.directions).all(1)
        if not active.any() or cp.ray_type.label not in RAY_TYPES:
            continue
        o4 = np.concatenate([r.origins, r.tmin[:, None]], 1).astype(np.float32).reshape(h, w, 4)
        d4 = np.concatenate([r.directions, r.tmax[:, None]], 1).astype(np.float32).reshape(h, w, 4)
        out.append(SimpleNamespace(label=cp.ray_type.label, any_hit=cp.ray_type.any_hit, ray_type=cp.ray_type,
                                   sample=cp.sample, light=cp.light, origin4=o4, dir4=d4, active=active))
        del cp, r
    return out


def pick_passes(m: int, k: int) -> list[int]:
    """Indices of the passes recorded out of m: all when k <= 0 or k >= m, else the middle pass of
    each of k equal strata, floor((i + 1/2) m / k) for i < k (deterministic, evenly spaced)."""
    if k <= 0 or k >= m:
        return list(range(m))
    return [int((2 * i + 1) * m // (2 * k)) for i in range(k)]


def _time_kernel(ctx, tracer, rays: _Rays, outs, bias: float) -> float:
    t0 = time.perf_counter()
    tracer.enqueue(rays.o_b, rays.d_b, *outs, rays.n, rays.any_hit, bias)
    clio.finish(ctx.queue)
    return (time.perf_counter() - t0) * 1e3


class _Recorder:
    """Step recording of whole passes in chunks of CHUNK rays, reduced on the device (lockstep.cl):
    per pass the step counts by kind, the steps cut off past --seq-len, and the lane sums per W."""

    def __init__(self, ctx, seq_len: int):
        from viewer.bench.lockstep import DeviceLockstep

        cl = ctx.cl
        mf = cl.mem_flags
        self.ctx, self.seq_len = ctx, seq_len
        self.seq = cl.Buffer(ctx.context, mf.READ_WRITE, CHUNK * seq_len)
        self.rec = cl.Buffer(ctx.context, mf.READ_WRITE, CHUNK * 16)
        self.outs = [cl.Buffer(ctx.context, mf.READ_WRITE, CHUNK * 4) for _ in range(3)]
        self.rec_host = np.empty((CHUNK, 4), np.int32)
        self.lock = DeviceLockstep(ctx, CHUNK, max(WIDTHS))

    def __call__(self, tracer, rays: _Rays, bias: float) -> dict:
        from viewer.bench.lockstep import combine

        _cl, q = self.ctx.cl, self.ctx.queue
        parts: dict = {w: [] for w in WIDTHS}
        counts = np.zeros(4, np.int64)
        cut = 0
        for s in range(0, rays.n, CHUNK):
            m = min(CHUNK, rays.n - s)
            o = rays.o_b.get_sub_region(16 * s, 16 * m)
            d = rays.d_b.get_sub_region(16 * s, 16 * m)
            tracer.enqueue(o, d, *self.outs, m, rays.any_hit, bias, self.rec, self.seq)
            for w in WIDTHS:
                parts[w].append(self.lock(self.seq, self.rec, m, self.seq_len, w))
            rec = self.rec_host[:m]
            clio.copy(q, rec, self.rec)
            clio.finish(q)
            o.release()
            d.release()
            counts += rec.sum(axis=0, dtype=np.int64)
            cut += int(np.maximum(rec.sum(axis=1, dtype=np.int64) - self.seq_len, 0).sum())
        return {"pass": rays.index, "sample": rays.sample, "light": rays.light, "rays": rays.n,
                "steps": counts.tolist(), "cut_steps": cut, "lanes": {w: combine(parts[w], w) for w in WIDTHS}}

    def release(self) -> None:
        for b in (self.seq, self.rec, *self.outs):
            b.release()
        self.lock.release()


def _record_label(per_pass: list[dict], of_passes: int) -> dict:
    """A ray type's record from its recorded passes: sums, utilisation of the pooled groups."""
    from viewer.bench.lockstep import combine

    steps = np.sum([r["steps"] for r in per_pass], axis=0)
    nr = sum(r["rays"] for r in per_pass)
    return {"interior": int(steps[0]), "leaf": int(steps[1]), "pop": int(steps[2]), "restarts": int(steps[3]),
            "rays": nr, "passes": [r["pass"] for r in per_pass], "of_passes": of_passes,
            "steps_per_ray": float(steps.sum() / nr) if nr else float("nan"),
            "cut_steps": int(sum(r["cut_steps"] for r in per_pass)),
            "lanes": {w: combine([r["lanes"][w] for r in per_pass], w) for w in WIDTHS}, "per_pass": per_pass}


class _ErrorSums:
    """Hit/miss disagreement and |t - t_ref| (voxel widths) against the reference, pass by pass,
    from the hits the timed kernel wrote (no extra trace)."""

    def __init__(self):
        self.n = 0
        self.disagree = self.voxel_only = self.reference_only = 0
        self.dt: list = []

    def add(self, ctx, outs, rays: _Rays, scale: float) -> None:
        t = np.empty(rays.n, np.float32)
        tri = np.empty(rays.n, np.int32)
        clio.copy(ctx.queue, t, outs[0])
        clio.copy(ctx.queue, tri, outs[1])
        clio.finish(ctx.queue)
        hv, hr = tri >= 0, rays.ref_hit
        self.n += rays.n
        self.disagree += int(np.count_nonzero(hv != hr))
        self.voxel_only += int(np.count_nonzero(hv & ~hr))
        self.reference_only += int(np.count_nonzero(~hv & hr))
        if rays.ref_t is not None:  # any hit: the distance is of whichever hit was found first, not comparable
            both = hv & hr
            self.dt.append(np.abs(t[both].astype(np.float64) - rays.ref_t[both]) * scale)

    def result(self) -> dict:
        dt = np.concatenate(self.dt) if self.dt else np.zeros(0)
        n = max(self.n, 1)
        return {"rays": self.n, "hitmiss_disagree": self.disagree / n, "voxel_only": self.voxel_only / n,
                "reference_only": self.reference_only / n,
                "t_err_voxels_mean": float(dt.mean()) if dt.size else float("nan"),
                "t_err_voxels_median": float(np.median(dt)) if dt.size else float("nan"),
                "t_err_voxels_p90": float(np.percentile(dt, 90)) if dt.size else float("nan")}


def _median(xs) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


class _Clock:
    """Elapsed seconds for the progress lines."""

    def __init__(self):
        self.t0 = time.perf_counter()

    def __str__(self) -> str:
        return f"[{time.perf_counter() - self.t0:7.1f} s]"


def study_scene(args, ctx_gl, name: str, spec: str, recording: str | None, size, resolutions, structures,
                stacks, checkpoint=None) -> dict:
    """One scene: capture, reference time, then per resolution voxelize, build, time, record, errors.
    `checkpoint(out)` is called after each finished resolution with the scene's results so far."""
    from viewer.backends.voxels import voxels_for
    from viewer.backends.voxels.scene import VoxelTracer, build_structure
    from viewer.bench.trace_vs_embree import time_backend
    from viewer.cl import cl_context
    from viewer.effects import parse_effects
    from viewer.paths import RECORDINGS as RECORDING_FOLDER
    from viewer.recording import load_recording
    from viewer.renderer import Renderer
    from viewer.session import prepare_scene

    clock = _Clock()
    prep = prepare_scene(spec, quiet=True)
    scene = prep.scene
    lo, hi = scene.bounds
    settings = parse_effects(args.effects)
    settings.ao_length = float(np.max(hi - lo)) / 3 / scene.diagonal  # 1/3 of the scene size (the paper)
    camera = scene.default_camera
    if recording and (RECORDING_FOLDER / recording).exists():
        rec = load_recording(RECORDING_FOLDER / recording)
        camera = rec.camera_for_frame(rec.frame_count() // 2)
    prepared = {}  # before the frame's rays are held: the builds' working memory does not add to them
    for res in resolutions:
        vox = voxels_for(scene.triangles, res, quiet=args.quiet)
        log(args, f"{clock} {name} {res}^3: {vox.count:,} voxels in {vox.stats['seconds']:.1f} s")
        built = {}
        for kind in structures:
            built[kind] = build_structure(kind, vox)
            log(args, f"{clock} {name} {res}^3 {kind}: built in {built[kind].stats['build_seconds']:.1f} s, "
                       f"{built[kind].stats['memory_bytes'] / 2**20:.0f} MiB")
        prepared[res] = (dict(vox.stats), vox.grid, built)
        del vox, built
    log(args, f"{clock} {name}: {scene.triangle_count:,} triangles; capturing one frame at {size[0]}x{size[1]}")
    r = Renderer(ctx_gl, scene, prep.bvh, size, args.reference, settings)
    ctx = cl_context()
    try:
        passes = _capture(r, camera)
        log(args, f"{clock} {name}: {len(passes)} passes captured; timing {args.reference}")
        ref_ms: dict = {}
        hits = None
        for rd in range(args.rounds):
            hits = None
            tr_ms, _, _, hits = time_backend(r, args.reference, passes)
            per: dict = {}
            for p, ms in zip(passes, tr_ms, strict=True):
                per[p.label] = per.get(p.label, 0.0) + ms
            for lb, ms in per.items():
                ref_ms.setdefault(lb, []).append(ms)
            log(args, f"{clock} {name}: {args.reference} round {rd + 1}/{args.rounds}: "
                       + ", ".join(f"{lb} {ms:.0f} ms" for lb, ms in per.items()))
        ref_image = None
        if not args.no_image:
            r.render(camera)
            ref_image = r.read_image().astype(np.float64)
        seen: dict = {}
        rays = []
        for i, p in enumerate(passes):  # to the CL device pass by pass, dropping the host copies
            rays.append(_Rays(ctx, p, hits[i], seen.get(p.label, 0)))
            seen[p.label] = seen.get(p.label, 0) + 1
            p.origin4 = p.dir4 = None
            hits[i] = None
        del passes, hits
    finally:
        r.release()
    labels = list(dict.fromkeys(x.label for x in rays))
    n_pass = {lb: sum(x.label == lb for x in rays) for lb in labels}
    picked = {lb: pick_passes(n_pass[lb], args.record_passes) for lb in labels}
    ref_time = {lb: _median(ref_ms[lb]) for lb in labels}
    out: dict = {"scene": name, "triangles": scene.triangle_count, "size": list(size), "effects": args.effects,
                 "rays": {lb: sum(x.n for x in rays if x.label == lb) for lb in labels}, "passes": n_pass,
                 "recorded_passes": picked, "reference": args.reference, "reference_ms": ref_time,
                 "resolutions": []}
    log(args, f"{clock} {name}: rays {out['rays']}; coherency recorded on passes "
               + ", ".join(f"{lb} {len(picked[lb])}/{n_pass[lb]}" for lb in labels))
    maxn = max(x.n for x in rays)
    cl = ctx.cl
    outs = [cl.Buffer(ctx.context, cl.mem_flags.READ_WRITE, 4 * maxn) for _ in range(3)]
    recorder = _Recorder(ctx, args.seq_len)
    try:
        for res in resolutions:
            vox_stats, g, built = prepared.pop(res)
            rrow: dict = {"resolution": res, "voxelize": vox_stats,
                          "structures": {kind: {"stats": dict(built[kind].stats), "stacks": {}} for kind in structures}}
            configs = [(kind, k) for kind in structures for k in stacks]
            err_cfg = (structures[0], max(stacks))
            tracers = {c: VoxelTracer(built[c[0]], g.origin, g.scale, c[1], ctx=ctx) for c in configs}
            for c in configs:  # PoCL compiles the work-group function at the first launch: not timed
                _time_kernel(ctx, tracers[c], rays[0], outs, 0.0)
            times = {c: {lb: [] for lb in labels} for c in configs}
            errs = {lb: _ErrorSums() for lb in labels}
            for rd in range(args.rounds):
                per = {c: {lb: 0.0 for lb in labels} for c in configs}
                last = time.perf_counter()
                for i, x in enumerate(rays):  # configs rotate per pass: load changes hit them all alike
                    rot = (rd + i) % len(configs)
                    for c in configs[rot:] + configs[:rot]:
                        per[c][x.label] += _time_kernel(ctx, tracers[c], x, outs, _bias(args, x.label))
                        if rd == 0 and c == err_cfg:
                            errs[x.label].add(ctx, outs, x, g.scale)
                    if time.perf_counter() - last > 30 or i == len(rays) - 1:
                        last = time.perf_counter()
                        log(args, f"{clock} {res}^3 timing round {rd + 1}/{args.rounds}: pass {i + 1}/{len(rays)} "
                                   f"({x.label})")
                for c in configs:
                    for lb in labels:
                        times[c][lb].append(per[c][lb])
            rrow["errors"] = {lb: errs[lb].result() for lb in labels}
            rrow["errors_from"] = {"structure": err_cfg[0], "stack": err_cfg[1]}
            for c in configs:
                tracers[c].release()
            for kind, k in configs:
                rec_tr = VoxelTracer(built[kind], g.origin, g.scale, k, record=True, ctx=ctx, seq_len=args.seq_len)
                krow: dict = {"ms": {lb: _median(times[(kind, k)][lb]) for lb in labels},
                              "ms_rounds": times[(kind, k)], "record": {}}
                for lb in labels:
                    sel = [x for x in rays if x.label == lb and x.index in picked[lb]]
                    krow["record"][lb] = _record_label([recorder(rec_tr, x, _bias(args, lb)) for x in sel],
                                                       n_pass[lb])
                rec_tr.release()
                rrow["structures"][kind]["stacks"][k] = krow
                log(args, f"{clock} {res}^3 {kind} stack {k}: " + ", ".join(
                    f"{lb} {krow['ms'][lb]:.0f} ms U64 {100 * krow['record'][lb]['lanes'][64]['utilisation']:.0f}%"
                    for lb in labels))
            del built
            if ref_image is not None:
                rrow["image_mae"] = _image_error(ctx_gl, prep, size, settings, camera, res, structures[0],
                                                 max(stacks), ref_image, args.bias)
                log(args, f"{clock} {res}^3: image error {rrow['image_mae']:.2f} (full render, {structures[0]})")
            out["resolutions"].append(rrow)
            if checkpoint is not None:
                checkpoint(out)
    finally:
        recorder.release()
        for b in outs:
            b.release()
        for x in rays:
            x.release()
    return out


def _bias(args, label: str) -> float:
    """Secondary rays start --bias voxel widths along the ray, as the backend's `bias` does."""
    return 0.0 if label == "primary" else float(args.bias)


def _image_error(ctx_gl, prep, size, settings, camera, res: int, structure: str, stack: int, ref_image,
                 bias: float) -> float:
    from viewer.renderer import Renderer

    r = Renderer(ctx_gl, prep.scene, prep.bvh, size, "voxels", settings,
                 backend_options={"voxels": f"structure={structure},resolution={res},stack={stack},bias={bias}"})
    try:
        r.render(camera)
        img = r.read_image().astype(np.float64)
    finally:
        r.release()
    return float(np.abs(img - ref_image).mean())


def _markdown(report: dict) -> str:
    from viewer.bench.lockstep import __doc__ as lockstep_doc

    scenes = report["scenes"]
    structures = report["structures"]
    stacks = report["stacks"]
    big = max(stacks)
    lines = [f"# Voxel ray tracing: BVH, KD-tree, octree ({report['device_cl']})", "",
             f"Command: `{report['command']}`", "",
             "Rays: one frame per scene captured with the reference backend; every structure traces the same rays. "
             f"Times: wall ms of the trace kernel over every pass (median of {report.get('rounds', '?')} "
             "interleaved round(s); structures and stacks rotate pass by pass). Coherency: SIMD lane utilisation "
             "U_W of lockstep groups of W consecutive rays (definition below), with steps per ray and restarts, "
             "measured on the recorded passes below; hit errors on every ray.", ""]
    if not report.get("complete", True):
        lines += ["**Partial: the study is still running or stopped early; finished resolutions only.**", ""]
    for sc in scenes:
        rp = sc.get("recorded_passes", {})
        lines.append(f"- {sc['scene']}: coherency from " + "; ".join(
            f"{lb} {len(rp[lb])} of {sc['passes'][lb]} passes"
            + (f" ({', '.join(map(str, rp[lb]))})" if len(rp[lb]) < sc["passes"][lb] else "")
            for lb in RAY_TYPES if lb in rp))
    lines.append("")
    for res in report["resolutions"]:
        for w in (64, 32, 8):
            lines += [f"## Table 1 analog: coherency U_{w} (%) at {res}^3, stack {big}", "",
                      "| scene | structure | " + " | ".join(RAY_TYPES) + " |", "|---|---|" + "---|" * len(RAY_TYPES)]
            avg: dict = {}
            for sc in scenes:
                rr = next((x for x in sc["resolutions"] if x["resolution"] == res), None)
                if rr is None:
                    continue
                for kind in structures:
                    rec = rr["structures"][kind]["stacks"][big]["record"]
                    vals = [100 * rec[lb]["lanes"][w]["utilisation"] if lb in rec else float("nan") for lb in RAY_TYPES]
                    avg.setdefault(kind, []).append(vals)
                    lines.append(f"| {sc['scene']} | {kind} | " + " | ".join(f"{v:.1f}" for v in vals) + " |")
            for kind, v in avg.items():
                with warnings.catch_warnings():  # a ray type absent from every scene: nan, no warning
                    warnings.simplefilter("ignore", RuntimeWarning)
                    mean = np.nanmean(v, axis=0)
                lines.append(f"| **average** | {kind} | " + " | ".join(f"{x:.1f}" for x in mean) + " |")
            lines.append("")
        lines += [f"## Table 2 analog: trace time (ms) at {res}^3, stack {big}, reference = {report['reference']}", "",
                  "| scene | structure | " + " | ".join(RAY_TYPES) + " |", "|---|---|" + "---|" * len(RAY_TYPES)]
        for sc in scenes:
            rr = next((x for x in sc["resolutions"] if x["resolution"] == res), None)
            if rr is None:
                continue
            for kind in structures:
                ms = rr["structures"][kind]["stacks"][big]["ms"]
                lines.append(f"| {sc['scene']} | {kind} | " + " | ".join(f"{ms.get(lb, float('nan')):.1f}"
                                                                        for lb in RAY_TYPES) + " |")
            lines.append(f"| {sc['scene']} | {report['reference']} (triangles) | " + " | ".join(
                f"{sc['reference_ms'].get(lb, float('nan')):.1f}" for lb in RAY_TYPES) + " |")
        head = " | ".join(f"restarts/1k s{k} | ms s{k}" for k in stacks)
        lines += ["", f"## Stack {' vs '.join(map(str, stacks))} at {res}^3: restarts per 1000 rays and time (ms)", "",
                  "Restarts: measured on the recorded passes (count / recorded rays); time: every pass.", "",
                  f"| scene | structure | ray type | {head} |",
                  "|---|---|---|" + "---|---|" * len(stacks)]
        for sc in scenes:
            rr = next((x for x in sc["resolutions"] if x["resolution"] == res), None)
            if rr is None:
                continue
            for kind in structures:
                for lb in RAY_TYPES:
                    if lb not in sc["rays"]:
                        continue
                    cells = []
                    for k in stacks:
                        kr = rr["structures"][kind]["stacks"][k]
                        q = kr["record"][lb]
                        cells += [f"{1000 * q['restarts'] / max(q.get('rays', sc['rays'][lb]), 1):.1f}",
                                  f"{kr['ms'][lb]:.1f}"]
                    lines.append(f"| {sc['scene']} | {kind} | {lb} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [f"## Steps per ray at stack {big} (interior / leaf / pop): what a scalar CPU work-item pays for", "",
              "| scene | res | structure | " + " | ".join(RAY_TYPES) + " |", "|---|---|---|" + "---|" * len(RAY_TYPES)]
    for sc in scenes:
        for rr in sc["resolutions"]:
            for kind in structures:
                rec = rr["structures"][kind]["stacks"][big]["record"]
                cells = []
                for lb in RAY_TYPES:
                    if lb not in rec:
                        cells.append("-")
                        continue
                    q = rec[lb]
                    n = max(q.get("rays", sc["rays"][lb]), 1)
                    cells.append(f"{q['interior'] / n:.1f} / {q['leaf'] / n:.1f} / {q['pop'] / n:.1f}")
                lines.append(f"| {sc['scene']} | {rr['resolution']} | {kind} | " + " | ".join(cells) + " |")
    lines += ["", "## Voxels and structures", "",
              "| scene | res | voxels | voxelize s | voxel MiB | structure | interior nodes x B | leaves x B | MiB | "
              "mean leaf depth | variance | build s |", "|" + "---|" * 12]
    for sc in scenes:
        for rr in sc["resolutions"]:
            v = rr["voxelize"]
            for kind in structures:
                s = rr["structures"][kind]["stats"]
                lines.append(f"| {sc['scene']} | {rr['resolution']} | {v['count']:,} | {v['seconds']:.2f} | "
                             f"{v['bytes'] / 2**20:.1f} | {kind} | {s['interior_nodes']:,} x {s['node_bytes']} | "
                             f"{s['leaves']:,} x {s['leaf_bytes']} | {s['memory_bytes'] / 2**20:.1f} | "
                             f"{s['mean_leaf_depth']:.2f} | {s['var_leaf_depth']:.2f} | {s['build_seconds']:.2f} |")
    lines += ["", f"## Speed against error ({structures[0]}, stack {big}) vs {report['reference']} on the same rays",
              "",
              "| scene | res | ray type | voxels ms | reference ms | hit/miss disagree | "
              "t error (voxels: median / mean) | image MAE (0-255) |", "|" + "---|" * 8]
    for sc in scenes:
        for rr in sc["resolutions"]:
            for lb in RAY_TYPES:
                if lb not in rr.get("errors", {}):
                    continue
                e = rr["errors"][lb]
                ms = rr["structures"][structures[0]]["stacks"][big]["ms"][lb]
                lines.append(f"| {sc['scene']} | {rr['resolution']} | {lb} | {ms:.1f} | {sc['reference_ms'][lb]:.1f} | "
                             f"{100 * e['hitmiss_disagree']:.2f}% | {_t_err(e, lb)} | "
                             f"{rr.get('image_mae', float('nan')):.2f} |")
    lines += ["", "## Lane utilisation: the model", "", "```", lockstep_doc.strip(), "```", ""]
    return "\n".join(lines)


def report_from_json(path: str | Path) -> dict:
    """A bench_voxels.json read back with its integer keys (stacks, widths) restored."""
    r = json.loads(Path(path).read_text())
    for sc in r["scenes"]:
        for rr in sc["resolutions"]:
            for s in rr["structures"].values():
                s["stacks"] = {int(k): v for k, v in s["stacks"].items()}
                for v in s["stacks"].values():
                    for rec in v["record"].values():
                        for q in [rec, *rec.get("per_pass", [])]:
                            q["lanes"] = {int(k): x for k, x in q["lanes"].items()}
    return r


def _t_err(e: dict, label: str) -> str:
    if label != "primary":  # any-hit ray types report no comparable distance
        return "-"
    return f"{e.get('t_err_voxels_median', float('nan')):.2f} / {e['t_err_voxels_mean']:.2f}"


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    big = max(report["stacks"])
    kind = report["structures"][0]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for sc in report["scenes"]:
        xs, ys, labels = [], [], []
        ref = sum(sc["reference_ms"].values())
        for rr in sc["resolutions"]:
            ms = sum(rr["structures"][kind]["stacks"][big]["ms"].values())
            xs.append(ms / ref)
            ys.append(rr.get("image_mae", np.nan))
            labels.append(str(rr["resolution"]))
        ax.plot(xs, ys, "o-", label=sc["scene"])
        for x, y, t in zip(xs, ys, labels, strict=True):
            ax.annotate(t, (x, y), fontsize=7)
    ax.axvline(1.0, color="grey", lw=0.8)
    ax.set_xlabel(f"voxel trace time / {report['reference']} time (same rays, all ray types)")
    ax.set_ylabel("image error vs reference (mean |pixel|, 0..255)")
    ax.set_xscale("log")
    ax.legend(fontsize=8)
    ax.set_title("voxels: speed against error, labels = resolution")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _voxelize_only(args, specs, resolutions: list[int], structures: list[str]) -> int:
    """Voxel count, time, output and peak process memory per resolution (ascending, so the peak
    resident size so far is the peak of the latest resolution), and each structure's statistics."""
    import resource

    from viewer.accel.voxelize import voxelize
    from viewer.backends.voxels.scene import build_structure
    from viewer.session import prepare_scene

    rows = []
    lines = ["| scene | triangles | res | voxels | voxelize s | voxels MiB | peak RSS MiB | structure | nodes x B | "
             "leaves x B | MiB | mean leaf depth | variance | build s |", "|" + "---|" * 14]
    for name, spec, _ in specs:
        scene = prepare_scene(spec, quiet=True).scene
        for res in resolutions:
            vox = voxelize(scene.triangles, res)
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            row = {"scene": name, "triangles": scene.triangle_count, **vox.stats, "peak_rss_mib": rss, "structures": {}}
            for kind in structures:
                st = build_structure(kind, vox).stats
                row["structures"][kind] = st
                lines.append(f"| {name} | {scene.triangle_count:,} | {res} | {vox.count:,} | "
                             f"{vox.stats['seconds']:.2f} | {vox.nbytes / 2**20:.1f} | {rss:.0f} | {kind} | "
                             f"{st['interior_nodes']:,} x "
                             f"{st['node_bytes']} | {st['leaves']:,} x {st['leaf_bytes']} | "
                             f"{st['memory_bytes'] / 2**20:.1f} | {st['mean_leaf_depth']:.2f} | "
                             f"{st['var_leaf_depth']:.2f} | {st['build_seconds']:.2f} |")
                log(args, lines[-1])
                _write_voxelize(args, rows + [row], lines)  # a late failure (out of memory) keeps these
            rows.append(row)
            del vox
    out = _write_voxelize(args, rows, lines)
    print(f"report: {out / 'voxelize.md'}")
    return 0


def _write_voxelize(args, rows: list, lines: list[str]) -> Path:
    """voxelize.json / .md with the rows so far (rewritten after every structure)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "voxelize.json").write_text(json.dumps(rows, indent=1, default=float))
    (out / "voxelize.md").write_text("\n".join([f"Command: `rtwalk bench-voxels {' '.join(sys.argv[2:])}`", "",
                                                 *lines, ""]))
    return out


def run(args) -> int:
    from viewer.accel.voxelize import check_resolution
    from viewer.backends import backend_info, backend_names
    from viewer.backends.voxels.scene import STACK_RANGE, STRUCTURES
    from viewer.cl import cl_context
    from viewer.gl.context import shared_context

    resolutions = _ints(args.resolutions, "resolutions")
    for r in resolutions:
        check_resolution(r)
    stacks = _ints(args.stacks, "stacks")
    if not stacks or any(not STACK_RANGE[0] <= k <= STACK_RANGE[1] for k in stacks):
        raise RtwalkError(f"--stacks: each must be in {STACK_RANGE[0]}..{STACK_RANGE[1]}")
    structures = [s.strip() for s in args.structures.split(",") if s.strip()]
    if not structures or any(s not in STRUCTURES for s in structures):
        raise RtwalkError(f"--structures: choose from {', '.join(STRUCTURES)}")
    if args.reference not in backend_names() or not backend_info(args.reference).exact:
        raise RtwalkError(f"--reference: an exact registered backend (got '{args.reference}')")
    from viewer.cli_args import parse_size

    w, h = parse_size(args.size)  # 0x1 used to pass and fail in the GL after the scene was loaded
    if args.rounds < 1 or args.seq_len < 1 or not args.bias >= 0 or args.record_passes < 0:
        raise RtwalkError("--rounds and --seq-len must be >= 1, --bias and --record-passes >= 0")
    specs = [_scene_spec(s.strip()) for s in args.scenes.split(",") if s.strip()]
    from viewer.cli_args import check_output_dir, check_report_free

    check_output_dir(args.out, "--out")
    check_report_free([Path(args.out) / ("voxelize.json" if args.voxelize_only else "bench_voxels.json")],
                      getattr(args, "force", False))
    if args.voxelize_only:
        return _voxelize_only(args, specs, sorted(resolutions), structures)
    ctx_gl = shared_context()
    report = {"command": "rtwalk bench-voxels " + " ".join(sys.argv[2:]), "device_cl": cl_context().name,
              "reference": args.reference, "structures": structures, "stacks": stacks, "resolutions": resolutions,
              "bias": args.bias, "widths": list(WIDTHS),
              "record_passes": args.record_passes, "seq_len": args.seq_len, "rounds": args.rounds,
              "scenes": []}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    saved: list[bool] = []

    def checkpoint(partial: dict) -> None:  # finished resolutions reach the disk at once
        _write(out, {**report, "complete": False, "scenes": report["scenes"] + [partial]})
        saved.append(True)

    try:
        for name, spec, rec in specs:
            report["scenes"].append(study_scene(args, ctx_gl, name, spec, rec, (w, h), resolutions,
                                                structures, stacks, checkpoint))
    except KeyboardInterrupt:  # Ctrl-C: say where the finished resolutions are (it said only "interrupted")
        if not saved:
            raise
        raise KeyboardInterrupt(f"interrupted: the resolutions finished so far are in {out / 'bench_voxels.json'} "
                                "(\"complete\": false)") from None
    report["complete"] = True
    _write(out, report)
    print(f"report: {out / 'bench_voxels.md'}")
    return 0


def _write(out: Path, report: dict) -> None:
    """bench_voxels.json/.md/.png; the JSON first (the record), each file replaced whole."""
    for fname, text in (("bench_voxels.json", json.dumps(report, indent=1, default=float)),
                        ("bench_voxels.md", _markdown(report))):
        tmp = out / (fname + ".tmp")
        tmp.write_text(text)
        tmp.replace(out / fname)
    _plot(report, out / "bench_voxels.png")

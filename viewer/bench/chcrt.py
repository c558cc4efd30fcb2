"""`rtwalk bench-chcrt`: the benchmark tables of the CHC+RT paper (Mattausch et al., EG 2015) in one command.

`rtwalk bench` measures one configuration; CHC+RT's speed depends on more than that: temporal
coherence (consecutive frames, a cold first frame after a reset), its parameters (aggressive
threshold, batching, multi-queries, query mode) and the per-draw / per-query cost of the GL
implementation. Studies (``--study``, comma list or ``all``):

- ``table2`` (paper Table 2): glsl vs chcrt per recording x size x effect: steady-state trace time
  (sum of the ``trace:*`` / ``chc:*`` GPU phases) and frame wall time, the cold first frame in its
  own columns, speedup glsl/chcrt, rays/frame and Mrays/s.
- ``table4`` (paper Table 4): aggressive mode (``visible_threshold`` 0/20/100/200 px): time and
  image error against the conservative (threshold 0) image of the same frame.
- ``phases`` (paper Figure 8): chc phase times and counters per frame over a longer run.
- ``ooc`` (paper Tables 1 and 3, section 5.4): out-of-core chcrt on a large city with GPU budgets
  of 47/32/20 % in core: sizes, Mrays/s, queries and MB transferred per frame, peak memory
  (bench/chcrt_ooc.py).
- ``coherence`` (paper Table 5 / Figure 10, section 5.3): glsl and chcrt at per-pixel sample rotations
  of 0 / 18 / 36 / 180 degrees, times and images side by side (bench/chcrt_coherence.py).
- ``stages``: glsl and chcrt with their ray traversals in fragment or compute shaders, over table2's
  rows (bench/chcrt_stages.py): what a GPU whose graphics pipeline has few processors gains.
- ``coldstart``: glsl and chcrt with a new front refined by the host's synchronous waves or settling
  on the device, over table2's rows (bench/chcrt_coldstart.py): the cold frame, the frames a device
  front takes to settle, and the settled and whole-run means.
- ``overhead``: GL per-draw / per-query costs measured on the same context (synthetic), and
  batching / multi-query / query-mode variants of a real chcrt run.

Every study writes ``<study>.json`` (all per-frame numbers, the parameters, the device),
``<study>.md`` and ``<study>.png`` into ``--out``.

Timing protocol of one run: three warm-up frames with at most two samples per effect (they compile
the shader variants of the cold and the steady passes, viewer.bench.harness.WARMUP_FRAMES; the
context's very first timer query reads as unknown on llvmpipe), reset of the backend's temporal
state, then N consecutive frames from the first frame. The first is the cold
frame; the mean of the rest is the steady state. Configurations compared with each other
(glsl and chcrt of a Table 2 row, the thresholds of Table 4, the overhead variants) are
interleaved frame by frame, each with its own renderer, so load from other jobs hits them alike.
One GL context; each scene is loaded once per command.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from viewer.backends.interface import params_text
from viewer.bench.chcrt_coherence import study_coherence
from viewer.bench.chcrt_coldstart import study_coldstart
from viewer.bench.chcrt_common import chc_phases, finish_study, join_params, save_png
from viewer.bench.chcrt_ooc import study_ooc
from viewer.bench.chcrt_stages import study_stages
from viewer.bench.estimate import CostModel, format_estimate, run_estimate, scenes_estimate
from viewer.bench.gl_micro import MicroResult, micro_overheads
from viewer.bench.harness import PROTOCOL, Harness, RunResult, RunSpec, effect_settings, is_trace_phase, load_average
from viewer.bench.partial import keep_partial
from viewer.bench.plots import barh, figure, finish, points, pyplot, stacked
from viewer.bench.report import fmt, md_table, notes_md, ratio, size_text
from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS, resolve_recording

STUDIES = ("table2", "table4", "phases", "overhead", "tuning", "ooc", "coherence", "stages", "coldstart")
# not part of "all" (a 10M-triangle scene; 16 runs; not paper tables): ask for them by name
EXPLICIT_ONLY = ("ooc", "coherence", "stages", "coldstart")
DEFAULT_RECORDINGS = ("city-near", "city-far", "sponza-walk", "sibenik-walk", "conference-walk")
PHASE_COUNTERS = ("queries", "multi_queries", "failed_multi_queries", "subtrees_scheduled", "draws",
                  "intersect_draws")
FORMAT = "rtwalk-bench-chcrt"
STUDY_COLD_START = "cold_start=sync"  # unless --chcrt or RTWALK_CHCRT sets it (options_from_args)
QUICK_SIZE = (96, 54)


# ----------------------------------------------------------------------------------------- options


@dataclass
class StudyOptions:
    """Everything a `bench-chcrt` invocation does, checked before any scene is loaded."""

    studies: list[str]
    sizes: list[tuple[int, int]]
    recordings: list[Path]
    frames: int = 4
    first_frame: int | None = None  # None: a third into each path
    out: Path = Path("out/bench-chcrt")
    chcrt: str = ""  # extra chcrt parameters for every chcrt run
    quiet: bool = False
    quick: bool = False
    effects: list[str] = field(default_factory=lambda: ["primary", "ao:20", "diffuse:20"])
    thresholds: list[int] = field(default_factory=lambda: [0, 20, 100, 200])
    table4_recording: Path = RECORDINGS / "city-near.json"
    table4_effect: str = "diffuse:20"
    table4_glsl: bool = True
    phases_recording: Path = RECORDINGS / "city-near.json"
    phases_effect: str = "ao:4"
    phases_frames: int = 40
    overhead_recording: Path = RECORDINGS / "city-near.json"
    overhead_effect: str = "ao:4"
    micro_scale: float = 1.0  # op counts of the synthetic benchmark (quick: smaller)
    tuning_effects: list[str] = field(default_factory=lambda: ["ao:4", "diffuse:4"])
    tuning_grid: str = "t_q=0.5|1|2;min_tile_fraction=0.015|0.06;requery_interval=3|8"
    ooc_scene_size: int = 10_000_000  # triangles of the City-200 analog
    ooc_fractions: list[float] = field(default_factory=lambda: [0.47, 0.32, 0.20])
    ooc_recordings: list[Path] = field(default_factory=lambda: [RECORDINGS / "city-near.json",
                                                                RECORDINGS / "city-far.json"])
    ooc_effects: list[str] = field(default_factory=lambda: ["primary", "ao:20", "diffuse:20"])
    ooc_frames: int = 6
    coherence_recordings: list[Path] = field(default_factory=lambda: [RECORDINGS / "city-near.json",
                                                                      RECORDINGS / "sponza-walk.json"])
    coherence_effects: list[str] = field(default_factory=lambda: ["ao:20", "diffuse:20"])
    perturbs: list[float] = field(default_factory=lambda: [0.0, 18.0, 36.0, 180.0])
    notes: list[str] = field(default_factory=list)


def _split(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _param_names() -> set[str]:
    from viewer.backends.chcrt import ChcrtParams

    return {f.name for f in fields(ChcrtParams)}


def effective_params(*texts: str | None) -> str:
    """The chcrt parameters a run gets: RTWALK_CHCRT, then the texts in order (later wins)."""
    from viewer.backends.chcrt import ChcrtParams
    from viewer.backends.interface import params_text, parse_params

    return params_text(parse_params(ChcrtParams, join_params(os.environ.get("RTWALK_CHCRT", ""), *texts), "--chcrt"))


def options_from_args(args: argparse.Namespace) -> StudyOptions:
    """Check all input up front (bad input fails in a second, not after an hour)."""
    from viewer.cli_args import parse_image_sizes

    studies: list[str] = []
    for s in _split(args.study or "all"):
        if s == "all":
            studies += [x for x in STUDIES if x not in studies and x not in EXPLICIT_ONLY]
        elif s in STUDIES:
            studies += [] if s in studies else [s]
        else:
            raise RtwalkError(f"unknown --study '{s}' (choose from {', '.join(STUDIES)}, all)")
    if not studies:
        raise RtwalkError("--study is empty")
    quick = bool(args.quick)
    if args.sizes:
        sizes = parse_image_sizes(args.sizes)
    else:
        sizes = [QUICK_SIZE] if quick else [(640, 360)]
    notes: list[str] = []
    if args.recordings:
        recordings = [resolve_recording(r) for r in _split(args.recordings)]
    else:
        names = ["city-near"] if quick else list(DEFAULT_RECORDINGS)
        recordings = [resolve_recording(n) for n in names]
    frames = args.frames if args.frames is not None else (2 if quick else 4)
    if frames < 1:
        raise RtwalkError("--frames must be >= 1")
    if args.first_frame is not None and args.first_frame < 0:
        raise RtwalkError("--first-frame must be >= 0")
    chcrt = args.chcrt or ""
    effective_params(chcrt)  # bad --chcrt text fails here
    if "cold_start" not in join_params(os.environ.get("RTWALK_CHCRT", ""), chcrt):
        # the studies compare fronts as the paper builds them, settled by their first pass; a device cold
        # start settles over its first frames, which a short run would mix into its steady state
        # (--study coldstart compares the two)
        chcrt = join_params(STUDY_COLD_START, chcrt)
        notes.append(f"chcrt runs take {STUDY_COLD_START}, the paper's first pass (--chcrt cold_start=... sets "
                     "another; --study coldstart runs both)")
    o = StudyOptions(studies=studies, sizes=sizes, recordings=recordings, frames=frames,
                     first_frame=args.first_frame, out=Path(args.out), chcrt=chcrt, quiet=bool(args.quiet),
                     quick=quick, notes=notes)
    o.effects = [e for e in _split(args.effects)] if args.effects else (
        ["primary", "ao:2", "diffuse:2"] if quick else o.effects)
    try:
        o.thresholds = [int(t) for t in _split(args.thresholds)] if args.thresholds else o.thresholds
    except ValueError:
        raise RtwalkError(f"bad --thresholds '{args.thresholds}': expected integers (pixels)") from None
    if any(t < 0 for t in o.thresholds) or not o.thresholds:
        raise RtwalkError("--thresholds must be integers >= 0")
    if args.table4_recording:
        o.table4_recording = resolve_recording(args.table4_recording)
    if args.phases_recording:
        o.phases_recording = resolve_recording(args.phases_recording)
    if args.overhead_recording:
        o.overhead_recording = resolve_recording(args.overhead_recording)
    o.table4_effect = args.table4_effect or ("diffuse:2" if quick else o.table4_effect)
    o.phases_effect = args.phases_effect or ("ao:1" if quick else o.phases_effect)
    o.overhead_effect = args.overhead_effect or ("ao:1" if quick else o.overhead_effect)
    o.phases_frames = args.phases_frames if args.phases_frames is not None else (4 if quick else o.phases_frames)
    if o.phases_frames < 1:
        raise RtwalkError("--phases-frames must be >= 1")
    o.table4_glsl = not args.no_glsl_reference
    o.micro_scale = 0.1 if quick else 1.0
    if args.tuning_effects:
        o.tuning_effects = _split(args.tuning_effects)
    elif quick:
        o.tuning_effects = ["ao:1"]
    o.tuning_grid = args.tuning_grid or ("t_q=0.5|2" if quick else o.tuning_grid)
    for params in tuning_configs(o.tuning_grid):
        try:
            effective_params(params)  # bad grid text fails here
        except RtwalkError as exc:  # it was reported as --chcrt's
            raise RtwalkError(f"--tuning-grid '{o.tuning_grid}': {str(exc).removeprefix('--chcrt: ')}") from None
    if args.ooc_recordings:
        o.ooc_recordings = [resolve_recording(r) for r in _split(args.ooc_recordings)]
    from viewer.recording import load_recording as _load_rec

    for path in o.ooc_recordings:
        if "builtin" not in _load_rec(path).scene:
            raise RtwalkError(f"--ooc-recordings: {path.name} does not use a builtin scene (its size is scaled)")
    if args.ooc_scene_size is not None:  # `or` took 0 for "not given": a 10 M city instead of an error
        from viewer.scene_io import check_builtin_size

        o.ooc_scene_size = check_builtin_size("city", args.ooc_scene_size, "--ooc-scene-size")
    elif quick:
        o.ooc_scene_size = 40_000
    try:
        o.ooc_fractions = [float(f) for f in _split(args.ooc_fractions)] if args.ooc_fractions else o.ooc_fractions
    except ValueError:
        raise RtwalkError(f"bad --ooc-fractions '{args.ooc_fractions}': expected numbers in (0, 1]") from None
    if not o.ooc_fractions or not all(0 < f <= 1 for f in o.ooc_fractions):
        raise RtwalkError("--ooc-fractions must be numbers in (0, 1]")
    o.ooc_effects = _split(args.ooc_effects) if args.ooc_effects else (["primary", "ao:1"] if quick else o.ooc_effects)
    o.ooc_frames = args.ooc_frames if args.ooc_frames is not None else (2 if quick else o.ooc_frames)
    if o.ooc_frames < 1:
        raise RtwalkError("--ooc-frames must be >= 1")
    if args.coherence_recordings:
        o.coherence_recordings = [resolve_recording(r) for r in _split(args.coherence_recordings)]
    elif quick:
        o.coherence_recordings = o.coherence_recordings[:1]
    o.coherence_effects = (_split(args.coherence_effects) if args.coherence_effects
                           else (["ao:1"] if quick else o.coherence_effects))
    try:
        o.perturbs = [float(v) for v in _split(args.perturbs)] if args.perturbs else (
            [0.0, 180.0] if quick else o.perturbs)
    except ValueError:
        raise RtwalkError(f"bad --perturbs '{args.perturbs}': expected degrees in 0..180") from None
    if not o.perturbs or not all(0 <= v <= 180 for v in o.perturbs):
        raise RtwalkError("--perturbs must be degrees in 0..180")
    for e in (o.effects + o.tuning_effects + o.ooc_effects + o.coherence_effects
              + [o.table4_effect, o.phases_effect, o.overhead_effect]):
        effect_settings(e)  # bad effect names fail here
    # every recording must load, and its scene must exist (a missing scene file of a default
    # recording is skipped with a note: ../shared/scenes is optional)
    from viewer.recording import load_recording, resolve_scene_spec

    keep = []
    for path in o.recordings:
        rec = load_recording(path)
        spec = resolve_scene_spec(rec, path)
        if "file" in rec.scene and not Path(spec.spec).is_file():
            if args.recordings:
                raise RtwalkError(f"{path.name}: scene file '{spec.spec}' not found (see ../shared/scenes)")
            notes.append(f"{path.stem} skipped: scene file {spec.spec} not found")
            continue
        keep.append(path)
    o.recordings = keep
    for path in set(o.recordings) | {o.table4_recording, o.phases_recording, o.overhead_recording}:
        n = load_recording(path).frame_count()
        if o.first_frame is not None and o.first_frame >= n:
            raise RtwalkError(f"--first-frame {o.first_frame} is outside {path.name}'s frames 0..{n - 1}")
    for study in ("table2", "stages", "coldstart"):
        if study in studies and not o.recordings:
            raise RtwalkError(f"{study}: none of the recordings' scenes are present")
    return o


# ----------------------------------------------------------------------------------------- estimate

# Steady-state microseconds per ray and cold-frame factors (first frame after a reset): the means
# over the five Table 2 recordings at 1920x1080 (`--study table2 --sizes 1920x1080 --effects
# primary,ao:4 --frames 8`, 2 cores, Mesa llvmpipe, 2026-11-29); diffuse scaled from AO by the
# ratio of the first fit. Only for the up-front estimate; tqdm shows the real rate.
COST = {"glsl": CostModel({"primary": 0.26, "ao": 0.23, "diffuse": 0.31}, 0.26),
        "chcrt": CostModel({"primary": 0.24, "ao": 0.22, "diffuse": 0.32}, 0.26,
                           cold_factor={"primary": 6.0, "ao": 2.4, "diffuse": 3.4}, cold_default=3.0,
                           scales_aggressive=True)}
_MICRO_S = 10.0


def _run_estimate(backend: str, effect: str, size: tuple[int, int], frames: int, aggressive: float = 1.0) -> float:
    return run_estimate(COST[backend], effect, size, frames, aggressive)


def estimate(o: StudyOptions) -> dict[str, float]:
    """Seconds per study (and 'scenes' for loading), from the cost model above."""
    out: dict[str, float] = {}
    scene_recs = set()
    if "table2" in o.studies:
        t = 0.0
        for _ in o.recordings:
            for size in o.sizes:
                for e in o.effects:
                    t += _run_estimate("glsl", e, size, o.frames) + _run_estimate("chcrt", e, size, o.frames)
        out["table2"] = t
        scene_recs.update(o.recordings)
    if "table4" in o.studies:
        t = 0.0
        thr = sorted(set([0] + o.thresholds))
        for size in o.sizes:
            for k in thr:
                t += _run_estimate("chcrt", o.table4_effect, size, o.frames, 1.0 if k == 0 else 0.5)
            if o.table4_glsl:
                t += _run_estimate("glsl", o.table4_effect, size, o.frames)
        out["table4"] = t
        scene_recs.add(o.table4_recording)
    if "phases" in o.studies:
        out["phases"] = _run_estimate("chcrt", o.phases_effect, o.sizes[0], o.phases_frames)
        scene_recs.add(o.phases_recording)
    if "overhead" in o.studies:
        n_variants = 7
        out["overhead"] = (_MICRO_S * max(o.micro_scale, 0.1)
                           + n_variants * _run_estimate("chcrt", o.overhead_effect, o.sizes[0], o.frames)
                           + _run_estimate("glsl", o.overhead_effect, o.sizes[0], o.frames))
        scene_recs.add(o.overhead_recording)
    if "tuning" in o.studies:
        n = len(tuning_configs(o.tuning_grid))
        out["tuning"] = sum(n * _run_estimate("chcrt", e, o.sizes[0], o.frames) * 1.5
                            + _run_estimate("glsl", e, o.sizes[0], o.frames) for e in o.tuning_effects)
        scene_recs.add(o.overhead_recording)
    if "ooc" in o.studies:
        n = len(o.ooc_fractions) + 1
        out["ooc"] = sum(n * _run_estimate("chcrt", e, o.sizes[0], o.ooc_frames) * 1.5
                         for e in o.ooc_effects) * len(o.ooc_recordings) + 8e-6 * o.ooc_scene_size
    if "stages" in o.studies:  # table2's rows, each configuration in both stages
        out["stages"] = sum(2 * (_run_estimate("glsl", e, size, o.frames) + _run_estimate("chcrt", e, size, o.frames))
                            for _ in o.recordings for size in o.sizes for e in o.effects)
        scene_recs.update(o.recordings)
    if "coldstart" in o.studies:  # table2's rows: glsl and chcrt with each cold start
        out["coldstart"] = sum(_run_estimate("glsl", e, size, o.frames) + 2 * _run_estimate("chcrt", e, size, o.frames)
                               for _ in o.recordings for size in o.sizes for e in o.effects)
        scene_recs.update(o.recordings)
    if "coherence" in o.studies:
        out["coherence"] = len(o.coherence_recordings) * len(o.perturbs) * sum(
            _run_estimate("chcrt", e, o.sizes[0], o.frames) + _run_estimate("glsl", e, o.sizes[0], o.frames)
            for e in o.coherence_effects)
        scene_recs.update(o.coherence_recordings)
    out["scenes"] = scenes_estimate(scene_recs)
    return out


# ----------------------------------------------------------------------------------------- runs


class Bench(Harness):
    """The harness with this command's options; the studies read both."""

    def __init__(self, o: StudyOptions):
        super().__init__(o.frames, o.first_frame, o.quiet)
        self.o = o

    def header(self, study: str, o: StudyOptions, extra: dict) -> dict:
        from viewer.backends.chcrt import ChcrtParams

        return {"format": FORMAT, "version": 1, "study": study, "device": self.device,
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "options": asdict(o),
                "parameters": {"sizes": [list(s) for s in o.sizes], "frames": o.frames,
                               "first_frame": o.first_frame, "chcrt": o.chcrt,
                               "RTWALK_CHCRT": os.environ.get("RTWALK_CHCRT", ""),
                               "chcrt_defaults": params_text(ChcrtParams()), "quick": o.quick, **extra},
                "load_average": {"command_start": self.load_at_start, "study_end": load_average(),
                                 "cpus": os.cpu_count()},  # other jobs on the machine skew timings
                "protocol": PROTOCOL,
                "notes": list(o.notes)}


# ----------------------------------------------------------------------------------------- table2


@dataclass
class Table2Row:
    """One (recording, size, effect): glsl vs chcrt, steady state and cold frame."""

    recording: str
    size: str
    effect: str
    rays_per_frame: float
    glsl_trace_ms: float
    glsl_frame_ms: float
    chcrt_trace_ms: float
    chcrt_frame_ms: float
    chcrt_cold_trace_ms: float
    chcrt_cold_frame_ms: float
    speedup_trace: float  # glsl / chcrt, steady
    speedup_frame: float
    glsl_mrays_per_s: float
    chcrt_mrays_per_s: float
    # chcrt's passes per steady frame that traced the whole BVH (incoherent rays, LCA limits, or a
    # front its work probe found to save too little: the latter also in chcrt_wasted_passes)
    chcrt_full_bvh_passes: float = 0.0
    chcrt_wasted_passes: float = 0.0
    # along the path, per steady frame (the same frames for both: they run interleaved): the frame
    # numbers, glsl's and chcrt's trace ms and chcrt's whole-BVH passes (where the queries cost more
    # than they save shows as a stretch of speedup below 1, often with whole-BVH passes)
    frame_numbers: list[int] = field(default_factory=list)
    glsl_trace_by_frame: list[float] = field(default_factory=list)
    chcrt_trace_by_frame: list[float] = field(default_factory=list)
    chcrt_full_bvh_by_frame: list[float] = field(default_factory=list)

    @staticmethod
    def of(g: RunResult, c: RunResult) -> Table2Row:
        gs, cs = g.best, c.best
        steady = c.frames[1:] or c.frames

        def per_frame(key: str) -> float:
            return sum(f.get("backend_stats", {}).get(key, 0.0) for f in steady) / max(len(steady), 1)

        return Table2Row(g.recording, size_text(g.size), g.effect, gs.rays, gs.trace_ms, gs.wall_ms, cs.trace_ms,
                         cs.wall_ms, c.cold.trace_ms, c.cold.wall_ms, ratio(gs.trace_ms, cs.trace_ms),
                         ratio(gs.wall_ms, cs.wall_ms), gs.mrays_per_s, cs.mrays_per_s,
                         per_frame("full_bvh_passes"), per_frame("wasted_front_passes"),
                         list(g.frame_numbers[1:]), [float(f["trace_ms"]) for f in g.frames[1:]],
                         [float(f["trace_ms"]) for f in c.frames[1:]],
                         [float(f.get("backend_stats", {}).get("full_bvh_passes", 0.0)) for f in c.frames[1:]])

    def windows(self, n: int) -> list[tuple[int, int, float, float]]:
        """The steady frames in `n` consecutive windows: (first frame, last frame, glsl / chcrt trace
        time over the window, chcrt's whole-BVH passes per frame)."""
        k = len(self.frame_numbers)
        out = []
        for w in range(min(n, k)):
            a, b = w * k // n, (w + 1) * k // n
            if b > a:
                out.append((self.frame_numbers[a], self.frame_numbers[b - 1],
                            ratio(sum(self.glsl_trace_by_frame[a:b]), sum(self.chcrt_trace_by_frame[a:b])),
                            sum(self.chcrt_full_bvh_by_frame[a:b]) / (b - a)))
        return out


def study_table2(b: Bench) -> dict:
    """Paper Table 2: for each recording x size x effect, glsl and chcrt over the same frames."""
    o = b.o
    total = len(o.recordings) * len(o.sizes) * len(o.effects) * 2 * o.frames
    b.progress("table2", total)
    runs: list[RunResult] = []
    rows: list[Table2Row] = []
    try:
        for path in o.recordings:
            for size in o.sizes:
                for effect in o.effects:
                    g, c = b.run_many(path, size, [RunSpec("glsl", effect, "glsl"),
                                                   RunSpec("chcrt", effect, "chcrt", o.chcrt)])
                    runs += [g, c]
                    rows.append(Table2Row.of(g, c))
    finally:
        b.done()
    report = b.header("table2", o, {"recordings": [p.stem for p in o.recordings], "effects": o.effects})
    report.update(rows=[asdict(r) for r in rows], runs=[asdict(r) for r in runs])
    steady = "steady state" if o.frames > 1 else "one frame only: no steady state, cold frame shown"
    md = [f"## Table 2 analog: glsl vs chcrt ({steady}; mean of frames 2..{o.frames} of {o.frames} consecutive)",
          "", f"Device: {b.device_text}. Trace = sum of the GPU tracing phases (trace:* / chc:*); frame = "
          "wall time of the whole frame. Cold = first frame after a reset (chcrt builds its fronts). "
          "Speedup = glsl / chcrt (> 1: chcrt faster). Whole-BVH passes = chcrt's passes per steady frame "
          "that traced the whole BVH (in brackets: because the work probe found their front saving too little).",
          ""]
    md.append(md_table(
        ["recording", "size", "effect", "rays/frame", "glsl trace ms", "glsl frame ms", "chcrt trace ms",
         "chcrt frame ms", "chcrt cold trace ms", "chcrt cold frame ms", "speedup trace", "speedup frame",
         "glsl Mrays/s", "chcrt Mrays/s", "chcrt whole-BVH passes"],
        [[r.recording, r.size, r.effect, fmt(r.rays_per_frame, 0), fmt(r.glsl_trace_ms), fmt(r.glsl_frame_ms),
          fmt(r.chcrt_trace_ms), fmt(r.chcrt_frame_ms), fmt(r.chcrt_cold_trace_ms), fmt(r.chcrt_cold_frame_ms),
          fmt(r.speedup_trace, 2), fmt(r.speedup_frame, 2), fmt(r.glsl_mrays_per_s, 2),
          fmt(r.chcrt_mrays_per_s, 2), f"{r.chcrt_full_bvh_passes:.1f} ({r.chcrt_wasted_passes:.1f})"]
         for r in rows]))
    md += _path_md(rows)
    md += notes_md(report["notes"])
    _plot_table2(rows, o.out / "table2.png", b.device["renderer"])
    return finish_study(o, "table2", report, "\n".join(md))


PATH_WINDOWS = 9  # table2's Markdown: the speedup along a path of at least PATH_MIN_FRAMES, in windows
PATH_MIN_FRAMES = 18


def _path_md(rows: list[Table2Row]) -> list[str]:
    """The speedup along each path in PATH_WINDOWS windows of consecutive frames (whole-BVH passes
    per frame in brackets), for runs long enough to have a path."""
    rows = [r for r in rows if len(r.frame_numbers) >= PATH_MIN_FRAMES]
    if not rows:
        return []
    md = ["", f"### Along the path: speedup trace in {PATH_WINDOWS} windows of consecutive steady frames "
              "(chcrt's whole-BVH passes per frame in brackets; per frame: the JSON rows and the plot)", ""]
    table = []
    for r in rows:
        cells = [f"{a}-{b}: {fmt(sp, 2)} ({full:.1f})" for a, b, sp, full in r.windows(PATH_WINDOWS)]
        table.append([r.recording, r.size, r.effect, *cells])
    width = max(len(t) for t in table)
    md.append(md_table(["recording", "size", "effect", *[f"window {i + 1}" for i in range(width - 3)]],
                       [t + [""] * (width - len(t)) for t in table]))
    return md


def _plot_table2(rows: list[Table2Row], path: Path, device: str) -> None:
    """The steady means (bars) and, below, the speedup frame by frame along each path (thin) and
    over a running window of up to 9 frames (a cross: a frame where chcrt traced some pass through
    the whole BVH)."""
    labels = [f"{r.recording} {r.size} {r.effect}" for r in rows]
    bar_h = 1.2 + 0.32 * len(rows)
    fig = pyplot().figure(figsize=(12, bar_h + 3.2), dpi=110)
    grid = fig.add_gridspec(2, 2, height_ratios=(bar_h, 3.2))
    ax0 = fig.add_subplot(grid[0, 0])
    ax1 = fig.add_subplot(grid[0, 1], sharey=ax0)
    barh(ax0, labels, {"glsl": [r.glsl_trace_ms for r in rows], "chcrt": [r.chcrt_trace_ms for r in rows]},
         "steady trace ms (log)", log=True)
    barh(ax1, labels, {"trace": [r.speedup_trace for r in rows], "frame": [r.speedup_frame for r in rows]},
         "speedup glsl / chcrt", ref=1.0)
    ax1.invert_yaxis()  # shared y axis: inverted once by each call
    ax2 = fig.add_subplot(grid[1, :])
    for r, label in zip(rows, labels, strict=True):
        g, c = np.asarray(r.glsl_trace_by_frame), np.asarray(r.chcrt_trace_by_frame)
        sp = [ratio(a, b) for a, b in zip(g, c, strict=True)]
        line = ax2.plot(r.frame_numbers, sp, lw=0.6, alpha=0.4)[0]
        # and over a running window of up to 9 frames (summed times: one slow frame is one frame)
        k = max(1, min(9, len(sp) // 10))
        if k > 1:
            kern = np.ones(k)
            run = np.convolve(g, kern, "valid") / np.convolve(c, kern, "valid")
            ax2.plot(r.frame_numbers[k // 2:k // 2 + len(run)], run, lw=1.4, color=line.get_color(), label=label)
        else:  # (too few frames for a running window: the frames themselves, drawn plainly)
            line.set(label=label, alpha=1.0, lw=1.2)
        full = [i for i, f in enumerate(r.chcrt_full_bvh_by_frame) if f > 0]
        ax2.plot([r.frame_numbers[i] for i in full], [sp[i] for i in full], "x", ms=3, color=line.get_color())
    ax2.axhline(1.0, color="k", lw=0.8)
    ax2.set_xlabel("frame")
    ax2.set_ylabel("speedup trace (glsl / chcrt)")
    ax2.grid(alpha=0.3)
    if rows:
        ax2.legend(fontsize=7)
    finish(fig, path, f"CHC+RT Table 2 analog - {device}")


# ----------------------------------------------------------------------------------------- table4


@dataclass
class Table4Row:
    """One aggressive threshold (or the glsl reference) at one size: time and image error."""

    config: str  # "threshold N" or "glsl"
    threshold: int | None
    size: str
    trace_ms: float  # steady
    frame_ms: float  # steady
    cold_trace_ms: float
    cold_frame_ms: float
    mae: float  # mean absolute error (0..255, over RGB) vs the threshold-0 image of the same frame, all frames
    max_error: float
    pct_pixels_over_8: float  # % pixels with an error > 8 in some channel
    psnr_min_db: float
    queries: float
    subtrees_scheduled: float
    per_frame_mae: list[float]


def study_table4(b: Bench) -> dict:
    """Paper Table 4: visible_threshold vs time and error against the conservative image."""
    from viewer.bench.harness import image_error

    o = b.o
    path = o.table4_recording
    thresholds = [0] + [t for t in dict.fromkeys(o.thresholds) if t != 0]
    per_size = len(thresholds) + int(o.table4_glsl)
    b.progress("table4", len(o.sizes) * per_size * o.frames)
    runs: list[RunResult] = []
    rows: list[Table4Row] = []
    img_dir = o.out / "table4-images"
    img_dir.mkdir(parents=True, exist_ok=True)
    try:
        for size in o.sizes:
            configs = [(f"threshold {t}", t) for t in thresholds] + ([("glsl", None)] if o.table4_glsl else [])
            images: list[list[np.ndarray]] = [[] for _ in configs]
            specs = []
            for i, (label, thr) in enumerate(configs):
                def sink(k: int, n: int, img: np.ndarray, store=images[i]) -> None:
                    store.append(img)

                specs.append(RunSpec(label, o.table4_effect, "glsl", None, sink) if thr is None else
                             RunSpec(label, o.table4_effect, "chcrt", join_params(o.chcrt, f"visible_threshold={thr}"),
                                     sink))
            size_runs = b.run_many(path, size, specs)
            ref = images[0]  # threshold 0
            for (label, thr), run, imgs in zip(configs, size_runs, images, strict=True):
                errs = [image_error(img, ref[k]) for k, img in enumerate(imgs)]
                for k, e in enumerate(errs):
                    run.frames[k]["image_error_vs_threshold0"] = e
                runs.append(run)
                st = run.best
                rows.append(Table4Row(
                    label, thr, size_text(size), st.trace_ms, st.wall_ms, run.cold.trace_ms, run.cold.wall_ms,
                    float(np.mean([e["mae"] for e in errs])), float(max(e["max"] for e in errs)),
                    100.0 * float(np.mean([e["pixels_over_8"] for e in errs])),
                    float(min(e["psnr_db"] for e in errs)), st.counters.get("queries", float("nan")),
                    st.counters.get("subtrees_scheduled", float("nan")), [e["mae"] for e in errs]))
                save_png(img_dir / f"{path.stem}-{size_text(size)}-{label.replace(' ', '')}.png", imgs[-1])
                if thr is not None and thr == thresholds[-1] and thr != 0:
                    diff = np.abs(imgs[-1].astype(np.int16) - ref[-1].astype(np.int16)).max(axis=-1)
                    save_png(img_dir / f"{path.stem}-{size_text(size)}-diff-x8-{label.replace(' ', '')}.png",
                              np.clip(diff * 8, 0, 255).astype(np.uint8))
    finally:
        b.done()
    report = b.header("table4", o, {"recording": path.stem, "effect": o.table4_effect, "thresholds": thresholds,
                                    "glsl_reference": o.table4_glsl})
    report.update(rows=[asdict(r) for r in rows], runs=[asdict(r) for r in runs])
    md = [f"## Table 4 analog: aggressive culling ({path.stem}, {o.table4_effect}, {o.frames} consecutive frames "
          f"from {runs[0].frame_numbers[0] if runs else '-'})", "",
          f"Device: {b.device_text}. Error: mean absolute difference (0..255, over RGB) to the "
          "conservative (threshold 0) image of the same frame, mean over all frames; '> 8': % pixels with "
          "an error above 8 in some channel. Times: steady state (cold frame apart).", ""]
    md.append(md_table(
        ["config", "size", "trace ms", "frame ms", "cold trace ms", "cold frame ms", "mean abs error",
         "max error", "% px > 8", "min PSNR dB", "queries/frame", "subtrees/frame"],
        [[r.config, r.size, fmt(r.trace_ms), fmt(r.frame_ms), fmt(r.cold_trace_ms), fmt(r.cold_frame_ms),
          fmt(r.mae, 3), fmt(r.max_error, 0), fmt(r.pct_pixels_over_8, 2), fmt(r.psnr_min_db, 1),
          fmt(r.queries, 0), fmt(r.subtrees_scheduled, 0)] for r in rows]))
    md += notes_md(report["notes"])
    _plot_table4(rows, o.out / "table4.png", f"{path.stem} {o.table4_effect} - {b.device['renderer']}")
    return finish_study(o, "table4", report, "\n".join(md))


def _plot_table4(rows: list[Table4Row], path: Path, title: str) -> None:
    fig, ax = figure(size=(7, 4.5))
    for size in dict.fromkeys(r.size for r in rows):
        rs = [r for r in rows if r.size == size and r.threshold is not None]
        color = points(ax, [r.mae for r in rs], [r.trace_ms for r in rs], [f"{r.threshold}px" for r in rs],
                       label=f"chcrt {size}", line=True)
        for r in rows:
            if r.size == size and r.threshold is None and np.isfinite(r.trace_ms):
                ax.axhline(r.trace_ms, ls="--", color=color, lw=0.8, label=f"glsl {size}")
    ax.set_xlabel("mean absolute error vs threshold 0 (0..255)")
    ax.set_ylabel("steady trace ms")
    ax.set_title(f"Aggressive CHC+RT: time vs error - {title}", fontsize=8)
    ax.legend(fontsize=7)
    finish(fig, path)


# ----------------------------------------------------------------------------------------- phases


def study_phases(b: Bench) -> dict:
    """Paper Figure 8: chc phase times and counters per frame over a longer consecutive run.

    sync_phases=1 by default (a glFinish after each phase) so each phase is charged its own work;
    --chcrt sync_phases=0 turns it off."""
    o = b.o
    path, size = o.phases_recording, o.sizes[0]
    pre = "sync_phases=1" if "sync_phases" in _param_names() else ""
    b.progress("phases", o.phases_frames)
    try:
        run = b.run("chcrt", path, size, o.phases_effect, "chcrt", join_params(pre, o.chcrt),
                    frames=b.frames_for(path, o.phases_frames))
    finally:
        b.done()
    phases = sorted({p for r in run.frames for p in r["gpu_ms"] if p.startswith("chc:")})
    counters = [c for c in PHASE_COUNTERS if any(c in r["backend_stats"] for r in run.frames)]
    report = b.header("phases", o, {"recording": path.stem, "effect": o.phases_effect, "size": list(size),
                                    "frames_requested": o.phases_frames})
    report.update(phases=phases, counters=counters, run=asdict(run))
    md = [f"## Figure 8 analog: chcrt phases per frame ({path.stem}, {size_text(size)}, {o.phases_effect})", "",
          f"Device: {b.device_text}. Parameters: {run.params}. GPU ms per phase; 'other' = G-buffer, "
          "ray generation, accumulation, shading. Frame 1 of the run is the cold frame.", ""]
    rows = []
    for r in run.frames:
        other = sum(v for p, v in r["gpu_ms"].items() if not is_trace_phase(p, chc_phases()))
        rows.append([str(r["frame"]) + (" (cold)" if r["cold"] else "")]
                    + [fmt(r["gpu_ms"].get(p, 0.0)) for p in phases]
                    + [fmt(other), fmt(r["wall_ms"])]
                    + [fmt(r["backend_stats"].get(c, float("nan")), 0) for c in counters])
    md.append(md_table(["frame"] + [p.removeprefix("chc:") + " ms" for p in phases] + ["other ms", "wall ms"]
                       + counters, rows))
    md += ["", f"Steady mean (frames 2..): trace {fmt(run.steady.trace_ms)} ms, wall {fmt(run.steady.wall_ms)} ms; "
               f"cold frame: trace {fmt(run.cold.trace_ms)} ms, wall {fmt(run.cold.wall_ms)} ms."]
    md += notes_md(report["notes"])
    _plot_phases(run, phases, counters, o.out / "phases.png", b.device["renderer"])
    return finish_study(o, "phases", report, "\n".join(md))


def _plot_phases(run: RunResult, phases: list[str], counters: list[str], path: Path, device: str) -> None:
    x = [r["frame"] for r in run.frames]
    fig, (ax, ax2) = figure(2, 1, size=(10, 7), sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    layers = {p.removeprefix("chc:"): [r["gpu_ms"].get(p, 0.0) for r in run.frames] for p in phases}
    layers["other phases"] = [sum(v for p, v in r["gpu_ms"].items() if not is_trace_phase(p, chc_phases()))
                              for r in run.frames]
    stacked(ax, x, layers, ylabel="GPU ms", colors={"other phases": "0.75"},
            title=f"CHC+RT phases per frame - {run.recording} {size_text(run.size)} {run.effect} - {device}")
    ax.plot(x, [r["wall_ms"] for r in run.frames], "k.", ms=4, label="frame wall ms")
    ax.legend(fontsize=7, loc="upper right")
    for c in counters:
        ax2.plot(x, [r["backend_stats"].get(c, 0.0) for r in run.frames], "o-", ms=3, label=c)
    ax2.set_yscale("symlog")
    ax2.xaxis.get_major_locator().set_params(integer=True)
    ax2.set_xlabel("frame (first = cold)")
    ax2.set_ylabel("count per frame")
    ax2.legend(fontsize=7, ncol=3)
    ax2.grid(alpha=0.3)
    finish(fig, path)


# ----------------------------------------------------------------------------------------- overhead



@dataclass
class OverheadRow:
    """One chcrt configuration on a real run: counts per frame and derived costs (steady state)."""

    config: str
    params: str | None
    draws: float
    intersect_draws: float
    queries: float
    multi_queries: float
    trace_ms: float
    trace_cpu_ms: float
    frame_ms: float
    ms_per_draw: float  # trace_ms / draws: all tracing time charged to draws (an upper bound)
    ms_per_query: float  # trace_ms / queries (same, for queries)
    same_as: str | None = None  # an earlier config with identical effective parameters


@dataclass
class Comparison:
    """Two configurations that differ in one setting: marginal cost of what changed."""

    a: str
    b: str
    d_draws: float
    d_queries: float
    d_trace_ms: float
    ms_per_extra_draw: float
    ms_per_extra_query: float


# (label, parameter text); (a, b) pairs compared: a adds draws / queries that b batches
OVERHEAD_VARIANTS = [
    ("default", ""),
    ("max_batch=24", "max_batch=24"),
    ("max_batch=1", "max_batch=1"),
    ("max_multi=24", "max_multi=24"),
    ("max_multi=1", "max_multi=1"),
    ("query_mode=batched", "query_mode=batched"),
    ("query_mode=hw", "query_mode=hw"),
    ("hw, max_batch=1", "query_mode=hw,max_batch=1"),
    ("hw, max_multi=1", "query_mode=hw,max_multi=1"),
    ("hw, max_batch=1, max_multi=1", "query_mode=hw,max_batch=1,max_multi=1"),
]
OVERHEAD_PAIRS = [("max_batch=1", "max_batch=24"), ("max_multi=1", "max_multi=24"),
                  ("query_mode=hw", "query_mode=batched"), ("hw, max_batch=1", "query_mode=hw"),
                  ("hw, max_multi=1", "query_mode=hw"), ("hw, max_batch=1, max_multi=1", "query_mode=hw")]


def overhead_variants(user: str) -> tuple[list[tuple[str, str, str]], list[str]]:
    """(label, run text, effective parameters) for the variants this ChcrtParams supports, and
    notes on the ones skipped (a parameter or value it does not have)."""
    have = _param_names()
    out, skipped = [], []
    for label, text in OVERHEAD_VARIANTS:
        keys = [kv.partition("=")[0] for kv in _split(text)]
        missing = [k for k in keys if k not in have]
        if missing:
            skipped.append(f"{label}: skipped, ChcrtParams has no {', '.join(missing)}")
            continue
        try:
            eff = effective_params(user, text)
        except RtwalkError as exc:
            skipped.append(f"{label}: skipped ({exc})")
            continue
        out.append((label, join_params(user, text), eff))
    return out, skipped


def _moved(delta: float, a: float, b: float) -> bool:
    """A count changed enough to charge a time difference to it (not a handful out of thousands)."""
    return bool(np.isfinite(delta) and abs(delta) >= max(10.0, 0.05 * max(abs(a), abs(b))))


def study_overhead(b: Bench) -> dict:
    """Per-draw / per-query cost: synthetic GL microbenchmark, then chcrt variants on a real path."""
    o = b.o
    size, path = o.sizes[0], o.overhead_recording
    if not o.quiet:
        print("overhead: synthetic GL microbenchmark ...", file=sys.stderr, flush=True)
    micro, micro_setup = micro_overheads(b.ctx, size, o.micro_scale, trials=3 if o.quick else 7)
    variants, skipped = overhead_variants(o.chcrt)
    unique: dict[str, str] = {}
    for label, _, eff in variants:
        unique.setdefault(eff, label)
    b.progress("overhead", (len(unique) + 1) * o.frames)
    rows: list[OverheadRow] = []
    try:
        frames = b.frames_for(path, o.frames)
        texts = {label: text for label, text, _ in variants}
        specs = [RunSpec("glsl", o.overhead_effect, "glsl")] + [
            RunSpec(label, o.overhead_effect, "chcrt", texts[label]) for label in unique.values()]
        g, *chc = b.run_many(path, size, specs, frames)
        runs = {r.label: r for r in chc}
        for label, _, eff in variants:
            first = unique[eff]
            run = runs[first]
            s, c = run.best, run.best.counters
            draws, queries = c.get("draws", float("nan")), c.get("queries", float("nan"))
            rows.append(OverheadRow(label, run.params, draws, c.get("intersect_draws", float("nan")), queries,
                                    c.get("multi_queries", float("nan")), s.trace_ms, s.trace_cpu_ms, s.wall_ms,
                                    ratio(s.trace_ms, draws), ratio(s.trace_ms, queries),
                                    None if first == label else first))
    finally:
        b.done()
    by_label = {r.config: r for r in rows}
    comps = []
    for a, bb in OVERHEAD_PAIRS:
        ra, rb = by_label.get(a), by_label.get(bb)
        if ra is None or rb is None or (ra.same_as or ra.config) == (rb.same_as or rb.config):
            continue
        dd, dq, dt = ra.draws - rb.draws, ra.queries - rb.queries, ra.trace_ms - rb.trace_ms
        comps.append(Comparison(a, bb, dd, dq, dt,
                                dt / dd if _moved(dd, ra.draws, rb.draws) else float("nan"),
                                dt / dq if _moved(dq, ra.queries, rb.queries) else float("nan")))
    report = b.header("overhead", o, {"recording": path.stem, "effect": o.overhead_effect, "size": list(size),
                                      "micro_setup": micro_setup})
    report["notes"] += skipped
    report.update(micro=[asdict(m) for m in micro], rows=[asdict(r) for r in rows],
                  comparisons=[asdict(c) for c in comps], glsl=asdict(g), runs={k: asdict(v) for k, v in runs.items()})
    md = [f"## Overhead: draws and queries on {b.device['renderer']}", "",
          f"### (a) Synthetic, same GL context, {size[0]}x{size[1]} target (best of {micro_setup['trials']} "
          "trials, median beside it; wall time per op with the final glFinish amortised; submit = CPU time "
          "to issue)", ""]
    md.append(md_table(["operation", "ops/trial", "us per op (wall)", "median", "us per op (submit)", "items/op",
                        "us per item", "check"],
                       [[m.name, str(m.ops_per_trial), fmt(m.us_per_op, 1), fmt(m.median_us_per_op, 1),
                         fmt(m.submit_us_per_op, 1), str(m.items_per_op), fmt(m.us_per_item, 2), m.check]
                        for m in micro]))
    gs = g.best
    md += ["", f"### (b) chcrt on {path.stem}, {size_text(size)}, {o.overhead_effect}, steady state of "
               f"{o.frames} consecutive frames from {frames[0]}", "",
           "Per frame. 'ms per draw/query' = trace ms / count (all tracing time charged to draws or queries: "
           f"upper bounds). glsl on the same frames: trace {fmt(gs.trace_ms)} ms, frame {fmt(gs.wall_ms)} ms.", ""]
    md.append(md_table(["config", "draws", "intersect draws", "queries", "multi-queries", "trace ms",
                        "trace CPU ms", "frame ms", "ms per draw", "ms per query"],
                       [[r.config + (f" (= {r.same_as})" if r.same_as else ""), fmt(r.draws, 0),
                         fmt(r.intersect_draws, 0), fmt(r.queries, 0), fmt(r.multi_queries, 0), fmt(r.trace_ms),
                         fmt(r.trace_cpu_ms), fmt(r.frame_ms), fmt(r.ms_per_draw, 3), fmt(r.ms_per_query, 3)]
                        for r in rows]))
    if comps:
        md += ["", "Marginal cost: configuration a vs b (one setting changed): extra trace ms per extra draw / "
                   "query, the whole time difference charged to each ('-': that count barely changed).", ""]
        md.append(md_table(["a", "b", "d draws", "d queries", "d trace ms", "ms per extra draw",
                            "ms per extra query"],
                           [[c.a, c.b, fmt(c.d_draws, 0), fmt(c.d_queries, 0), fmt(c.d_trace_ms),
                             fmt(c.ms_per_extra_draw, 3), fmt(c.ms_per_extra_query, 3)] for c in comps]))
    md += notes_md(report["notes"])
    _plot_overhead(micro, rows, o.out / "overhead.png", b.device["renderer"])
    return finish_study(o, "overhead", report, "\n".join(md))


def _plot_overhead(micro: list[MicroResult], rows: list[OverheadRow], path: Path, device: str) -> None:
    fig, (ax, ax2) = figure(1, 2, size=(13, 5))
    barh(ax, [m.name for m in micro], {"us per op": [m.us_per_op for m in micro]}, "us per op (wall, log)",
         log=True, title="synthetic GL operations", label_size=6)
    rs = [r for r in rows if r.same_as is None]
    barh(ax2, [r.config for r in rs], {"trace ms": [r.trace_ms for r in rs]}, "steady trace ms per frame",
         texts=[f"{fmt(r.draws, 0)} draws, {fmt(r.queries, 0)} queries" for r in rs], title="chcrt configurations",
         color="C1")
    finish(fig, path, f"Draw / query overhead - {device}")


# ----------------------------------------------------------------------------------------- driver


def tuning_configs(grid: str) -> list[str]:
    """chcrt parameter texts of a grid "key=v1|v2;key2=w1|w2" (every combination)."""
    import itertools

    axes = []
    for part in filter(None, (p.strip() for p in grid.split(";"))):
        key, sep, vals = part.partition("=")
        values = [v.strip() for v in vals.split("|") if v.strip()]
        if not sep or not values:
            raise RtwalkError(f"bad --tuning-grid item '{part}': expected key=v1|v2|...")
        axes.append([f"{key.strip()}={v}" for v in values])
    return [",".join(c) for c in itertools.product(*axes)] if axes else [""]


@dataclass
class TuningRow:
    effect: str
    params: str
    trace_ms: float
    wall_ms: float
    queries: float
    query_fragments_per_ray: float
    box_tests_per_ray: float  # intersection (subtree traversal and batch items)
    query_box_tests_per_ray: float
    tri_tests_per_ray: float
    tests_per_ray: float  # all ray/box and ray/triangle tests
    nodes_per_ray: float  # intersection: BVH nodes fetched
    # what SIMD lane groups pay (base.lane_group_work: every lane waits for its group's busiest):
    # nodes and triangle tests per ray with groups of 8 (llvmpipe) and 32 (a GPU warp) pixels
    simd8_nodes_per_ray: float
    simd32_nodes_per_ray: float
    simd8_tri_per_ray: float
    simd32_tri_per_ray: float


def study_tuning(b: Bench) -> dict:
    """Parameter sweep for this machine: chcrt over a grid of split-rule / tile / re-query settings
    against glsl, timed and with the shader work counters (RTWALK_COUNT_WORK): on a CPU
    rasterizer time follows the number of tests, so the counters explain the timings and do not
    suffer from other jobs' load."""
    o = b.o
    path, size = o.overhead_recording, o.sizes[0]
    configs = tuning_configs(o.tuning_grid)
    old = os.environ.get("RTWALK_COUNT_WORK")
    os.environ["RTWALK_COUNT_WORK"] = "1"
    rows: list[TuningRow] = []
    runs = []
    b.progress("tuning", len(o.tuning_effects) * (len(configs) + 1) * o.frames)
    try:
        for effect in o.tuning_effects:
            specs = [RunSpec("glsl", effect, "glsl")] + [
                RunSpec(c, effect, "chcrt", join_params(c, "overdraw_overlay=0", o.chcrt)) for c in configs]
            for spec, run in zip(specs, b.run_many(path, size, specs), strict=True):
                st, rays = run.best.counters, max(run.best.rays, 1.0)

                def per_ray(key: str, st=st, rays=rays) -> float:
                    return st.get(f"work_{key}", 0.0) / rays

                box, qbox, tri = per_ray("box_tests"), per_ray("query_box_tests"), per_ray("tri_tests")
                rows.append(TuningRow(effect, spec.label, run.best.trace_ms, run.best.wall_ms, st.get("queries", 0.0),
                                      per_ray("query_fragments"), box, qbox, tri, box + qbox + tri, per_ray("nodes"),
                                      per_ray("simd8_nodes"), per_ray("simd32_nodes"), per_ray("simd8_tri_tests"),
                                      per_ray("simd32_tri_tests")))
                runs.append(asdict(run))
    finally:
        b.done()
        if old is None:
            os.environ.pop("RTWALK_COUNT_WORK", None)
        else:
            os.environ["RTWALK_COUNT_WORK"] = old
    report = b.header("tuning", o, {"recording": path.stem, "size": list(size), "grid": o.tuning_grid,
                                    "effects": o.tuning_effects})
    report.update(rows=[asdict(r) for r in rows], runs=runs)
    md = [f"## chcrt parameter sweep ({path.stem}, {size_text(size)}, steady state of {o.frames} consecutive frames)",
          "", f"Device: {b.device_text}. Work counters per traced ray (RTWALK_COUNT_WORK=1; counting adds "
          "time to both backends). 'tests' = ray/box + ray/triangle tests of intersection and queries. "
          "'lanes 8 / 32': the intersection's nodes and triangle tests as SIMD groups of 8 (llvmpipe) and 32 (a "
          "GPU warp) neighbouring pixels pay them, every lane waiting for its group's busiest.", ""]
    md.append(md_table(["effect", "config", "trace ms", "queries/frame", "query frags/ray", "isect box/ray",
                        "query box/ray", "tri/ray", "tests/ray", "nodes/ray", "nodes/ray, lanes 8 / 32",
                        "tri/ray, lanes 8 / 32"],
                       [[r.effect, r.params, fmt(r.trace_ms), fmt(r.queries, 0), fmt(r.query_fragments_per_ray, 2),
                         fmt(r.box_tests_per_ray, 1), fmt(r.query_box_tests_per_ray, 1),
                         fmt(r.tri_tests_per_ray, 2), fmt(r.tests_per_ray, 1), fmt(r.nodes_per_ray, 1),
                         f"{fmt(r.simd8_nodes_per_ray, 1)} / {fmt(r.simd32_nodes_per_ray, 1)}",
                         f"{fmt(r.simd8_tri_per_ray, 2)} / {fmt(r.simd32_tri_per_ray, 2)}"] for r in rows]))
    md += notes_md(report["notes"])
    _plot_tuning(rows, o.out / "tuning.png", b.device["renderer"])
    return finish_study(o, "tuning", report, "\n".join(md))


def _plot_tuning(rows: list[TuningRow], path: Path, device: str) -> None:
    effects = list(dict.fromkeys(r.effect for r in rows))
    fig, axes = figure(1, len(effects), size=(6 * len(effects), 4.5), dpi=100, squeeze=False)
    for ax, effect in zip(axes[0], effects, strict=True):
        for r in (r for r in rows if r.effect == effect):
            points(ax, [r.tests_per_ray], [r.trace_ms],
                   [r.params.replace("min_tile_fraction", "tile").replace("requery_interval", "rq")],
                   color="tab:red" if r.params == "glsl" else "tab:blue", xlabel="ray/box + ray/triangle tests per ray",
                   ylabel="trace ms per frame", title=f"{effect}: chcrt configs (blue) vs glsl (red)")
    finish(fig, path, f"chcrt tuning - {device}")


STUDY_FUNCS: dict[str, Callable[[Bench], dict]] = {"table2": study_table2, "table4": study_table4,
                                                    "phases": study_phases, "overhead": study_overhead,
                                                    "tuning": study_tuning, "ooc": study_ooc,
                                                    "coherence": study_coherence, "stages": study_stages,
                                                    "coldstart": study_coldstart}


def run_studies(o: StudyOptions, out=None) -> list[dict]:
    out = out or sys.stdout  # looked up per call: a stream bound at import may be closed by now
    est = estimate(o)
    if not o.quiet:
        print(format_estimate(est), file=sys.stderr, flush=True)
        for n in o.notes:
            print(f"rtwalk: note: {n}", file=sys.stderr)
    o.out.mkdir(parents=True, exist_ok=True)
    b = Bench(o)
    done = []
    t0 = time.perf_counter()
    with keep_partial("bench-chcrt", defer=True) as part:  # Ctrl-C: the finished studies stay, marked incomplete
        b.interrupt = part
        for study in o.studies:
            part.started(study)
            part.check()  # before a study, not after: a signal during the last one's printing leaves the run complete
            res = STUDY_FUNCS[study](b)
            part.finished(res["json"])
            done.append(res)
            print(res["markdown"] + "\n", file=out)
            print(f"{study}: {res['json']}  {res['md']}  {res['png']}\n", file=out, flush=True)
    if not o.quiet:
        print(f"bench-chcrt: {len(done)} studies in {(time.perf_counter() - t0) / 60:.1f} min "
              f"(estimated {sum(est.values()) / 60:.1f})", file=sys.stderr)
    return done


HELP = "CHC+RT paper tables: glsl vs chcrt, aggressive mode, phases, overhead"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The `bench-chcrt` subcommand's options (kept here so cli.py only registers it)."""
    p.description = (__doc__ or "").split("\n\n")[0].replace("`", "")
    p.add_argument("--study", default="all",
                   help=f"comma list of {', '.join(STUDIES)}, or all (all but {', '.join(EXPLICIT_ONLY)})")
    p.add_argument("--sizes", default=None, help="comma list of WIDTHxHEIGHT (default 640x360; --quick: 96x54); "
                                                 "phases and overhead use the first")
    p.add_argument("--recordings", default=None,
                   help="table2: comma list of recordings (name in recordings/ or path; default all five)")
    p.add_argument("--frames", type=int, default=None,
                   help="consecutive frames per run; the first is the cold frame (default 4; --quick: 2)")
    p.add_argument("--first-frame", type=int, default=None, help="first frame (default: a third into each path)")
    p.add_argument("--out", default="out/bench-chcrt", help="folder for JSON, Markdown and plots")
    p.add_argument("--chcrt", default=None, metavar="KEY=VALUE,...", help="extra chcrt parameters for every chcrt run")
    p.add_argument("--effects", default=None,
                   help="table2: comma list, one run each (join effects of one run with '+'); "
                        "default primary,ao:20,diffuse:20")
    p.add_argument("--thresholds", default=None, help="table4: visible_threshold values, px (default 0,20,100,200)")
    p.add_argument("--table4-recording", default=None, help="table4 path (default city-near)")
    p.add_argument("--table4-effect", default=None, help="table4 effect (default diffuse:20)")
    p.add_argument("--no-glsl-reference", action="store_true", help="table4: leave out the glsl row")
    p.add_argument("--phases-recording", default=None, help="phases path (default city-near)")
    p.add_argument("--phases-effect", default=None, help="phases effect (default ao:4)")
    p.add_argument("--phases-frames", type=int, default=None, help="phases: consecutive frames (default 40)")
    p.add_argument("--overhead-recording", default=None, help="overhead path (default city-near)")
    p.add_argument("--overhead-effect", default=None, help="overhead effect (default ao:4)")
    p.add_argument("--tuning-effects", default=None, help="tuning: comma list of effects (default ao:4,diffuse:4)")
    p.add_argument("--tuning-grid", default=None,
                   help="tuning: chcrt grid 'key=v1|v2;key=...' (default t_q=0.5|1|2;min_tile_fraction=0.015|0.06;"
                        "requery_interval=3|8)")
    p.add_argument("--ooc-scene-size", type=int, default=None,
                   help="ooc: triangles of the large city (default 10000000; --quick: 40000)")
    p.add_argument("--ooc-fractions", default=None,
                   help="ooc: GPU budgets as fractions in core (default 0.47,0.32,0.2)")
    p.add_argument("--ooc-recordings", default=None, help="ooc: builtin-city recordings (default city-near,city-far)")
    p.add_argument("--ooc-effects", default=None, help="ooc: comma list of effects (default primary,ao:20,diffuse:20)")
    p.add_argument("--ooc-frames", type=int, default=None, help="ooc: consecutive frames per run (default 6)")
    p.add_argument("--coherence-recordings", default=None,
                   help="coherence: comma list of recordings (default city-near,sponza-walk)")
    p.add_argument("--coherence-effects", default=None,
                   help="coherence: comma list of effects (default ao:20,diffuse:20)")
    p.add_argument("--perturbs", default=None, help="coherence: per-pixel rotations, degrees (default 0,18,36,180)")
    p.add_argument("--quick", action="store_true", help="tiny size, 2 frames, one recording, few samples (tests)")
    p.add_argument("--dry-run", action="store_true", help="print the plan and the time estimate, run nothing")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    o = options_from_args(args)
    if args.dry_run:
        est = estimate(o)
        print(f"studies: {', '.join(o.studies)}; sizes: {', '.join(size_text(s) for s in o.sizes)}; "
              f"recordings: {', '.join(p.stem for p in o.recordings)}; {o.frames} consecutive frames per run")
        for n in o.notes:
            print(f"note: {n}")
        print(format_estimate(est))
        return 0
    from viewer.cli_args import check_output_dir, check_report_free

    check_output_dir(str(o.out), "--out")
    check_report_free([o.out / f"{s}.json" for s in o.studies], getattr(args, "force", False))
    run_studies(o)
    return 0

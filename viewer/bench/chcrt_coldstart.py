"""`rtwalk bench-chcrt --study coldstart`: a new front refined by the host's waves or settling on the device.

A chcrt front starts as (screen, root). The paper's Algorithm 1 (`cold_start=sync`) refines it in
the front's first passes through waves of occlusion queries whose results the host waits for
within the pass; on the device (`cold_start=device`; its first levels split as if every pair were
entered, ChcrtParams.cold_start_pairs) every pass is a steady pass from the first: it refines the
front one level from its own counts, with nothing read back, and the front settles over its first
frames (ChcrtParams.settle_splits). Per recording x size x effect (table2's
options), glsl and chcrt with both cold starts, interleaved frame by frame over the run's frames
(ask for enough of them for the front to settle: 24 or more): the cold frame (trace ms, host
syncs, bytes read back, Python ms), the frames the device front took to settle and their mean,
the settled frames against the same frames of the others, and the whole run's mean (what a
walkthrough of that length costs). Every pass of either is exact (tests/test_chcrt.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from viewer.bench.chcrt_common import finish_study, table2_rows
from viewer.bench.plots import figure, finish
from viewer.bench.report import fmt, md_table, notes_md, ratio, size_text

#: (label, backend, parameters): the baseline, then chcrt with each cold start
CONFIGS = (("glsl", "glsl", None), ("chcrt sync", "chcrt", "cold_start=sync"),
           ("chcrt device", "chcrt", "cold_start=device"))
SETTLING_STAT = "settling_fronts"  # chcrt's fronts still settling after the frame (ChcrtBackend.end_frame)


@dataclass
class ColdStartRow:
    """One (recording, size, effect). Trace ms are GPU tracing phases per frame; `*_cold_*` the
    first frame after the reset; `settled_after` the frames (the cold one included) until the device
    front reported no settling front (None: not within the run); `*_settled_ms` the mean over the
    frames after that, the same frames for all three."""

    recording: str
    size: str
    effect: str
    frames: int
    glsl_cold_ms: float
    sync_cold_ms: float
    device_cold_ms: float
    glsl_cold_syncs: float
    sync_cold_syncs: float
    device_cold_syncs: float
    sync_cold_bytes_to_host: float
    device_cold_bytes_to_host: float
    sync_cold_python_ms: float
    device_cold_python_ms: float
    settled_after: int | None
    glsl_settling_ms: float  # mean of frames 2..settled_after (the device front settling)
    sync_settling_ms: float
    device_settling_ms: float
    glsl_settled_ms: float
    sync_settled_ms: float
    device_settled_ms: float
    glsl_run_ms: float  # mean of every frame of the run, the cold one included
    sync_run_ms: float
    device_run_ms: float
    speedup_sync_settled: float  # glsl / chcrt over the settled frames
    speedup_device_settled: float
    speedup_sync_run: float  # glsl / chcrt over the whole run
    speedup_device_run: float


def settled_after(frames: list[dict]) -> int | None:
    """Frames (1-based, the cold one included) until the backend reported no settling front; None if never."""
    for k, f in enumerate(frames):
        if f["backend_stats"].get(SETTLING_STAT, 0.0) == 0.0:
            return k + 1
    return None


def _mean(frames: list[dict], key: str = "trace_gpu_ms") -> float:
    return float(np.mean([f[key] for f in frames])) if frames else float("nan")


def study_coldstart(b) -> dict:
    """The three configurations per recording x size x effect (module docstring). `b` is bench.chcrt.Bench."""
    o = b.o
    rows: list[ColdStartRow] = []
    runs = []
    series = []
    for path, size, effect, results in table2_rows(b, "coldstart", CONFIGS, config_wins=True):
        g, s, d = results
        runs += [asdict(r) for r in results]
        rows.append(_row(path.stem, size, effect, g.frames, s.frames, d.frames))
        series.append((f"{path.stem} {size_text(size)} {effect}",
                       [[f["trace_gpu_ms"] for f in r.frames] for r in results], rows[-1].settled_after))
    report = b.header("coldstart", o, {"recordings": [p.stem for p in o.recordings], "effects": o.effects,
                                       "configs": [list(c) for c in CONFIGS]})
    report.update(rows=[asdict(r) for r in rows], runs=runs)
    md = [f"## Cold start: the host's synchronous refinement or the device's settling front ({o.frames} consecutive "
          "frames)", "", f"Device: {b.device_text}. Trace ms = the GPU tracing phases per frame, the three "
          "configurations interleaved frame by frame after a reset. Cold = the first frame; 'settled after' = the "
          "frames until the device front reported no settling front; settling = the mean of frames 2.. that one; "
          "settled = the mean of the frames after it (the same frames for all three); run = every frame. Host "
          "syncs and bytes are the cold frame's (phase timing by sync adds one per phase to all three).", ""]
    md.append(md_table(
        ["recording", "size", "effect", "cold ms glsl / sync / device", "cold host syncs glsl / sync / device",
         "cold Python ms sync / device", "settled after", "settling ms glsl / sync / device",
         "settled ms glsl / sync / device", "vs glsl settled, sync / device", "run ms glsl / sync / device",
         "vs glsl run, sync / device"],
        [[r.recording, r.size, r.effect, f"{fmt(r.glsl_cold_ms)} / {fmt(r.sync_cold_ms)} / {fmt(r.device_cold_ms)}",
          f"{fmt(r.glsl_cold_syncs, 0)} / {fmt(r.sync_cold_syncs, 0)} / {fmt(r.device_cold_syncs, 0)}",
          f"{fmt(r.sync_cold_python_ms)} / {fmt(r.device_cold_python_ms)}",
          "not settled" if r.settled_after is None else str(r.settled_after),
          f"{fmt(r.glsl_settling_ms)} / {fmt(r.sync_settling_ms)} / {fmt(r.device_settling_ms)}",
          f"{fmt(r.glsl_settled_ms)} / {fmt(r.sync_settled_ms)} / {fmt(r.device_settled_ms)}",
          f"{fmt(r.speedup_sync_settled, 2)} / {fmt(r.speedup_device_settled, 2)}",
          f"{fmt(r.glsl_run_ms)} / {fmt(r.sync_run_ms)} / {fmt(r.device_run_ms)}",
          f"{fmt(r.speedup_sync_run, 2)} / {fmt(r.speedup_device_run, 2)}"] for r in rows]))
    md += notes_md(report["notes"])
    _plot(series, o.out / "coldstart.png", b.device["renderer"])
    return finish_study(o, "coldstart", report, "\n".join(md))


def _row(recording: str, size: tuple[int, int], effect: str, g: list[dict], s: list[dict],
         d: list[dict]) -> ColdStartRow:
    k = settled_after(d)
    cut = len(d) if k is None else k
    settling = [x[1:cut] for x in (g, s, d)]
    settled = [x[cut:] for x in (g, s, d)]
    cold = [x[0] for x in (g, s, d)]
    gs, ss, ds = (_mean(x) for x in settled)
    gr, sr, dr = (_mean(x) for x in (g, s, d))
    return ColdStartRow(
        recording, size_text(size), effect, len(d), *(c["trace_gpu_ms"] for c in cold),
        *(float(c["io"]["host_syncs"]) for c in cold), float(cold[1]["io"]["bytes_to_host"]),
        float(cold[2]["io"]["bytes_to_host"]), float(cold[1]["io"]["python_ms"]), float(cold[2]["io"]["python_ms"]),
        k, *(_mean(x) for x in settling), gs, ss, ds, gr, sr, dr, ratio(gs, ss), ratio(gs, ds), ratio(gr, sr),
        ratio(gr, dr))


def _plot(series: list[tuple[str, list[list[float]], int | None]], path, device: str) -> None:
    n = max(len(series), 1)
    fig, axes = figure(n, 1, size=(7.0, 2.6 * n), squeeze=False)
    for ax, (title, per_config, settled) in zip((a[0] for a in axes), series, strict=False):
        for (label, _, _), ms in zip(CONFIGS, per_config, strict=True):
            ax.plot(range(1, len(ms) + 1), ms, marker=".", label=label)
        if settled is not None:
            ax.axvline(settled + 0.5, color="grey", linestyle=":", label="device front settled")
        ax.set_title(title, fontsize=8)
        ax.set_xlabel("frame after the reset (1 = cold)")
        ax.set_ylabel("trace ms")
        ax.legend(fontsize=7)
    finish(fig, path, f"chcrt cold start - {device}")

"""`rtwalk bench` end to end on a tiny path: deterministic frames, JSON report with phases, rays,
Mrays/s and error against Embree, plus the plot."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from tests.cli_runner import run_cli
from viewer.camera import Camera
from viewer.recording import Keyframe, Recording, save_recording


def _room_path(tmp_path):
    cams = [Camera.look_at([-1.5, 1.2, 2.0], [0.5, 0.8, -1.0]), Camera.look_at([1.0, 1.4, 2.2], [-0.5, 0.6, -1.0])]
    keys = [Keyframe.from_camera(float(i), c) for i, c in enumerate(cams)]
    rec = Recording({"builtin": "room"}, (64, 36), 4.0, keys)
    return save_recording(rec, tmp_path / "room-path.json")


def test_bench_writes_report_with_speed_and_error(tmp_path):
    path = _room_path(tmp_path)
    out = tmp_path / "bench"
    proc = subprocess.run([sys.executable, "-m", "viewer.cli", "bench", "--recording", str(path),
                           "--effects", "shadows,ao:2,reflections", "--size", "64x36", "--out", str(out),
                           "--name", "t", "--quiet", "--reference-every", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "t.json").read_text())
    assert (out / "t.png").stat().st_size > 1000
    frames = report["frames"]
    assert [f["frame"] for f in frames] == [0, 1, 2, 3, 4]  # 1 s at 4 fps, sampled, not timed
    for f in frames:
        assert f["rays"]["ao"] > 0 and f["rays"]["shadows"] > 0
        assert set(f["gpu_ms"]) >= {"gbuffer", "raygen", "trace:ao", "trace:shadows", "shade"}
        assert np.isfinite(f["mrays_per_s"]["ao"])
        assert f["error"]["ao"]["hit_agreement"] >= 0.999
        assert f["image_error"]["mae"] < 1.0
    # rays per frame depend only on the camera path: a second run gives the same counts
    proc2 = subprocess.run([sys.executable, "-m", "viewer.cli", "bench", "--recording", str(path),
                            "--effects", "shadows,ao:2,reflections", "--size", "64x36", "--out", str(out),
                            "--name", "t2", "--quiet", "--reference", "none"], capture_output=True, text=True,
                           timeout=300)
    assert proc2.returncode == 0, proc2.stderr
    again = json.loads((out / "t2.json").read_text())
    assert [f["rays"] for f in again["frames"]] == [f["rays"] for f in frames]


def test_bench_chcrt_consecutive_frames_saves_overlays(tmp_path):
    """--first-frame replays consecutive frames; with --save-frames, chcrt's overlay views are
    saved next to the frames, and the heat map differs from the final image."""
    from PIL import Image

    path = _room_path(tmp_path)
    out, frames_dir = tmp_path / "bench", tmp_path / "frames"
    proc = subprocess.run([sys.executable, "-m", "viewer.cli", "bench", "--recording", str(path),
                           "--backend", "chcrt", "--chcrt", "t_q=0.5", "--effects", "primary,ao:1",
                           "--size", "64x36", "--first-frame", "1", "--frames", "2", "--reference", "none",
                           "--save-frames", str(frames_dir), "--frame-every", "1", "--out", str(out),
                           "--name", "c", "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "c.json").read_text())
    assert [f["frame"] for f in report["frames"]] == [1, 2]
    assert "t_q=0.5" in report["backend_params"]
    for f in report["frames"]:
        assert f["overlays"] == [f"query_overdraw_{f['frame']:05d}.png", f"subtree_batches_{f['frame']:05d}.png"]
        final = np.asarray(Image.open(frames_dir / f"frame_{f['frame']:05d}.png"))
        heat = np.asarray(Image.open(frames_dir / f["overlays"][0]))
        assert heat.shape == final.shape and not np.array_equal(heat, final)
    bad = run_cli("bench", "--recording", str(path), "--first-frame", "99", "--quiet")
    assert bad.returncode == 2 and bad.stderr.strip().startswith("rtwalk: error:") and "Traceback" not in bad.stderr


def test_bench_trace_same_rays_against_embree(tmp_path, capsys):
    """`rtwalk bench-trace` on a tiny room path: one row per ray type with the active ray count, finite
    Mrays/s for the backend and for raw Embree, and full hit/miss agreement with the Embree reference."""
    from viewer.cli import main

    path = _room_path(tmp_path)
    out = tmp_path / "trace"
    assert main(["bench-trace", "--recordings", str(path), "--sizes", "48x27", "--effects", "primary,shadows",
                 "--backends", "glsl", "--embree-threads", "1,2", "--rounds", "2", "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "bench_trace.json").read_text())
    assert report["complete"] is True
    (group,) = report["groups"]
    rows = {r["ray_type"]: r for r in group["rows"]}
    assert set(rows) == {"primary", "shadows"}
    assert rows["primary"]["rays"] == 48 * 27 and 0 < rows["shadows"]["rays"] <= 48 * 27
    for r in rows.values():
        for key in ("glsl", "embree_1t", "embree_2t"):
            assert np.isfinite(r["mrays_s"][key]) and r["mrays_s"][key] > 0 and len(r["ms_rounds"][key]) == 2
        assert r["hitmiss_agree"]["glsl"] >= 0.999
    md = (out / "bench_trace.md").read_text()
    assert "| primary | 1,296 |" in md and "--sizes 48x27 --effects primary,shadows" in md
    assert (out / "bench_trace.png").stat().st_size > 1000
    assert "Mrays/s" in capsys.readouterr().out


def test_bench_trace_ctrl_c_keeps_the_groups_done(tmp_path, monkeypatch):
    """Ctrl-C during bench-trace's second group: the first group's rows are written, marked
    "complete": false, with one line and exit 130 (everything measured was lost before)."""
    import viewer.bench.trace_vs_embree as tve
    from tests.cli_runner import run_cli

    real, calls = tve.study_frame, []

    def study_then_ctrl_c(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(tve, "study_frame", study_then_ctrl_c)
    out = tmp_path / "trace"
    proc = run_cli("bench-trace", "--recordings", str(_room_path(tmp_path)), "--sizes", "32x18,48x27",
                   "--effects", "primary", "--backends", "glsl", "--embree-threads", "1", "--rounds", "1",
                   "--out", str(out), "--quiet")
    assert proc.returncode == 130, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rtwalk: interrupted after 1 groups"), lines
    assert "partial report" in lines[0]
    report = json.loads((out / "bench_trace.json").read_text())
    assert report["complete"] is False and len(report["groups"]) == 1 and report["groups"][0]["size"] == [32, 18]


def test_bench_trace_unknown_recording_is_one_error_line(tmp_path, capsys):
    from viewer.cli import main

    assert main(["bench-trace", "--recordings", "nope-walk", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rtwalk: error: ") and "nope-walk" in err[0]


def test_estimate_is_readable_for_short_runs():
    """The bench's "estimated ... more" line: seconds for a short replay ("0.0 min" before)."""
    from viewer.bench.replay import duration_text

    assert duration_text(2.4) == "2 s" and duration_text(89) == "89 s" and duration_text(150) == "2.5 min"

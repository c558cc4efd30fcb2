"""`rtwalk bench-chcrt` end to end (in-process, --quick, city-near at 96x54): the files each study
writes, the table4 error column (threshold 0 is the reference: exactly 0), the overhead variants,
and bad input as one line with exit 2. No speeds are asserted."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from viewer.cli import main

SIZE = "96x54"


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """table4 + overhead + tuning in one command (the scene is loaded once)."""
    out = tmp_path_factory.mktemp("bench-chcrt")
    rc = main(["bench-chcrt", "--quick", "--study", "table4,overhead,tuning", "--sizes", SIZE,
               "--recordings", "city-near", "--out", str(out), "--quiet"])
    return rc, out


def _load(out, study: str) -> dict:
    path = out / f"{study}.json"
    assert path.is_file(), path
    data = json.loads(path.read_text())
    assert data["format"] == "rtwalk-bench-chcrt" and data["study"] == study
    assert data["device"]["renderer"]  # GL_RENDERER string
    for ext in ("md", "png"):
        assert (out / f"{study}.{ext}").stat().st_size > 0
    return data


def test_exit_code(quick_run):
    rc, _ = quick_run
    assert rc == 0


def test_table4_errors(quick_run):
    _, out = quick_run
    data = _load(out, "table4")
    rows = data["rows"]
    assert [r["config"] for r in rows] == ["threshold 0", "threshold 20", "threshold 100", "threshold 200", "glsl"]
    t0 = rows[0]
    assert t0["threshold"] == 0 and t0["mae"] == 0.0 and t0["max_error"] == 0.0 and t0["pct_pixels_over_8"] == 0.0
    assert t0["per_frame_mae"] == [0.0, 0.0]
    for r in rows:
        assert r["size"] == SIZE
        for key in ("mae", "max_error", "pct_pixels_over_8"):
            assert math.isfinite(r[key]) and r[key] >= 0, (r["config"], key, r[key])
        assert len(r["per_frame_mae"]) == 2
    # raw per-frame numbers: 2 consecutive frames per run, the first cold, with the chcrt parameters used
    runs = data["runs"]
    assert len(runs) == len(rows)
    for run, row in zip(runs, rows, strict=True):
        assert [f["cold"] for f in run["frames"]] == [True, False]
        assert run["frame_numbers"][1] == run["frame_numbers"][0] + 1
        if row["threshold"] is not None:
            assert f"visible_threshold={row['threshold']}" in run["params"]
            assert any(p.startswith("chc:") for p in run["frames"][0]["gpu_ms"])
        for f in run["frames"]:
            assert "image_error_vs_threshold0" in f and f["wall_ms"] > 0
    md = (out / "table4.md").read_text()
    for label in ("threshold 0", "threshold 20", "threshold 100", "threshold 200", "glsl"):
        assert f"| {label} | {SIZE} |" in md


def test_overhead_tables(quick_run):
    _, out = quick_run
    data = _load(out, "overhead")
    micro = data["micro"]
    assert len(micro) >= 8
    for m in micro:
        assert math.isfinite(m["us_per_op"]) and m["us_per_op"] >= 0
        assert "unexpected" not in m["check"] and "!=" not in m["check"], m
    configs = [r["config"] for r in data["rows"]]
    assert configs[0] == "default" and "max_batch=1" in configs and "max_multi=1" in configs
    from dataclasses import fields

    from viewer.backends.chcrt import ChcrtParams

    if "query_mode" in {f.name for f in fields(ChcrtParams)}:
        assert "query_mode=hw" in configs
    else:
        assert any("query_mode" in n for n in data["notes"])
    for r in data["rows"]:
        assert r["draws"] >= 1 and r["queries"] >= 0 and math.isfinite(r["trace_ms"])
    md = (out / "overhead.md").read_text()
    assert "| default |" in md and "| max_batch=1 |" in md
    assert "occlusion query one at a time" in md


def test_missing_parameter_is_skipped_with_a_note(monkeypatch):
    import viewer.bench.chcrt as bc

    have = bc._param_names() - {"query_mode"}
    monkeypatch.setattr(bc, "_param_names", lambda: have)
    variants, skipped = bc.overhead_variants("")
    assert all("query_mode" not in text for _, text, _ in variants)
    assert skipped and all("query_mode" in s for s in skipped)


def test_estimate_all_at_640x360_is_under_an_hour():
    import argparse

    import viewer.bench.chcrt as bc

    p = argparse.ArgumentParser()
    bc.add_arguments(p)
    o = bc.options_from_args(p.parse_args(["--sizes", "640x360"]))
    est = bc.estimate(o)
    assert set(est) >= {"table2", "table4", "phases", "overhead"} or o.notes
    assert 0 < sum(est.values()) < 3600


@pytest.mark.parametrize("args,needle", [
    (["--study", "table9"], "table9"),
    (["--sizes", "0x10"], "--sizes"),
    (["--sizes", "wide"], "wide"),
    (["--recordings", "nope-walk"], "nope-walk"),
    (["--chcrt", "max_batch=99"], "max_batch"),
    (["--thresholds", "a,b"], "--thresholds"),
    (["--first-frame", "100000"], "--first-frame"),
    (["--effects", "sparkles"], "sparkles"),
    (["--tuning-grid", "t_q"], "--tuning-grid"),
    (["--tuning-grid", "t_q=1|fast"], "t_q"),
])
def test_bad_input_is_one_line(capsys, args, needle):
    rc = main(["bench-chcrt", "--quick", *args, "--out", "/nonexistent/never-written"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("rtwalk: error")]
    assert len(lines) == 1 and needle in lines[0], err
    assert "Traceback" not in err


def test_tuning_sweep_counts_work(quick_run):
    """The sweep's work counters: glsl makes no queries; chcrt's queries and tests are counted; a
    larger t_q (fewer object-space splits) never needs more queries here."""
    from viewer.bench.chcrt import tuning_configs

    _, out = quick_run
    rows = _load(out, "tuning")["rows"]
    assert [r["params"] for r in rows] == ["glsl", "t_q=0.5", "t_q=2"]
    glsl, a, b = rows
    assert glsl["queries"] == 0 and glsl["query_fragments_per_ray"] == 0 and glsl["tests_per_ray"] > 1
    for r in (a, b):
        # after the cold frame the GPU-driven pass makes its queries by intersecting (no query fragments)
        assert r["queries"] > 0 and r["query_fragments_per_ray"] >= 0 and r["box_tests_per_ray"] > 0
        assert r["tests_per_ray"] == pytest.approx(r["box_tests_per_ray"] + r["query_box_tests_per_ray"]
                                                   + r["tri_tests_per_ray"])
        # the same rays hit the same triangles: triangle tests differ only by the traversal order
        assert r["tri_tests_per_ray"] > 0
    for r in rows:  # lane groups pay at least every lane's own work, the wider ones more
        assert 0 < r["nodes_per_ray"] <= r["simd8_nodes_per_ray"] <= r["simd32_nodes_per_ray"], r
        assert 0 < r["tri_tests_per_ray"] <= r["simd8_tri_per_ray"] <= r["simd32_tri_per_ray"], r
    assert b["queries"] <= a["queries"]
    assert tuning_configs("t_q=1|2;requery_interval=3|8") == [
        "t_q=1,requery_interval=3", "t_q=1,requery_interval=8", "t_q=2,requery_interval=3", "t_q=2,requery_interval=8"]


@pytest.fixture(scope="module")
def ooc_run(tmp_path_factory):
    """The out-of-core and coherence studies, --quick (a 40k-triangle city)."""
    out = tmp_path_factory.mktemp("bench-chcrt-ooc")
    rc = main(["bench-chcrt", "--quick", "--study", "ooc,coherence", "--sizes", SIZE, "--ooc-recordings",
               "city-near", "--ooc-effects", "primary", "--out", str(out), "--quiet"])
    return rc, out


def test_ooc_tables(ooc_run):
    rc, out = ooc_run
    assert rc == 0
    data = _load(out, "ooc")
    t1 = data["table1"]
    assert [r["config"] for r in t1] == ["in-core", "47% in core", "32% in core", "20% in core"]
    for r, pct in zip(t1, (100, 47, 32, 20), strict=True):
        assert abs(r["in_core_pct"] - pct) < 0.5, r
        assert r["triangles"] > 30_000 and math.isclose(r["total_mb"], r["bvh_mb"] + r["geometry_mb"])
    t3 = data["table3"]
    assert len(t3) == 4
    assert t3[0]["upload_bvh_mb"] == 0 and t3[0]["upload_geom_mb"] == 0 and t3[0]["slowdown"] == 1.0
    # the smallest budget re-uploads subtrees every frame, and no more than the larger budgets
    assert t3[-1]["upload_geom_mb"] > 0 and t3[-1]["upload_bvh_mb"] > 0 and t3[-1]["subtrees_uploaded"] > 0
    assert t3[-1]["upload_geom_mb"] >= t3[1]["upload_geom_mb"]
    mem = data["memory"]
    assert mem["build_peak_gib"] > 0 and mem["render_peak_gib"] > 0


def test_coherence_table(ooc_run):
    _, out = ooc_run
    data = _load(out, "coherence")
    rows = data["rows"]
    assert [r["perturb_deg"] for r in rows] == [0.0, 180.0]
    for r in rows:
        assert r["max_abs_diff"] == 0  # conservative chcrt renders glsl's image
        assert r["glsl_trace_ms"] > 0 and r["chcrt_trace_ms"] > 0 and r["queries"] > 0
    assert (out / "coherence-images").is_dir()


@pytest.mark.parametrize("args,needle", [
    (["--study", "ooc", "--ooc-fractions", "1.5"], "--ooc-fractions"),
    (["--study", "ooc", "--ooc-recordings", "sponza-walk"], "builtin"),
    (["--study", "coherence", "--perturbs", "200"], "--perturbs"),
    (["--study", "coherence", "--coherence-effects", "ao:2@perturb=500"], "perturb"),
])
def test_ooc_coherence_bad_input(capsys, args, needle):
    rc = main(["bench-chcrt", "--quick", *args, "--out", "/nonexistent/never-written"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("rtwalk: error")]
    assert len(lines) == 1 and needle in lines[0], err


def test_table2_counts_whole_bvh_passes(tmp_path):
    """table2 reports, per row, chcrt's passes per steady frame that traced the whole BVH and how many
    of them its work probe chose (a limit no front can meet sends every front there between its
    measurements; none without the probe)."""
    rows = {}
    for probe in ("work_probe=4,work_ratio_full=0.001,work_ratio_full_any=0.001", "work_probe=0"):
        out = tmp_path / probe.split(",")[0].replace("=", "")
        rc = main(["bench-chcrt", "--quick", "--study", "table2", "--sizes", SIZE, "--recordings", "city-near",
                   "--effects", "primary", "--frames", "4", "--chcrt", probe, "--out", str(out), "--quiet"])
        assert rc == 0
        rows[probe] = _load(out, "table2")["rows"]
        assert "chcrt whole-BVH passes" in (out / "table2.md").read_text()
    on, off = (rows[k][0] for k in rows)
    assert on["chcrt_wasted_passes"] > 0 and on["chcrt_full_bvh_passes"] >= on["chcrt_wasted_passes"], on
    assert off["chcrt_wasted_passes"] == 0, off
    # ... and per steady frame along the path (frames 2..4), averaging to the row's figures
    assert len(on["frame_numbers"]) == len(on["chcrt_full_bvh_by_frame"]) == len(on["glsl_trace_by_frame"]) == 3
    assert np.mean(on["chcrt_full_bvh_by_frame"]) == pytest.approx(on["chcrt_full_bvh_passes"])
    assert np.mean(on["chcrt_trace_by_frame"]) == pytest.approx(on["chcrt_trace_ms"])


def test_table2_path_windows_and_plot(tmp_path):
    """table2 along a path: the speedup in windows of consecutive frames is the ratio of the
    windows' summed trace times (not a mean of per-frame ratios), listed in the Markdown for paths of
    PATH_MIN_FRAMES frames or more, and the plot draws it frame by frame."""
    from viewer.bench.chcrt import PATH_MIN_FRAMES, PATH_WINDOWS, Table2Row, _path_md, _plot_table2

    n = 2 * PATH_WINDOWS + 1
    frames = list(range(1, n + 1))
    glsl = [10.0] * n
    chcrt = [5.0 if k < n // 2 else 20.0 for k in range(n)]  # 2x faster, then 2x slower (whole-BVH)
    full = [0.0 if k < n // 2 else 1.0 for k in range(n)]
    row = Table2Row("walk", "64x36", "primary", 1.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 0.8, 0.8, 1.0, 1.0,
                    0.5, 0.5, frames, glsl, chcrt, full)
    win = row.windows(PATH_WINDOWS)
    assert len(win) == PATH_WINDOWS and win[0][:2] == (1, 2) and win[-1][1] == n
    assert win[0][2] == pytest.approx(2.0) and win[0][3] == 0.0
    assert win[-1][2] == pytest.approx(0.5) and win[-1][3] == 1.0
    a, b = win[PATH_WINDOWS // 2][:2]  # the window across the switch: summed times, not mean ratios
    ks = range(a - 1, b)
    assert win[PATH_WINDOWS // 2][2] == pytest.approx(sum(glsl[k] for k in ks) / sum(chcrt[k] for k in ks))
    md = "\n".join(_path_md([row]))
    assert "Along the path" in md and "1-2: 2.00 (0.0)" in md and ": 0.50 (1.0)" in md
    short = Table2Row(*[getattr(row, f) for f in list(row.__dataclass_fields__)[:16]],
                      frames[:PATH_MIN_FRAMES - 1], glsl[:PATH_MIN_FRAMES - 1], chcrt[:PATH_MIN_FRAMES - 1],
                      full[:PATH_MIN_FRAMES - 1])
    assert _path_md([short]) == []
    _plot_table2([row, short], tmp_path / "t2.png", "test device")
    assert (tmp_path / "t2.png").stat().st_size > 1000


def test_stages_study_runs_each_backend_in_both_stages(tmp_path):
    """--study stages: glsl and chcrt in the fragment and the compute stage, interleaved; each row has
    the four trace times and the ratios the Markdown table shows (no speed asserted), and the runs
    carry the stage parameters they were made with."""
    rc = main(["bench-chcrt", "--quick", "--study", "stages", "--sizes", SIZE, "--recordings", "city-near",
               "--effects", "primary", "--frames", "3", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    data = _load(tmp_path, "stages")
    (row,) = data["rows"]
    times = [row[k] for k in ("glsl_fragment_ms", "glsl_compute_ms", "chcrt_fragment_ms", "chcrt_compute_ms")]
    assert all(t > 0 for t in times), row
    assert row["glsl_compute_speedup"] == pytest.approx(times[0] / times[1])
    assert row["chcrt_speedup_compute"] == pytest.approx(times[1] / times[3])
    assert row["chcrt_speedup_best"] == pytest.approx(min(times[:2]) / min(times[2:]))
    params = [run["params"] or "" for run in data["runs"]]
    assert "stage=compute" in params[1] and "visible_stage=compute" in params[3], params
    assert "chcrt vs glsl, compute" in (tmp_path / "stages.md").read_text()


def test_coldstart_study_compares_both_cold_starts(tmp_path):
    """--study coldstart: glsl and chcrt with each cold start, interleaved; the device cold start's
    cold frame waits for fewer host syncs than the synchronous one's (its waves of queries), the
    runs carry the cold start they were made with, and the settled frames are the ones after the
    device front reported none settling (no speed asserted). The other studies take the paper's
    synchronous cold start unless told otherwise."""
    from viewer.bench.chcrt_coldstart import settled_after

    rc = main(["bench-chcrt", "--quick", "--study", "coldstart", "--sizes", SIZE, "--recordings", "city-near",
               "--effects", "primary", "--frames", "3", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    data = _load(tmp_path, "coldstart")
    (row,) = data["rows"]
    glsl, sync, device = data["runs"]
    assert "cold_start=sync" in sync["params"] and "cold_start=device" in device["params"], data["runs"]
    assert row["sync_cold_syncs"] > row["device_cold_syncs"], row
    assert row["sync_cold_ms"] == sync["frames"][0]["trace_gpu_ms"]
    k = settled_after(device["frames"])
    assert row["settled_after"] == k
    if k is None:  # (3 frames: a young front may not have settled) every later frame counts as settling
        assert row["device_settling_ms"] == pytest.approx(np.mean([f["trace_gpu_ms"] for f in device["frames"][1:]]))
    assert "cold_start=sync" in data["parameters"]["chcrt"]
    assert settled_after([{"backend_stats": {"settling_fronts": s}} for s in (2, 1, 0, 0)]) == 3
    assert settled_after([{"backend_stats": {"settling_fronts": 1}}]) is None

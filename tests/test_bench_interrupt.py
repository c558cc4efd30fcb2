"""Ctrl-C / SIGTERM during a multi-configuration benchmark keeps what it finished
(viewer/bench/partial.py): the JSON of the finished studies/rows, `"complete": false`, one
`rtwalk: interrupted ...: partial report PATH` line, exit 130. One small run per command family,
the signal sent once the first study/row is known to be done."""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest


def _cl_reason() -> str | None:
    from viewer.cl import cl_available

    return cl_available()


def _interrupt(args: list[str], done, signame: str = "SIGINT", timeout: float = 120) -> tuple[int, str]:
    """Run `rtwalk ARGS`, send the signal once `done(stdout, stderr)` (so far) is true; (exit code, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "viewer.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    out: list[str] = []
    err: list[str] = []
    readers = [threading.Thread(target=lambda s=s, b=b: b.extend(iter(lambda: s.read(1), "")), daemon=True)
               for s, b in ((proc.stdout, out), (proc.stderr, err))]
    for r in readers:
        r.start()
    deadline = time.monotonic() + timeout
    while not done("".join(out), "".join(err)):
        assert proc.poll() is None and time.monotonic() < deadline, "".join(err)[-2000:]
        time.sleep(0.05)
    proc.send_signal(getattr(signal, signame))
    code = proc.wait(timeout=120)
    for r in readers:
        r.join(timeout=10)
    return code, "".join(err)


def _check(code: int, err: str, report: Path) -> dict:
    assert code == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    said = [ln for ln in err.replace("\r", "\n").splitlines() if ln.startswith("rtwalk:")]
    assert len(said) == 1 and said[0].startswith("rtwalk: interrupted") and "partial report" in said[0], said
    assert str(report) in said[0] and '("complete": false)' in said[0], said
    data = json.loads(report.read_text())
    assert data["complete"] is False
    return data


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_bench_bvh_keeps_the_builds_done(tmp_path, signame):
    out = tmp_path / "b"
    code, err = _interrupt(["bench-bvh", "--builders", "sah", "--triangles", ",".join(["4000"] * 200),
                            "--out", str(out)], lambda o, e: " tris " in o, signame)
    data = _check(code, err, out / "bvh-build.json")
    assert 1 <= len(data["rows"]) < 200 and all(r["builder"] == "sah" for r in data["rows"])


def test_bench_pgrid_keeps_the_studies_done(tmp_path):
    if _cl_reason() is not None:
        pytest.skip(f"no OpenCL device: {_cl_reason()}")
    out = tmp_path / "bp"
    code, err = _interrupt(["bench-pgrid", "--study", "table41,lightdist,anim", "--scenes", "city", "--city-size",
                            "3000", "--sizes", "64x36", "--frames", "1", "--light-scene", "city",
                            "--distances", "0.5,1,2,4,8,16,32,64", "--anim-frames", "200", "--anim-size", "64x36",
                            "--out", str(out), "--quiet"],
                           lambda o, e: (out / "table41.json").exists() and "4.1" in o)
    data = _check(code, err, out / "table41.json")
    assert len(data["rows"]) == 1
    assert "study lightdist left out" in err and not (out / "lightdist.json").exists()
    assert not (out / "anim.json").exists()


def test_bench_voxelwalk_keeps_the_rows_done(tmp_path):
    if _cl_reason() is not None:
        pytest.skip(f"no OpenCL device: {_cl_reason()}")
    out = tmp_path / "vw"
    code, err = _interrupt(["bench-voxelwalk", "--study", "table51", "--scenes", "room", "--sizes",
                            ",".join(["48x27"] * 100), "--repeats", "1", "--out", str(out)],
                           lambda o, e: e.count("capturing reflection rays") >= 2)
    data = _check(code, err, out / "table51.json")
    assert 1 <= len(data["rows"]) < 100


def test_bench_cl_keeps_the_rows_done(tmp_path):
    if _cl_reason() is not None:
        pytest.skip(f"no OpenCL device: {_cl_reason()}")
    out = tmp_path / "cl"
    code, err = _interrupt(["bench-cl", "--elements", ",".join(["3000"] * 300), "--reps", "2", "--out", str(out)],
                           lambda o, e: " n=" in o)
    data = _check(code, err, out / "bench_cl.json")
    assert 1 <= len(data["rows"]) < 300 * 3 and (out / "bench_cl.md").exists()


def test_bench_gbuffer_keeps_the_frames_done(tmp_path):
    out = tmp_path / "gb"
    code, err = _interrupt(["bench-gbuffer", "--frames", "300", "--size", "32x18", "--scene-size", "20000",
                            "--out", str(out)], lambda o, e: "frame 30/300" in e)
    data = _check(code, err, out / "gbuffer.json")
    assert 30 <= data["frames"] < 300
    assert all(len(c["ms"]) == data["frames"] for c in data["configs"].values())


def test_bench_grids_keeps_the_rounds_done(tmp_path):
    if _cl_reason() is not None:
        pytest.skip(f"no OpenCL device: {_cl_reason()}")
    out = tmp_path / "grids.json"
    code, err = _interrupt(["bench-grids", "--scene", "mixed", "--size", "32x18", "--backends", "clbvh,ugrid",
                            "--rounds", "5000", "--json", str(out)], lambda o, e: "round 1/5000 done" in e)
    data = _check(code, err, out)
    assert 1 <= data["rounds"] < 5000 and [r["backend"] for r in data["rows"]] == ["clbvh", "ugrid"]
    assert all(len(r["times"]) == data["rounds"] and r["ms"] > 0 for r in data["rows"])


def test_bench_chcrt_keeps_the_studies_done(tmp_path):
    """The signal once tuning (one comparison in --quick) is printed: table2, several comparisons,
    stops at its next one and is named; tuning's report is kept, marked incomplete (a signal after
    the last study's comparisons leaves the run complete: test_chcrt_signal_in_the_last_study...)."""
    out = tmp_path / "chc"
    code, err = _interrupt(["bench-chcrt", "--quick", "--study", "tuning,table2", "--sizes", "32x18",
                            "--recordings", "city-near", "--out", str(out), "--quiet"],
                           lambda o, e: "tuning: " in o)
    data = _check(code, err, out / "tuning.json")
    assert data["study"] == "tuning"
    assert "study table2 left out" in err and not (out / "table2.json").exists()


def test_keep_partial_marks_and_names_what_it_kept(tmp_path, capsys):
    """In-process: a finished study is re-marked incomplete, the rows in hand are written, the
    study in progress is named; a failing plot costs a note, not the JSON."""
    from viewer.bench.partial import keep_partial, write_plots
    from viewer.bench.report import write_study

    done = write_study(tmp_path, "first", {"rows": [1]}, "md")
    assert json.loads(done["json"].read_text())["complete"] is True
    with pytest.raises(KeyboardInterrupt) as exc:
        with keep_partial("bench-x") as part:
            part.finished(done["json"])
            part.keep(lambda complete: write_study(tmp_path, "rows", {"complete": complete, "rows": [2]}, "md")["json"])
            part.started("second")
            raise KeyboardInterrupt
    line = exc.value.args[0]
    assert line.startswith("interrupted (study second left out): bench-x: partial report ")
    assert str(done["json"]) in line and str(tmp_path / "rows.json") in line and line.endswith('("complete": false)')
    for name in ("first", "rows"):
        assert json.loads((tmp_path / f"{name}.json").read_text())["complete"] is False
    write_plots(lambda: 1 / 0)
    assert "plot not written" in capsys.readouterr().err


def test_chcrt_signal_in_the_last_study_keeps_the_run_complete(tmp_path, monkeypatch):
    """In-process, fake studies: a deferred signal that arrives during the last study (after its
    comparisons) leaves every report `"complete": true` (chcrt checked after each study and re-marked
    a finished run incomplete); one during an earlier study stops before the next, which is named."""
    from viewer.bench import chcrt
    from viewer.bench.report import write_study

    class FakeBench:
        def __init__(self, o):
            self.interrupt = None

    def study(name: str, signal_here: bool):
        def run(b) -> dict:
            if signal_here:
                b.interrupt.flag.requested = True  # what the deferred handler does
            return {**write_study(tmp_path, name, {"rows": [name]}, "md"), "markdown": "md"}
        return run

    monkeypatch.setattr(chcrt, "Bench", FakeBench)
    monkeypatch.setattr(chcrt, "estimate", lambda o: {})
    o = chcrt.StudyOptions(studies=["a", "b"], sizes=[(8, 8)], recordings=[], out=tmp_path, quiet=True)
    monkeypatch.setattr(chcrt, "STUDY_FUNCS", {"a": study("a", False), "b": study("b", True)})
    assert len(chcrt.run_studies(o, out=io.StringIO())) == 2
    assert all(json.loads((tmp_path / f"{n}.json").read_text())["complete"] is True for n in "ab")

    monkeypatch.setattr(chcrt, "STUDY_FUNCS", {"a": study("a", True), "b": study("b", False)})
    (tmp_path / "b.json").unlink()
    with pytest.raises(KeyboardInterrupt) as exc:
        chcrt.run_studies(o, out=io.StringIO())
    assert "study b left out" in exc.value.args[0] and not (tmp_path / "b.json").exists()
    assert json.loads((tmp_path / "a.json").read_text())["complete"] is False


def test_bench_trace_partial_plot_failure_is_a_note(tmp_path, monkeypatch):
    """bench-trace interrupted: a plot that fails on the partial groups is a note line; the JSON
    and the one interrupt line stay (the plot's exception escaped as a traceback)."""
    from tests.cli_runner import run_cli
    from viewer.bench import trace_vs_embree

    def measure(args, ctx, recs, sizes, backends, threads, settings, report) -> None:
        report["groups"].append({"recording": "r", "frame": 0, "size": [8, 8]})
        raise KeyboardInterrupt

    monkeypatch.setattr(trace_vs_embree, "_measure", measure)
    monkeypatch.setattr(trace_vs_embree, "_markdown", lambda report: "md")
    monkeypatch.setattr(trace_vs_embree, "_plot", lambda report, path: 1 / 0)
    proc = run_cli("bench-trace", "--backends", "glsl", "--embree-threads", "", "--out", str(tmp_path / "t"))
    assert proc.returncode == 130 and "Traceback" not in proc.stderr, proc.stderr
    assert "plot not written" in proc.stderr and "partial report" in proc.stderr
    assert json.loads((tmp_path / "t/bench_trace.json").read_text())["complete"] is False


def test_deferred_interrupt_keeps_an_ignored_signal_ignored():
    """A signal the parent set to SIG_IGN (`rtwalk bench-... &` in a script ignores SIGINT) is not
    turned into a stop request inside a deferred block (it stopped the run there); the handlers
    are back after the block. Handlers are only inspected, no signal is sent."""
    from viewer.interrupt import deferred_interrupt

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with deferred_interrupt():
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
            assert callable(signal.getsignal(signal.SIGTERM))
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) == before[signal.SIGTERM]
    finally:
        signal.signal(signal.SIGINT, before[signal.SIGINT] or signal.default_int_handler)


def test_report_json_is_replaced_whole(tmp_path, monkeypatch):
    """An interrupt while a report is written leaves the earlier JSON as it was, and no temporary
    file (a plain write_text cut it: a finished report lost, a partial one unreadable)."""
    import os

    from viewer.bench import report

    path = tmp_path / "r.json"
    report.write_json(path, {"complete": True, "rows": [1]})

    def cut(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", cut)
    with pytest.raises(KeyboardInterrupt):
        report.write_json(path, {"complete": False, "rows": [1, 2]})
    monkeypatch.undo()
    assert json.loads(path.read_text()) == {"complete": True, "rows": [1]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]

"""`rtwalk bench-cl` (viewer/bench/cl_primitives.py): a tiny run writes its table, and bad input
or a missing OpenCL device is one error line with exit status 2."""

from __future__ import annotations

import json

import pytest

from viewer.bench import cl_primitives as bench
from viewer.cl import context as clctx
from viewer.cli import main as cli_main
from viewer.errors import RtwalkError


def test_parse_sizes():
    assert bench.parse_sizes("1M,10M") == [1_000_000, 10_000_000]
    assert bench.parse_sizes("250k, 1.5M,77") == [250_000, 1_500_000, 77]
    for bad in ("", "ten", "0", "1G", "-5"):
        with pytest.raises(RtwalkError, match="--elements"):
            bench.parse_sizes(bad)


def test_small_run_writes_json_markdown_plot(tmp_path, capsys):
    reason = clctx.cl_available()
    if reason is not None:
        pytest.skip(f"no OpenCL device: {reason}")
    out = tmp_path / "b"
    assert cli_main(["bench-cl", "--elements", "3000,20K", "--reps", "2", "--out", str(out)]) == 0
    report = json.loads((out / "bench_cl.json").read_text())
    rows = report["rows"]
    assert [(r["op"], r["n"]) for r in rows] == [(op, n) for n in (3000, 20000) for op in bench.OPS]
    for r in rows:
        assert len(r["numpy_samples_ms"]) == len(r["opencl_samples_ms"]) == 2
        assert r["opencl_ms"] > 0 and r["numpy_ms"] > 0 and r["speedup"] > 0
    md = (out / "bench_cl.md").read_text()
    assert "| sort | 20,000 |" in md and "rtwalk bench-cl --elements 3000,20K" in md
    assert (out / "bench_cl.png").stat().st_size > 1000
    assert "speedup" in capsys.readouterr().out


@pytest.mark.parametrize("argv,msg", [(["--elements", "big"], "--elements"), (["--sizes", "big"], "--elements"),
                                      (["--ops", "sort,fft"], "--ops"),
                                      (["--reps", "0"], "--reps")])
def test_bad_options_exit_2(tmp_path, capsys, argv, msg):
    assert cli_main(["bench-cl", *argv, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rtwalk: error: ") and msg in err[0]


def test_no_opencl_device_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(clctx, "_context", None)
    monkeypatch.setattr(clctx, "list_devices", lambda: [])
    assert cli_main(["bench-cl", "--sizes", "1000", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["rtwalk: error: no OpenCL device (install pocl-opencl-icd)"]

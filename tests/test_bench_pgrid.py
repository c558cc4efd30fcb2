"""`rtwalk bench-pgrid` (viewer/bench/pgrid.py): a tiny run of every study writes its tables and
plots with numbers that add up, the cost model follows its formulas, and bad input is one error
line with exit status 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from viewer.bench import pgrid as bench
from viewer.cli import main


def _cl_reason() -> str | None:
    from viewer.cl import cl_available

    return cl_available()


def test_model_totals_follow_the_formulas():
    t = {b: {"primary_build": 10.0, "primary_trace": 5.0, "shadow_build": 0.0, "rearrange": 0.0, "shadow_trace": 4.0,
             "secondary_build": 0.0, "secondary_trace": 6.0} for b in ("clbvh", "glsl", "ugrid")}
    t["pgrid"] = {"primary_build": 2.0, "primary_trace": 3.0, "shadow_build": 1.0, "rearrange": 0.5,
                  "shadow_trace": 2.5, "secondary_build": 7.0, "secondary_trace": 6.0}
    lights = np.array([0.0, 1.0, 4.0])
    m = bench.model_totals(t, lights, np.zeros(3))
    assert np.allclose(m["clbvh"], 15 + 4 * lights)
    assert np.allclose(m["pgrid"], 5 + 4 * lights)
    m = bench.model_totals(t, np.ones(3), np.array([0.0, 1.0, 2.0]))
    assert np.allclose(m["pgrid"], [9.0, 9 + 7 + 6, 9 + 7 + 12])  # the uniform grid is built once when B > 0


@pytest.mark.parametrize("argv, message", [
    (["--sizes", "64"], "--sizes"), (["--study", "nope"], "--study"), (["--scenes", "moon"], "--scenes"),
    (["--frames", "0"], "--frames")])
def test_bad_input_is_one_error_line(argv, message, capsys):
    assert main(["bench-pgrid", *argv, "--out", "/nonexistent/never"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rtwalk: error:") and message in err[0]


def test_tiny_run_writes_every_study(tmp_path, capsys):
    reason = _cl_reason()
    if reason is not None:
        pytest.skip(f"no OpenCL device: {reason}")
    out = tmp_path / "bp"
    rc = main(["bench-pgrid", "--scenes", "city", "--city-size", "3000", "--sizes", "64x36", "--frames", "1",
               "--light-scene", "city", "--distances", "0.5,2", "--anim-frames", "2", "--anim-size", "64x36",
               "--out", str(out), "--quiet"])
    assert rc == 0
    t41 = json.loads((out / "table41.json").read_text())
    (row,) = t41["rows"]
    for b in bench.BACKENDS:
        terms = row["terms"][b]
        parts = sum(terms[k] for k in ("primary_build", "primary_trace", "shadow_build", "rearrange", "shadow_trace"))
        assert terms["total"] == pytest.approx(parts) and terms["primary_trace"] > 0 and terms["shadow_trace"] > 0
    assert row["terms"]["pgrid"]["shadow_build"] > 0 and row["terms"]["pgrid"]["rearrange"] > 0
    assert row["stats"]["pgrid"]["pairs_shadows"] > 0 and row["stats"]["ugrid"]["grid_pairs"] > 0
    ld = json.loads((out / "lightdist.json").read_text())
    assert [r["distance"] for r in ld["rows"]] == [0.5, 2.0]
    assert {"chunk=64", "chunk=128", "chunk=256", "no balancing", "clbvh"} <= set(ld["rows"][0]["configs"])
    (pr,) = json.loads((out / "pairs.json").read_text())["rows"]
    cam = pr["camera"]
    assert pr["ugrid_pairs"] > 0 and cam["k=1,frustum"]["pairs"] > 0
    for k in (1, 2, 4):  # back-face culling only removes pairs; coarser tiles never add any
        assert cam[f"k={k},back"]["pairs"] <= cam[f"k={k},frustum"]["pairs"]
        assert cam[f"k={k},back"]["culled_backface"] > 0
    assert cam["k=4,frustum"]["pairs"] <= cam["k=2,frustum"]["pairs"] <= cam["k=1,frustum"]["pairs"]
    (rr,) = json.loads((out / "rearrange.json").read_text())["rows"]
    assert rr["rearrange_ms"] == row["phases"]["pgrid"]["pgrid:rearrange:shadows"] > 0
    anim = {r["backend"]: r for r in json.loads((out / "anim.json").read_text())["rows"]}
    assert set(anim) == {"pgrid", "ugrid", "clbvh", "glsl"}
    assert anim["pgrid"]["builds_ms"]["pgrid:build:primary"] > 0 and anim["pgrid"]["builds_ms"]["build:bvh"] > 0
    assert anim["clbvh"]["builds_ms"]["build:bvh4"] > 0 and anim["ugrid"]["builds_ms"]["ugrid:build"] > 0
    for name in ("table41", "lightdist", "model", "pairs", "rearrange", "anim"):
        assert (out / f"{name}.md").read_text().startswith("# ")
        assert (out / f"{name}.png").stat().st_size > 1000
    assert "break-even" in (out / "model.md").read_text().lower()

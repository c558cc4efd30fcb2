"""`rtwalk bench-voxels` end to end on the built-in room at a tiny size: the report has every
table, utilisations are fractions, bigger stacks never restart more, errors shrink with resolution."""

from __future__ import annotations

import json

import pytest

from tests.conftest import opencl_missing
from viewer.cli import main

pytestmark = pytest.mark.skipif(opencl_missing() is not None, reason=opencl_missing() or "")


def test_bench_voxels_room(tmp_path, gl_ctx):
    rc = main(["bench-voxels", "--scenes", "room", "--resolutions", "16,64", "--size", "96x54", "--effects",
               "primary,shadows,ao:1", "--rounds", "1", "--stacks", "1,8", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    rep = json.loads((tmp_path / "bench_voxels.json").read_text())
    md = (tmp_path / "bench_voxels.md").read_text()
    assert "Table 1 analog" in md and "Table 2 analog" in md and "Speed against error" in md
    assert (tmp_path / "bench_voxels.png").stat().st_size > 0
    sc = rep["scenes"][0]
    assert set(sc["rays"]) == {"primary", "shadows", "ao"}
    for rr in sc["resolutions"]:
        for srow in rr["structures"].values():
            s1, s8 = srow["stacks"]["1"], srow["stacks"]["8"]
            for lb in sc["rays"]:
                for w in ("8", "32", "64"):
                    u = s8["record"][lb]["lanes"][w]["utilisation"]
                    assert 0 < u <= 1
                assert s8["record"][lb]["lanes"]["8"]["utilisation"] >= s8["record"][lb]["lanes"]["64"]["utilisation"]
                assert s1["record"][lb]["restarts"] >= s8["record"][lb]["restarts"]
                assert s8["record"][lb]["cut_steps"] == 0
    e16 = sc["resolutions"][0]["errors"]["primary"]["t_err_voxels_mean"]
    assert sc["resolutions"][1]["image_mae"] < sc["resolutions"][0]["image_mae"]
    assert e16 >= 0


def test_bench_voxels_bad_input(capsys):
    assert main(["bench-voxels", "--resolutions", "100"]) == 2
    assert "power of two" in capsys.readouterr().err
    assert main(["bench-voxels", "--structures", "grid"]) == 2
    assert main(["bench-voxels", "--scenes", "nope"]) == 2

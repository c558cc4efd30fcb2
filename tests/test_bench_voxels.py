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


def test_pick_passes():
    from viewer.bench.voxels import pick_passes

    assert pick_passes(36, 4) == [4, 13, 22, 31]
    assert pick_passes(36, 0) == list(range(36)) and pick_passes(3, 5) == [0, 1, 2]
    assert pick_passes(1, 1) == [0] and pick_passes(5, 1) == [2]
    for m in range(1, 40):
        for k in range(1, m + 1):
            p = pick_passes(m, k)
            assert len(p) == k and p == sorted(set(p)) and 0 <= p[0] and p[-1] < m


def _study(tmp_path, sub: str, extra: list[str]) -> dict:
    out = tmp_path / sub
    rc = main(["bench-voxels", "--scenes", "room", "--resolutions", "32", "--size", "64x36", "--effects",
               "primary,ao:5", "--rounds", "1", "--stacks", "2", "--no-image", "--out", str(out), "--quiet", *extra])
    assert rc == 0
    return json.loads((out / "bench_voxels.json").read_text())


def test_record_passes_subset(tmp_path, gl_ctx):
    """Recording K of the ao passes gives, pass for pass, what recording all of them gives for those
    passes; the aggregate is theirs alone, the markdown names them; timing and errors use every pass."""
    from viewer.bench.lockstep import combine

    full = _study(tmp_path, "all", [])
    part = _study(tmp_path, "k2", ["--record-passes", "2"])
    sc_f, sc_p = full["scenes"][0], part["scenes"][0]
    assert sc_p["passes"]["ao"] == 5 and sc_p["recorded_passes"] == {"primary": [0], "ao": [1, 3]}
    assert sc_f["recorded_passes"]["ao"] == [0, 1, 2, 3, 4] and full["complete"] and part["complete"]
    for kind in ("bvh", "kd", "octree"):
        rf = sc_f["resolutions"][0]["structures"][kind]["stacks"]["2"]["record"]
        rp = sc_p["resolutions"][0]["structures"][kind]["stacks"]["2"]["record"]
        assert rf["primary"]["per_pass"] == rp["primary"]["per_pass"]
        picked = [q for q in rf["ao"]["per_pass"] if q["pass"] in (1, 3)]
        assert rp["ao"]["per_pass"] == picked and rp["ao"]["passes"] == [1, 3] and rp["ao"]["of_passes"] == 5
        assert rp["ao"]["rays"] == sum(q["rays"] for q in picked) < rf["ao"]["rays"] == sc_f["rays"]["ao"]
        assert rp["ao"]["restarts"] == sum(q["steps"][3] for q in picked)
        for w in ("8", "32", "64"):
            want = combine([{k: v for k, v in q["lanes"][w].items()} for q in picked], int(w))
            assert rp["ao"]["lanes"][w]["utilisation"] == want["utilisation"]
            assert rp["ao"]["lanes"][w]["slots"] == want["slots"] > 0
    assert sc_p["resolutions"][0]["errors"]["ao"]["rays"] == sc_p["rays"]["ao"]  # errors: every ray
    md = (tmp_path / "k2" / "bench_voxels.md").read_text()
    assert "ao 2 of 5 passes (1, 3)" in md and "primary 1 of 1 passes" in md


def test_finished_scene_survives_a_later_error(tmp_path, gl_ctx, monkeypatch):
    import viewer.bench.voxels as bv

    real = bv.study_scene
    calls = []

    def flaky(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("late failure")
        return real(*a, **k)

    monkeypatch.setattr(bv, "study_scene", flaky)
    with pytest.raises(RuntimeError):
        main(["bench-voxels", "--scenes", "room,room", "--resolutions", "16", "--size", "64x36", "--effects",
              "primary", "--rounds", "1", "--stacks", "2", "--structures", "bvh", "--no-image", "--out",
              str(tmp_path), "--quiet"])
    rep = json.loads((tmp_path / "bench_voxels.json").read_text())
    assert rep["complete"] is False and len(rep["scenes"]) == 1
    assert rep["scenes"][0]["resolutions"][0]["resolution"] == 16
    assert "Partial" in (tmp_path / "bench_voxels.md").read_text()


def test_voxelize_only_keeps_finished_structures(tmp_path, monkeypatch):
    """--voxelize-only writes its report after every structure: a build that dies late (the
    4096^3 KD-tree ran out of memory here) leaves the finished rows on disk."""
    import viewer.backends.voxels.scene as vscene

    real = vscene.build_structure

    def build(kind, vox):
        if kind == "octree" and vox.stats["resolution"] == 32:
            raise MemoryError("simulated")
        return real(kind, vox)

    monkeypatch.setattr(vscene, "build_structure", build)
    with pytest.raises(MemoryError):
        main(["bench-voxels", "--scenes", "room", "--resolutions", "16,32", "--voxelize-only", "--out",
              str(tmp_path), "--quiet"])
    rows = json.loads((tmp_path / "voxelize.json").read_text())
    assert [r["resolution"] for r in rows] == [16, 32]
    assert set(rows[0]["structures"]) == {"bvh", "kd", "octree"} and set(rows[1]["structures"]) == {"bvh", "kd"}
    assert all(r["count"] > 0 for r in rows)

"""The bench harness drives a backend it has never heard of: a probe backend registered only in
this test (its own parameters, phase name, counter and reset), timed next to glsl. Checks that
configurations are interleaved frame by frame, reset once after the warm-up, that the probe's own
phase counts as tracing time and that its parameters reach the report; plus the report and plot
helpers every study uses."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest

from viewer.backends.base import BackendContext, TraceResult
from viewer.backends.gl_traversal import ResumableTraversal
from viewer.backends.interface import BackendInfo
from viewer.camera import Camera
from viewer.rays import HitBuffer, PassInfo, RayBatch
from viewer.recording import Keyframe, Recording, save_recording

LOG: list[tuple[str, str, int]] = []  # (event, label, frame)


@dataclass
class ProbeParams:
    label: str = "a"
    repeat: int = 1  # draws per pass (more work: a visible difference in time and counters)

    def validate(self, source: str = "probe") -> None:
        from viewer.errors import RtwalkError

        if not 1 <= self.repeat <= 8:
            raise RtwalkError(f"{source}: repeat must be in 1..8")


class ProbeBackend:
    """Full BVH traversal (the GL backends' resumable traversal) under its own phase name, with a
    counter and a log."""

    info = BackendInfo("probe", "test backend", params=ProbeParams, counters=("probe_draws",),
                       phases=("probe:trace",))

    def __init__(self, bc: BackendContext, params: ProbeParams):
        self.bc, self.params = bc, params
        self.overlays_enabled = False
        self.traversal = ResumableTraversal(bc)
        self.frame = -1

    def begin_frame(self, frame_index: int) -> None:
        self.frame = frame_index
        LOG.append(("frame", self.params.label, frame_index))

    def reset(self) -> None:
        LOG.append(("reset", self.params.label, self.frame))

    def tile_level(self, size: tuple[int, int]) -> int:
        return -1

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        with self.bc.profiler.phase("probe:trace"):
            for _ in range(self.params.repeat):
                self.traversal.bind_flags(hits.size)
                self.traversal.run(rays, pinfo, hits)
        return TraceResult(stats={"probe_draws": float(self.params.repeat)})

    def release(self) -> None:
        self.traversal.release()


@pytest.fixture
def probe_registered(monkeypatch):
    from viewer import backends

    monkeypatch.setitem(backends.BACKENDS, "probe", f"{__name__}:ProbeBackend")
    LOG.clear()
    yield
    LOG.clear()


def _room_path(tmp_path):
    cams = [Camera.look_at([-1.5, 1.2, 2.0], [0.5, 0.8, -1.0]), Camera.look_at([1.0, 1.4, 2.2], [-0.5, 0.6, -1.0])]
    keys = [Keyframe.from_camera(float(i), c) for i, c in enumerate(cams)]
    return save_recording(Recording({"builtin": "room"}, (64, 36), 4.0, keys), tmp_path / "room-path.json")


def test_harness_drives_an_unknown_backend(probe_registered, tmp_path, gl_ctx):
    from viewer.bench.harness import WARMUP_FRAMES, Harness, RunSpec

    path = _room_path(tmp_path)
    h = Harness(frames=3, first_frame=1, quiet=True, ctx=gl_ctx)
    images: list[tuple[int, int]] = []
    specs = [RunSpec("glsl", "primary", "glsl"),
             RunSpec("probe a", "primary", "probe", "label=a,repeat=1"),
             RunSpec("probe b", "primary+shadows", "probe", "label=b,repeat=3",
                     sink=lambda k, n, img: images.append((k, n)))]
    glsl, a, b = h.run_many(path, (48, 27), specs)
    # each configuration warmed up on the first WARMUP_FRAMES frames (here all three) and reset once;
    # then every configuration renders frame n before any renders frame n+1
    ev = [(e, label) for e, label, _ in LOG]
    warm = [("frame", "a")] * 3 + [("reset", "a")] + [("frame", "b")] * 3 + [("reset", "b")]
    assert WARMUP_FRAMES == 3 and ev[:8] == warm  # warm-up, reset
    assert ev[8:] == [("frame", "a"), ("frame", "b")] * 3  # then interleaved, frame by frame
    assert a.frame_numbers == b.frame_numbers == glsl.frame_numbers == [1, 2, 3]
    assert images == [(0, 1), (1, 2), (2, 3)]
    for run in (a, b):
        assert [f["cold"] for f in run.frames] == [True, False, False]
        for f in run.frames:
            assert "probe:trace" in f["gpu_ms"] and not any(p.startswith("trace:") for p in f["gpu_ms"])
            assert f["trace_gpu_ms"] == pytest.approx(f["gpu_ms"]["probe:trace"])
            assert f["trace_gpu_ms"] > 0
        assert run.steady.frames == 2 and run.cold.frames == 1
    assert a.params == "label=a,repeat=1" and b.params == "label=b,repeat=3"
    assert glsl.params == "stage=auto"  # a backend's effective parameters, its defaults included
    # counters per pass summed per frame: b has two passes (primary, shadows) of 3 draws each
    assert a.steady.counters["probe_draws"] == 1.0
    assert b.steady.counters["probe_draws"] == 6.0
    assert glsl.steady.counters.get("draws") == 1.0
    # the same primary rays in glsl and in probe a
    assert a.steady.rays == glsl.steady.rays > 0
    assert b.steady.rays > a.steady.rays


def test_bad_parameters_of_an_unknown_backend_are_one_line(probe_registered):
    from viewer.backends import check_params
    from viewer.errors import RtwalkError

    assert "repeat=2" in check_params("probe", "repeat=2")
    with pytest.raises(RtwalkError, match="repeat"):
        check_params("probe", "repeat=9")


def test_report_and_plot_helpers(tmp_path):
    from PIL import Image

    from viewer.bench.plots import barh, figure, finish, points, stacked
    from viewer.bench.report import fmt, md_table, ratio, write_study

    assert fmt(float("nan")) == "-" and fmt(None) == "-" and fmt(1234.567, 2) == "1,234.57"
    assert np.isnan(ratio(1.0, 0.0)) and ratio(3.0, 1.5) == 2.0
    md = md_table(["a", "b"], [["1", "2"], ["3", "4"]])
    assert md.splitlines() == ["| a | b |", "|---|---|", "| 1 | 2 |", "| 3 | 4 |"]
    report = {"n": np.int64(3), "x": np.float32(0.5), "arr": np.arange(3), "p": tmp_path, "nan": float("nan")}
    res = write_study(tmp_path, "demo", report, md)
    back = json.loads(res["json"].read_text())
    assert back["n"] == 3 and isinstance(back["n"], int) and back["x"] == 0.5 and back["arr"] == [0, 1, 2]
    assert back["p"] == str(tmp_path) and np.isnan(back["nan"])
    assert res["md"].read_text() == md + "\n"
    fig, (ax1, ax2, ax3) = figure(1, 3, size=(9, 3))
    barh(ax1, ["x", "y"], {"s1": [1.0, 2.0], "s2": [2.0, 4.0]}, "ms", log=True, ref=1.0)
    stacked(ax2, [0, 1, 2], {"p": [1, 2, 3], "q": [1, 1, 1]})
    points(ax3, [1, 2], [3, 4], ["a", "b"], line=True)
    finish(fig, res["png"], "title")
    img = np.asarray(Image.open(res["png"]).convert("RGB"))
    assert img.shape[0] > 100 and len(np.unique(img.reshape(-1, 3), axis=0)) > 10

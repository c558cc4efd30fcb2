"""The full-BVH traversal's two stages (viewer.backends.gl_traversal.STAGES, glsl's `stage`): a
full-screen fragment draw or a compute dispatch run the same traversal, so they must give the same
hits bit for bit, finish long traversals alike under llvmpipe's loop limit, and cost the same
host syncs. The fragment stage is judged against Embree and the float64 tracer elsewhere
(test_agreement, test_exactness), so agreeing with it bit for bit is the strict bar."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from tests.test_exactness import closed_disk
from viewer.effects import parse_effects
from viewer.paths import RECORDINGS
from viewer.recording import load_recording
from viewer.renderer import Renderer

STAGES = ("fragment", "compute")


def _walk(ctx, stage: str, effects: str, size=(96, 54), frames=range(118, 121)):
    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    r = Renderer(ctx, prep.scene, prep.bvh, size, "glsl", parse_effects(effects),
                 backend_options={"glsl": f"stage={stage}"})
    try:
        reports = [r.render(rec.camera_for_frame(n), capture=True) for n in frames]
        return reports, r.read_image()
    finally:
        r.release()


@pytest.mark.parametrize("loop_limit", ["llvmpipe", "none"])
def test_compute_stage_gives_the_fragment_stages_bits(loop_limit, gl_ctx, monkeypatch):
    if loop_limit == "none":
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    else:
        monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
    monkeypatch.setenv("RTWALK_PHASE_TIMING", "timer")  # no per-phase finishes in the syncs
    effects = "primary,shadows,ao:2,reflections"
    walks = {stage: _walk(gl_ctx, stage, effects) for stage in STAGES}
    out = {stage: reports for stage, (reports, _) in walks.items()}
    n_pass = 0
    for a, b in zip(out["fragment"], out["compute"], strict=True):
        assert len(a.captured) == len(b.captured) > 0
        for pa, pb in zip(a.captured, b.captured, strict=True):
            assert np.array_equal(pa.tri, pb.tri), pa.ray_type
            assert np.array_equal(pa.t.view(np.int32), pb.t.view(np.int32)), pa.ray_type
            n_pass += int((pa.tri >= 0).any())
    assert np.array_equal(walks["fragment"][1], walks["compute"][1])
    assert n_pass >= 6  # passes that hit something were compared
    # the same host waits (the loop limit's counter reads, or none); each dispatch also draws once
    assert out["compute"][-1].io.host_syncs == out["fragment"][-1].io.host_syncs


def test_compute_stage_finishes_long_traversals(gl_ctx, monkeypatch):
    """Rays through a closed fan of 62,832 needles need more node visits than llvmpipe's loop limit
    lets one dispatch run: the compute stage resumes them in further dispatches, with the fragment
    stage's hits."""
    from viewer.backends import create_backend
    from viewer.backends.base import BackendContext
    from viewer.effects import RayType
    from viewer.gl import io as glio
    from viewer.profiler import GpuProfiler
    from viewer.rays import HitBuffer, PassInfo, RayBatch
    from viewer.tracing import _prepared

    monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
    tris = closed_disk(62_832)
    rng = np.random.default_rng(3)
    n = 64
    u = rng.normal(size=(n, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.2
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = np.zeros((n, 4), np.float32)
    o[:, :3] = 0.5 * u
    d = np.zeros((n, 4), np.float32)
    d[:, :3] = -o[:, :3]
    d[:, 3] = 3.0e38
    scene, bvh, gpu_scene, programs = _prepared(gl_ctx, tris)
    size = (8, 8)
    results = {}
    for stage in STAGES:
        rays, hits = RayBatch(gl_ctx, size), HitBuffer(gl_ctx, size)
        try:
            glio.write(rays.origin, o.tobytes())
            glio.write(rays.direction, d.tobytes())
            bc = BackendContext(gl_ctx, programs, GpuProfiler(gl_ctx, enabled=False), gpu_scene, scene, bvh)
            be = create_backend("glsl", bc, f"stage={stage}")
            be.begin_frame(0)
            stats = be.trace(rays, PassInfo(RayType.PRIMARY), hits).stats
            be.release()
            results[stage] = (*hits.read(), stats)
        finally:
            rays.release()
            hits.release()
    (tf, idf, sf), (tc, idc, sc) = results["fragment"], results["compute"]
    assert (idc >= 0).all() and np.array_equal(idf, idc) and np.array_equal(tf.view(np.int32), tc.view(np.int32))
    if "llvmpipe" in gl_ctx.info["GL_RENDERER"].lower():
        assert sc["resumed_rays"] == sf["resumed_rays"] > 0 and sc["draws"] == sf["draws"] > 1, (sf, sc)


def test_compute_stage_hits_beyond_a_storage_block_are_one_line(gl_ctx, monkeypatch):
    """The compute stage keeps 8 bytes a pixel in one storage block: a size this device cannot
    address there is one line, before anything is dispatched."""
    from viewer.errors import RtwalkError
    from viewer.gl.limits import check_storage_block

    cap = int(gl_ctx.info["GL_MAX_SHADER_STORAGE_BLOCK_SIZE"])
    check_storage_block(gl_ctx, cap, "fits")
    with pytest.raises(RtwalkError) as exc:
        check_storage_block(gl_ctx, cap + 8, "the compute traversal's hits at 99999x99999")
    assert "\n" not in str(exc.value) and "99999x99999" in str(exc.value)


def test_chcrt_whole_bvh_passes_take_either_stage(gl_ctx, monkeypatch):
    """chcrt's whole-BVH passes run the glsl traversal (full_bvh_stage): with every front forced
    wasteful (its work probe's bars at 0.001), a walk traces whole-BVH passes, with the same bits in
    both stages."""
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    out = {}
    for stage in STAGES:
        # (the fronts built by the first pass, cold_start=sync: a device cold start's young front is not
        # measured, so it would not turn wasteful within these frames)
        params = f"cold_start=sync,work_ratio_full=0.001,work_ratio_full_any=0.001,full_bvh_stage={stage}"
        r = Renderer(gl_ctx, prep.scene, prep.bvh, (96, 54), "chcrt", parse_effects("primary,ao:2"),
                     backend_options={"chcrt": params})
        try:
            out[stage] = [r.render(rec.camera_for_frame(n), capture=True) for n in range(118, 124)]
        finally:
            r.release()
    full = sum(int(rep.backend_stats.get("full_bvh_passes", 0)) for rep in out["compute"])
    assert full >= 2, [rep.backend_stats.get("full_bvh_passes") for rep in out["compute"]]
    for a, b in zip(out["fragment"], out["compute"], strict=True):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            assert np.array_equal(pa.tri, pb.tri) and np.array_equal(pa.t.view(np.int32), pb.t.view(np.int32))


def _chcrt_walk(ctx, params: str, overlays: bool, frames=range(116, 124), size=(128, 72)):
    """chcrt over city-near frames with `params`: each frame's report and, with overlays, the last
    frame's overlay images."""
    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    r = Renderer(ctx, prep.scene, prep.bvh, size, "chcrt", parse_effects("primary,shadows,ao:2,reflections"),
                 backend_options={"chcrt": params})
    try:
        r.capture_overlays = overlays
        reports = [r.render(rec.camera_for_frame(n), capture=True) for n in frames]
        return reports, (r.read_overlays() if overlays else {}), r.read_image()
    finally:
        r.release()


@pytest.mark.parametrize("case", ["llvmpipe", "none", "overlays"])
def test_chcrt_visible_records_take_either_stage(case, gl_ctx, monkeypatch):
    """visible_stage: the device fronts' visible records as a fragment per (record, pixel) or an
    invocation per pixel over its tile's records give the same hits, image and overlays, bit for
    bit, and the same ray counts; under llvmpipe's loop limit (default parameters: the work probe's
    passes too, where this walk finds most fronts wasteful) and without one (work_probe=0: every
    front that can is traced on the device)."""
    if case == "llvmpipe":
        monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
        extra = ""
    else:
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
        extra = ",work_probe=0"
    # (cold_start=sync: settled fronts with visible records from the first frame on)
    out = {stage: _chcrt_walk(gl_ctx, f"cold_start=sync,visible_stage={stage}{extra}", overlays=case == "overlays")
           for stage in STAGES}
    (frag, ov_f, img_f), (comp, ov_c, img_c) = out["fragment"], out["compute"]
    stats = [rep.backend_stats for rep in comp]
    if case == "llvmpipe":
        assert sum(s.get("work_probe_passes", 0) for s in stats) >= 1, stats
    else:  # passes on a device front that were not whole-BVH: their visible records took the stage
        on_fronts = sum(s.get("gpu_driven", 0) - s.get("full_bvh_passes", 0) for s in stats)
        assert on_fronts >= 20, stats
    for a, b in zip(frag, comp, strict=True):
        assert a.rays == b.rays
        assert len(a.captured) == len(b.captured) > 0
        for pa, pb in zip(a.captured, b.captured, strict=True):
            assert np.array_equal(pa.tri, pb.tri), (pa.ray_type, int((pa.tri != pb.tri).sum()))
            assert np.array_equal(pa.t.view(np.int32), pb.t.view(np.int32)), pa.ray_type
    assert np.array_equal(img_f, img_c)
    assert set(ov_f) == set(ov_c)
    for name in ov_f:
        assert np.array_equal(ov_f[name], ov_c[name]), name
    if case == "overlays":
        assert {"query_overdraw", "subtree_id", "batch_subtrees"} <= set(ov_c)
        assert ov_c["batch_subtrees"].any() and ov_c["query_overdraw"].any() and (ov_c["subtree_id"] >= 0).any()


def test_auto_takes_the_fragment_stage_on_a_software_rasterizer_and_the_probes_choice_elsewhere(gl_ctx, monkeypatch):
    """stage=auto (viewer.gl.stages): llvmpipe's fragment stage traces faster, so a software rasterizer
    takes it without a probe; another device takes compute only where the probe measured it
    COMPUTE_MARGIN times faster, and measures once per context. The backends report what they ran."""
    import viewer.gl.stages as stages
    from viewer.backends.chcrt.chcrt_params import ChcrtParams
    from viewer.backends.glsl.glsl import GlslParams
    from viewer.errors import RtwalkError

    assert GlslParams().stage == ChcrtParams().visible_stage == ChcrtParams().full_bvh_stage == "auto"
    with pytest.raises(RtwalkError, match="stage"):
        GlslParams(stage="vertex").validate("--backend-params")
    calls = []

    def probe(ctx):
        calls.append(ctx)
        return probes.pop(0)

    monkeypatch.setattr(stages, "measure_stages", probe)
    probes = []
    if stages.is_software_renderer(gl_ctx.info["GL_RENDERER"]):
        assert stages.resolve_stage(gl_ctx, "auto") == "fragment" and not calls  # no probe on a CPU rasterizer
    for stage in stages.STAGES:  # an explicit stage is taken as it is
        assert stages.resolve_stage(gl_ctx, stage) == stage

    class Ctx:  # a hardware device, as far as the choice can tell
        info = {"GL_RENDERER": "NVIDIA H200/PCIe/SSE2"}
        extra = None

    hw = Ctx()
    probes = [stages.StageProbe(fragment_ms=31.0, compute_ms=1.0, iterations=64)]
    assert stages.resolve_stage(hw, "auto") == "compute" and stages.resolve_stage(hw, "auto") == "compute"
    assert len(calls) == 1  # measured once per context
    other = Ctx()
    probes = [stages.StageProbe(fragment_ms=3.0, compute_ms=2.0, iterations=64)]
    assert stages.resolve_stage(other, "auto") == "fragment"  # faster, but not by the margin
    # what glsl and chcrt ran is in their statistics
    reports, _ = _walk(gl_ctx, "auto", "primary", frames=range(118, 119))
    expected = int(stages.resolve_stage(gl_ctx, "auto") == "compute")
    assert reports[-1].backend_stats["compute_stage"] == expected


def test_the_probe_measures_both_stages(gl_ctx):
    """measure_stages on this device: positive times for the same work, sized up until it takes
    PROBE_MIN_MS (or the iteration cap), and a choice; nothing left bound that a frame would read."""
    from viewer.gl.stages import PROBE_MAX_ITERATIONS, PROBE_MIN_MS, STAGES, measure_stages

    probe = measure_stages(gl_ctx)
    assert probe.fragment_ms > 0 and probe.compute_ms > 0 and probe.choice in STAGES
    assert max(probe.fragment_ms, probe.compute_ms) >= PROBE_MIN_MS or probe.iterations >= PROBE_MAX_ITERATIONS


@pytest.mark.parametrize("limit", ["none", "llvmpipe"])
def test_chcrt_compute_stage_leaves_no_pair_to_a_fragment_draw(limit, gl_ctx, monkeypatch):
    """visible_stage=compute: the invisible pairs the cull keeps and no visible record carries (tiles
    without a visible record, or with more than max_batch kept pairs: the survivors' records of the
    fragment stage) are traced by the same dispatch, after the tile's records, in the survivors'
    order: no survivors' record is drawn, and the hits are the fragment stage's bit for bit, with
    and without llvmpipe's loop limit (the records and the kept chunks share its budget). A device
    cold start's young fronts are all such pairs."""
    if limit == "none":
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    else:
        monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
    out = {stage: _chcrt_walk(gl_ctx, f"cold_start=device,work_probe=0,visible_stage={stage}", overlays=False)
           for stage in STAGES}
    frag, comp = out["fragment"][0], out["compute"][0]
    drawn_f = [rep.backend_stats["query_records_drawn"] for rep in frag]
    drawn_c = [rep.backend_stats["query_records_drawn"] for rep in comp]
    assert min(drawn_f) > 0 and drawn_c == [0] * len(comp), (drawn_f, drawn_c)
    for a, b in zip(frag, comp, strict=True):
        assert a.rays == b.rays
        for pa, pb in zip(a.captured, b.captured, strict=True):
            assert np.array_equal(pa.tri, pb.tri), (pa.ray_type, int((pa.tri != pb.tri).sum()))
            assert np.array_equal(pa.t.view(np.int32), pb.t.view(np.int32)), pa.ray_type
    assert np.array_equal(out["fragment"][2], out["compute"][2])

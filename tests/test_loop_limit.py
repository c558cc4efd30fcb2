"""The GL traversals' loop limit (viewer.backends.gl_traversal.loop_limit): only Mesa's CPU
rasterizers end shader loops silently, so only there does a pass read back whether rays were left
unfinished. Without a limit (an NVIDIA GPU; RTWALK_LOOP_LIMIT=none here, on scenes whose traversals
are short) every ray finishes in its first draw and a pass waits for nothing: the same hits, one host
wait fewer per pass for glsl and chcrt alike."""

from __future__ import annotations

import numpy as np
import pytest

from viewer.backends.gl_traversal import LOOP_LIMIT, loop_limit
from viewer.errors import RtwalkError


def test_loop_limit_choice(gl_ctx, monkeypatch):
    monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
    renderer = gl_ctx.info["GL_RENDERER"].lower()
    assert loop_limit(gl_ctx) == (LOOP_LIMIT if "llvmpipe" in renderer or "softpipe" in renderer else None)
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    assert loop_limit(gl_ctx) is None
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "70000")
    assert loop_limit(gl_ctx) == 70000
    for bad in ("abc", "-1", "100"):
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", bad)
        with pytest.raises(RtwalkError):
            loop_limit(gl_ctx)


@pytest.mark.parametrize("backend", ["glsl", "chcrt"])
def test_no_loop_limit_same_hits_no_wait_per_pass(backend, gl_ctx, monkeypatch):
    from tests.conftest import prepared_scene
    from viewer.effects import parse_effects
    from viewer.paths import RECORDINGS
    from viewer.recording import load_recording
    from viewer.renderer import Renderer

    prep = prepared_scene("city", 60_000)
    rec = load_recording(RECORDINGS / "city-near.json")
    monkeypatch.setenv("RTWALK_PHASE_TIMING", "timer")  # no per-phase finishes in the counts
    out = {}
    for limit in ("65535", "none"):
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", limit)
        r = Renderer(gl_ctx, prep.scene, prep.bvh, (128, 72), backend, parse_effects("primary,shadows,ao:2"))
        try:
            reps = [r.render(rec.camera_for_frame(10 + i), capture=True) for i in range(3)]
        finally:
            r.release()
        out[limit] = reps
    passes = 4
    for a, b in zip(out["65535"], out["none"], strict=True):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            assert np.array_equal(pa.tri, pb.tri) and np.array_equal(pa.t.view(np.int32), pb.t.view(np.int32))
    assert out["none"][-1].io.host_syncs == out["65535"][-1].io.host_syncs - passes, (
        out["65535"][-1].io, out["none"][-1].io)

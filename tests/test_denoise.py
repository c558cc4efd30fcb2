"""Denoising (viewer.denoise, viewer.passes.denoise): the filtered picture is closer to a
many-sample reference than the raw 4-sample frame, and the raw frame the tests and the bench
compare is never touched.

The reference is the same frame rendered with ao:64 (not 256: on a loaded 2-core machine 256 AO
passes at this size take minutes; `rtwalk bench-denoise` uses 256 by default). At 64 samples its
own AO noise is 1/4 of the 4-sample frame's standard deviation, well below the gaps asserted.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.cli_runner import run_cli
from viewer.denoise import library_missing

SIZE = (160, 90)
REFERENCE_SAMPLES = 64


@pytest.fixture(scope="module")
def city_near_120(gl_ctx):
    from viewer.bench.denoise import measure
    from viewer.effects import parse_effects
    from viewer.paths import resolve_recording
    from viewer.recording import load_recording
    from viewer.session import prepare_scene_for_recording

    rec = load_recording(resolve_recording("city-near"))
    prep = prepare_scene_for_recording(rec, quiet=True)
    return measure(prep, rec, 120, parse_effects("shadows,ao:4,reflections"), SIZE, gl_ctx,
                   REFERENCE_SAMPLES, repeats=1)


def test_device_filter_is_closer_to_the_reference(city_near_120):
    r = city_near_120
    assert r["raw_mae"] > 2.0  # the 4-sample grain is there to remove
    assert r["device_mae"] < 0.85 * r["raw_mae"], r
    assert r["device_draws"] <= 6


@pytest.mark.skipif(library_missing() is not None, reason=str(library_missing()))
def test_library_filter_is_closer_to_the_reference(city_near_120):
    r = city_near_120
    assert r["library_mae"] < 0.85 * r["raw_mae"], r


def test_filters_keep_geometry_and_background(city_near_120):
    """Edge-aware: background (sky) and mirror pixels are the raw ones (to rounding), and no
    filter moves the mean brightness (a blur towards grey or black would)."""
    imgs = city_near_120["images"]
    raw, ref = imgs["raw"].astype(np.float64), imgs["reference"].astype(np.float64)
    kept = city_near_120["kept"]
    assert 0.01 < kept.mean() < 0.9
    for name in ("device", "library"):
        if name in imgs:
            out = imgs[name].astype(np.float64)
            assert np.abs(out[kept] - raw[kept]).max() <= 1.0, name
            assert abs(out.mean() - ref.mean()) < 0.05 * ref.mean(), name


def test_denoising_leaves_the_raw_frame_alone(gl_ctx):
    """read_image (agreement, image tests, the bench's Embree check) is the raw frame, before and
    after both filters ran; the filtered picture differs from it."""
    from tests.conftest import prepared_scene
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer

    prep = prepared_scene("city", 30_000)
    r = Renderer(gl_ctx, prep.scene, prep.bvh, (96, 54), None, parse_effects("shadows,ao:2"))
    try:
        cam = prep.scene.default_camera
        r.render(cam)
        before = r.read_image()
        dev = r.read_denoised("device", cam)
        lib = r.read_denoised("library", cam)
        after = r.read_image()
        np.testing.assert_array_equal(before, after)
        assert (dev != before).any() and (lib != before).any()
        # in the frame (the window's moving frames): a phase of the report, a fixed number of
        # draws, the raw frame unchanged, the shown picture the filtered one
        off = r.render(cam)
        r.denoise = True
        on = r.render(cam)
        assert "denoise" in on.gpu_ms and "denoise" not in off.gpu_ms
        assert on.io.gl_draws - off.io.gl_draws == r.device_denoiser.draws <= 6
        np.testing.assert_array_equal(r.read_image(), before)
        assert r.shown_texture is not r.final_texture
        shown = np.frombuffer(r.shown_texture.read(), np.uint8).reshape(54, 96, 4)[::-1, :, :3]
        np.testing.assert_array_equal(shown, dev)
        r.view = "ao"  # a single effect shown alone is a diagnostic: never filtered
        r.render(cam)
        np.testing.assert_array_equal(r.read_denoised("library", cam), r.read_image())
        assert r.shown_texture is r.final_texture
        r.view, r.settings = "final", parse_effects("shadows")  # exact effects only: nothing to filter
        rep = r.render(cam)
        assert "denoise" not in rep.gpu_ms and r.shown_texture is r.final_texture
        np.testing.assert_array_equal(r.read_denoised("library", cam), r.read_image())
    finally:
        r.release()


def test_cli_denoise_flag(tmp_path):
    import subprocess
    import sys

    from PIL import Image

    outs = {}
    for mode in ("on", "off"):
        out = tmp_path / f"{mode}.png"
        proc = subprocess.run([sys.executable, "-m", "viewer.cli", "render", "city", "--scene-size", "20000",
                               "--effects", "ao:2", "--size", "96x54", "--denoise", mode, "-o", str(out)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        assert ("denoised" in proc.stderr) == (mode == "on"), proc.stderr
        outs[mode] = np.asarray(Image.open(out))
    assert (outs["on"] != outs["off"]).any()
    proc = run_cli("render", "--denoise", "maybe")
    assert proc.returncode == 2 and "--denoise" in proc.stderr

"""Headless screenshots of each effect: every registered backend vs the Embree backend with the same
shading.

The Embree image is produced by tracing the same rays with Embree and shading them with the same
formula (the accumulate/shade shaders), so any difference comes from the tracer. The backends come
from the registry (tests.conftest.backend_params); each renders two frames of a still camera and the
second is compared, so backends with temporal state are compared warm. The Embree image is made
once per scene and effect and shared by the backends.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import REFERENCE_BACKEND, backend_params, checked_backend, prepared_scene, shared_scene
from viewer.effects import parse_effects
from viewer.renderer import Renderer

SIZE = (240, 135)
# each effect alone, then the any-hit effects and reflections together; fewer samples than a default
# frame (every backend renders two frames): diffuse rays are the dearest for a culling backend
# (chcrt pays ~7 s per diffuse sample and frame here), so they get one sample and stay out of the mix
EFFECTS = ["shadows", "soft:2", "ao:2", "diffuse:1", "reflections", "shadows,soft:1,ao:1,reflections"]


_reference: dict = {}  # (scene, effects) -> the Embree image


def _render(ctx, prep, backend: str, effects: str, view: str = "final", frames: int = 1) -> np.ndarray:
    """The image of the last of `frames` frames of the scene's default camera."""
    r = Renderer(ctx, prep.scene, prep.bvh, SIZE, backend, parse_effects(effects))
    try:
        r.view = view
        for _ in range(frames):
            r.render(prep.scene.default_camera)
        return r.read_image()
    finally:
        r.release()


@pytest.mark.parametrize("scene", ["room", "city", "sponza"])
@pytest.mark.parametrize("effects", EFFECTS)
@pytest.mark.parametrize("backend", backend_params(reference=False))
def test_effect_image_matches_embree(gl_ctx, backend, scene, effects):
    backend = checked_backend(backend)
    if scene == "sponza":
        prep = prepared_scene(shared_scene("sponza-dabrovic/sponza.obj"))
    else:
        prep = prepared_scene(scene, 40_000 if scene == "city" else None)
    ours = _render(gl_ctx, prep, backend, effects, frames=2)
    if (scene, effects) not in _reference:
        _reference[(scene, effects)] = _render(gl_ctx, prep, REFERENCE_BACKEND, effects)
    ref = _reference[(scene, effects)]
    diff = np.abs(ours.astype(np.int32) - ref.astype(np.int32)).max(axis=-1)
    assert ours.std() > 2.0, f"{backend}: image is flat: nothing rendered"
    # identical rays and shading: only the rare tracer disagreement may change a pixel
    assert (diff > 8).mean() <= 0.002, f"{backend}: {(diff > 8).mean():.4%} of pixels differ by more than 8/255"
    assert diff.mean() <= 0.5, (backend, diff.mean())


@pytest.mark.parametrize("view", ["shadows", "ao", "reflections", "albedo", "normal", "depth", "triangle_id"])
def test_each_pass_can_be_shown_alone(gl_ctx, view):
    prep = prepared_scene("room")
    img = _render(gl_ctx, prep, "glsl", "shadows,ao:2,reflections", view=view)
    assert img.shape == (SIZE[1], SIZE[0], 3)
    assert img.std() > 1.0, f"view {view} is flat"


def test_effects_change_the_image(gl_ctx):
    """Shadows darken, AO darkens, reflections change mirror pixels: guards against no-op passes."""
    prep = prepared_scene("room")
    base = _render(gl_ctx, prep, "glsl", "none").astype(np.float64)
    shadowed = _render(gl_ctx, prep, "glsl", "shadows").astype(np.float64)
    ao = _render(gl_ctx, prep, "glsl", "ao:4").astype(np.float64)
    refl = _render(gl_ctx, prep, "glsl", "reflections").astype(np.float64)
    assert shadowed.mean() < base.mean() - 0.5
    assert ao.mean() < base.mean() - 0.5
    assert np.abs(refl - base).max(axis=-1).mean() > 0.2

"""Default lights along the shipped recordings: what each walk looks at is directly lit.

Issue 23: conference-walk's `--view shadows` was black at frames 0..360 (one light placed for the
default camera). Every 60th frame of every shipped recording must show >= 30% directly lit pixels.
Measured twice: the renderer's `--view shadows` image (viewer.bench.lit, what the user sees), and
independently with Embree (primary rays, then shadow rays to every point light), which must agree.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import shared_scene
from viewer.reference import EmbreeTracer

SIZE = (160, 90)
MIN_LIT = 0.30


def _embree_lit_share(scene, camera, emb: EmbreeTracer, size=SIZE) -> float:
    """Share of pixels whose surface faces at least one point light with an unoccluded segment.
    `emb`: the Embree scene of `scene.triangles`, built once per recording (a build per frame cost
    conference-walk 3.6 s of its 13 s)."""
    o, d = camera.primary_rays(*size)
    d = np.asarray(d, np.float64).reshape(-1, 3)
    o = np.broadcast_to(np.asarray(o, np.float64).reshape(-1, 3), d.shape)
    r = len(d)
    t, ids = emb.trace(o, d, np.zeros(r), np.full(r, np.inf))
    hit = ids >= 0
    p = o[hit] + t[hit, None].astype(np.float64) * d[hit]
    tri = scene.triangles[ids[hit]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    n[np.einsum("ij,ij->i", n, d[hit]) > 0] *= -1
    eps = 1e-4 * scene.diagonal
    lit = np.zeros(len(p), bool)
    for light in scene.point_lights:
        to_l = light.position.astype(np.float64) - p
        facing = np.einsum("ij,ij->i", to_l, n) > 0
        _, occ = emb.trace(p + eps * n, to_l, np.zeros(len(p)), np.full(len(p), 1.0 - 1e-6), any_hit=True)
        lit |= facing & (occ < 0)
    return float(lit.sum()) / r


def _check_recording(gl_ctx, name: str) -> None:
    from viewer.bench.lit import lit_fractions
    from viewer.paths import resolve_recording
    from viewer.recording import load_recording
    from viewer.session import prepare_scene_for_recording

    rec = load_recording(resolve_recording(name))
    prep = prepare_scene_for_recording(rec, quiet=True)
    assert 1 <= len(prep.scene.point_lights) <= 8
    rows = lit_fractions(prep, rec, gl_ctx, SIZE, every=60)
    assert len(rows) == (rec.frame_count() - 1) // 60 + 1
    emb = None if prep.scene.animated else EmbreeTracer(prep.scene.triangles)
    for frame, share in rows:
        assert share >= MIN_LIT, (name, frame, share)
        if prep.scene.animated:
            continue  # Embree sees the scene at time 0; the render at the frame's scene time
        ref = _embree_lit_share(prep.scene, rec.camera_for_frame(frame), emb)
        assert abs(share - ref) < 0.05, (name, frame, share, ref)


needs_embree = pytest.mark.skipif(not EmbreeTracer.available(), reason="embreex not installed")


@needs_embree
@pytest.mark.parametrize("name", ["city-near", "city-far", "room-anim-walk"])
def test_builtin_recordings_are_lit(gl_ctx, name):
    _check_recording(gl_ctx, name)


@needs_embree
@pytest.mark.scenes
@pytest.mark.parametrize("name,rel", [("conference-walk", "conference/conference.ply"),
                                      ("sibenik-walk", "sibenik/sibenik.obj"),
                                      ("sponza-walk", "sponza-dabrovic/sponza.obj")])
def test_study_scene_recordings_are_lit(gl_ctx, name, rel):
    shared_scene(rel)  # skips when ../shared/scenes (or $RTWALK_SHARED/scenes) lacks it
    _check_recording(gl_ctx, name)


def test_lights_follow_the_recording_not_only_the_first_camera():
    """place_set over a walk's cameras lights each of them; a light for the first camera alone
    does not light a camera looking elsewhere (a procedural room, no shared scenes needed)."""
    from tests.conftest import prepared_scene
    from viewer.camera import Camera
    from viewer.default_lights import PATH_GRID, lit_share, place_set, visible_samples

    prep = prepared_scene("room")
    scene = prep.scene
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    c = (lo + hi) / 2
    eye_y = lo[1] + 0.4 * (hi[1] - lo[1])
    cams = [Camera.look_at([c[0], eye_y, c[2]], [c[0] + s * (hi[0] - lo[0]), eye_y, c[2]]) for s in (1, -1)]
    placed = place_set(scene, prep.bvh, c, cams)
    assert 1 <= len(placed) <= 4
    lights = np.array([pl.position for pl in placed])
    for cam in cams:
        p, n, _ = visible_samples(scene, prep.bvh, cam, PATH_GRID)
        _, lit = lit_share(scene, prep.bvh, lights, p, n, 1e-4 * scene.diagonal)
        assert lit.any(0).mean() > 0.5

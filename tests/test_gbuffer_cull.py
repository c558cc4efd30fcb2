"""Frustum culling of the G-buffer raster by BVH subtrees (viewer.passes.cull): the cut partitions
the triangle slots, the visible ranges hold every triangle that lies in the view pyramid (checked
per triangle in float64), and the culled G-buffer is the unculled one, pixel for pixel."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import prepared_scene
from viewer.camera import Camera
from viewer.gl.textures import read_texture
from viewer.passes.cull import bvh_cut, frustum_planes, visible_ranges

SIZE = (96, 54)


@pytest.fixture(scope="module")
def city():
    return prepared_scene("city", 20000)


def _cameras(scene) -> list[Camera]:
    lo, hi = (np.asarray(v, np.float64) for v in scene.bounds)
    c, d = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    street = c + np.array([0.0, -0.45, 0.0]) * (hi - lo)  # low among the buildings
    return [scene.default_camera or Camera.look_at(c + [0, 0, d], c),
            Camera.look_at(street, street + [1.0, 0.05, 0.3]),  # a street view: most of the city is out
            Camera.look_at(street, street + [-0.2, -0.1, -1.0], fov_y=20.0),
            Camera.look_at(c + [0, d * 3, 0.01], c + [0, d * 4, 0.0])]  # looking away: nothing to draw


def test_cut_partitions_the_slots(city):
    bvh = city.bvh
    cut = bvh_cut(bvh, 256)
    n = city.scene.triangle_count
    assert cut.first[0] == 0 and int(cut.count.sum()) == n
    np.testing.assert_array_equal(cut.first[1:], (cut.first + cut.count)[:-1])  # contiguous, disjoint
    np.testing.assert_array_equal(cut.count, bvh.node_count[cut.nodes])
    assert 16 < len(cut.nodes) < 4 * 256 + 64  # a cut, not the root or the leaves


def test_visible_ranges_hold_every_triangle_in_the_pyramid(city):
    """Independent check: each triangle whose float64 vertices reach into the pyramid (clipped
    against the four planes per triangle, by its vertices' convex hull) lies in a drawn range."""
    scene, bvh = city.scene, city.bvh
    cut = bvh_cut(bvh, 512)
    tris = scene.triangles.astype(np.float64)
    n = len(tris)
    culled_any = False
    for cam in _cameras(scene):
        aspect = SIZE[0] / SIZE[1]
        ranges = visible_ranges(cut, bvh.node_min, bvh.node_max, cam, aspect)
        drawn = np.zeros(n, bool)
        for f, c in ranges.tolist():
            drawn[f:f + c] = True
        # a triangle is surely outside when all three vertices are outside one plane
        planes = frustum_planes(cam, aspect, widen=0.0)
        d = np.einsum("tvj,pj->tvp", tris - np.asarray(cam.position), planes)  # (T, 3, 4)
        maybe_inside = ~(d < 0).all(axis=1).any(axis=1)
        assert not (maybe_inside & ~drawn).any()
        culled_any |= drawn.sum() < n
    assert culled_any


def test_culled_gbuffer_equals_the_full_raster(gl_ctx, city):
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    r.gbuffer.occlusion = False  # the frustum culling alone (occlusion: the next test)
    try:
        drawn = []
        for cam in _cameras(city.scene):
            out = {}
            for cull in (False, True):
                r.gbuffer.cull = cull
                r.gbuffer.render(cam)
                out[cull] = [read_texture(t).copy() for t in (r.gbuffer.tri_id, r.gbuffer.position,
                                                               r.gbuffer.normal, r.gbuffer.albedo)]
                if cull:
                    drawn.append(r.gbuffer.drawn_triangles)
            for a, b in zip(out[False], out[True], strict=True):
                np.testing.assert_array_equal(a, b)
        n = city.scene.triangle_count
        assert drawn[-1] == 0  # looking away from the scene
        assert min(drawn[1:3]) < n // 2  # street views draw a fraction of the city
    finally:
        r.release()


def _walk(scene, n: int = 8) -> list[Camera]:
    """A street-level walk that turns: what was hidden comes into view (the occlusion state is
    carried from frame to frame), then a jump back to the first view and one looking away."""
    lo, hi = (np.asarray(v, np.float64) for v in scene.bounds)
    c = (lo + hi) / 2
    street = c + np.array([0.0, -0.45, 0.0]) * (hi - lo)
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = street + np.array([np.cos(a), 0.0, np.sin(a)]) * 0.05 * (hi - lo)
        cams.append(Camera.look_at(eye, eye + [np.cos(a + 1.3), 0.02, np.sin(a + 1.3)]))
    return [*cams, cams[0], _cameras(scene)[3]]


@pytest.mark.parametrize("preview", [False, True], ids=["exact", "preview"])
def test_occlusion_culled_gbuffer_equals_the_unculled_one(gl_ctx, city, preview):
    """Occlusion culling (two device passes over a distance pyramid, with last frame's visible set
    first) draws a fraction of the frustum-culled triangles along a walk and changes no pixel: the
    same triangle, position, normal and albedo everywhere, except where two triangles meet at the
    same distance (a tie the draw order decides). The preview raster too, with its depth test's
    resolution."""
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        ratios, totals = [], np.zeros(2)
        for cam in _walk(city.scene):
            out, drawn = {}, {}
            for occlusion in (False, True):  # the culled frame last: its state carries to the next
                g.occlusion = occlusion
                g.render(cam, preview=preview)
                out[occlusion] = [read_texture(t).copy().reshape(SIZE[1], SIZE[0], -1)
                                  for t in (g.tri_id, g.position, g.normal, g.albedo)]
                drawn[occlusion] = g.drawn_triangles
            ids_a, ids_b = out[False][0][..., 0], out[True][0][..., 0]
            same = ids_a == ids_b
            # a tie: the same distance (exact: the ray test's t; preview: within the resolution of
            # the rasterizer's float depth far from its near plane, ~1e-4 relative)
            tie = np.isclose(out[False][1][..., 3], out[True][1][..., 3], rtol=1e-3 if preview else 1e-6, atol=0)
            bad = [tuple(b) for b in np.argwhere(~(same | tie))[:5]]
            assert not bad, [(b, out[False][1][b][3], out[True][1][b][3]) for b in bad]
            assert same.mean() >= 0.995
            for a, b in zip(out[False][1:], out[True][1:], strict=True):
                np.testing.assert_array_equal(a[same], b[same])
            totals += drawn[False], drawn[True]
            if drawn[False]:
                ratios.append(drawn[True] / drawn[False])
            else:
                assert drawn[True] == 0
        # street views hide much of what is in the pyramid (city-near at 112x63: 58 % drawn)
        assert totals[1] <= 0.85 * totals[0] and min(ratios) < 0.5, ratios
    finally:
        g.occlusion = True
        r.release()


def test_first_frame_and_jumps_guess_the_occluders(gl_ctx, city, monkeypatch):
    """Without a last frame (a new culler) or after a camera jump, phase 1 draws a guess (the nodes
    nearest the camera, up to a triangle budget per pixel), so the first frame of a street view
    already culls much of the pyramid; a small move keeps last frame's set. The picture is the
    unculled one. (A budget of 0.1 triangle a pixel: this 20 k city at 96x54 holds about a triangle
    a pixel in view, so the default budget would guess everything in view.)"""
    import viewer.passes.occlusion as occlusion
    from viewer.renderer import Renderer

    monkeypatch.setattr(occlusion, "SEED_TRIANGLES_PER_PIXEL", 0.1)
    street = _cameras(city.scene)[1]
    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        g.occlusion = False
        g.render(street)
        full = [read_texture(t).copy() for t in (g.tri_id, g.position)]
        frustum_drawn = g.drawn_triangles
        g.occlusion = True
        occ = g._occluder
        assert occ._last_view is None  # never drawn with occlusion yet
        g.render(street)
        budget = 0.1 * SIZE[0] * SIZE[1]
        assert 0 < occ.seeded < occ.count
        # the guess holds the budget, overshooting by less than one node
        assert budget <= occ.seeded_triangles <= budget + int(occ._cut.count.max()), occ.seeded_triangles
        assert g.drawn_triangles < 0.6 * frustum_drawn, (g.drawn_triangles, frustum_drawn)
        ids, pos = (read_texture(t) for t in (g.tri_id, g.position))
        same = (ids == full[0])[..., 0]
        assert same.mean() >= 0.995
        np.testing.assert_array_equal(pos[same], full[1][same])
        eye, fwd = np.asarray(street.position), np.asarray(street.forward)
        g.render(Camera.look_at(eye + 1e-3 * fwd, eye + fwd))  # a small step: last frame's set
        assert occ.seeded == 0
        g.render(Camera.look_at(eye, eye - fwd))  # turned around: a jump, guessed again
        assert occ.seeded > 0
    finally:
        g.occlusion = True
        r.release()


def test_occlusion_pyramid_bounds_the_exact_distances(gl_ctx, city):
    """The exact raster writes no position before its resolve, so its occlusion pyramid takes the
    distance from the depth t / (t + scale) (hiz.comp distanceAbove): at level 0 never nearer than
    the resolved distance (position.w), and within 1e-5 of it (a bound that culls); misses far."""
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        for cam in _walk(city.scene)[:4]:
            g.render(cam)
            ids = read_texture(g.tri_id).reshape(SIZE[1], SIZE[0])
            t = read_texture(g.position).reshape(SIZE[1], SIZE[0], 4)[..., 3].astype(np.float64)
            bound = read_texture(g._occluder._hiz).reshape(SIZE[1], SIZE[0]).astype(np.float64)
            hit = ids >= 0
            assert hit.mean() > 0.3
            assert (bound[hit] >= t[hit]).all()
            assert (bound[hit] <= t[hit] * (1 + 1e-5) + 1e-30).all()
            assert (bound[~hit] >= 1e38).all()
    finally:
        r.release()


def _render_targets(r, cam, source: str, textures) -> tuple[list[np.ndarray], object]:
    """The G-buffer `textures` (H, W, C) after rendering `cam` from G-buffer `source`, and the report."""
    r.gbuffer_source = source
    report = r.render(cam)
    return [read_texture(t).copy().reshape(SIZE[1], SIZE[0], -1) for t in textures], report


def test_traced_gbuffer_equals_the_raster(gl_ctx, city):
    """gbuffer_source "trace" (the backend's primary rays, then the raster's outputs per hit
    triangle) gives the raster's G-buffer: the same triangle per pixel (ties on shared edges
    aside) and, where the triangle is the same, the same position, normal, albedo and depth."""
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        for cam in _cameras(city.scene)[:3]:
            out = {source: _render_targets(r, cam, source, (g.tri_id, g.position, g.normal, g.albedo, g.depth))[0]
                   for source in ("raster", "trace")}
            ids_r, ids_t = out["raster"][0], out["trace"][0]
            same = ids_r == ids_t
            assert same.mean() >= 0.995, same.mean()
            assert ((ids_r >= 0) == (ids_t >= 0)).mean() >= 0.999
            for a, b in zip(out["raster"][1:], out["trace"][1:], strict=True):
                np.testing.assert_array_equal(a[same[..., 0]], b[same[..., 0]])
    finally:
        r.release()


def test_preview_raster_is_the_exact_one_away_from_edges(gl_ctx, city):
    """gbuffer_source "preview" (moving frames: the plain raster, no geometry shader) sees the same
    triangle as the exact conservative raster on nearly every pixel, and where the triangle is
    the same, the same position (to rounding: the preview takes the distance to the triangle's
    plane, the exact raster the ray test's), normal and albedo; only edge pixels may differ."""
    from viewer.renderer import Renderer

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        for cam in _cameras(city.scene)[:3]:
            out, reports = {}, {}
            targets = (g.tri_id, g.position, g.normal, g.albedo)
            for source in ("raster", "preview"):
                out[source], reports[source] = _render_targets(r, cam, source, targets)
            assert "gbuffer:preview" in reports["preview"].gpu_ms  # the preview pass ran
            ids_r, ids_p = out["raster"][0], out["preview"][0]
            same = (ids_r == ids_p)[..., 0]
            assert same.mean() >= 0.98, same.mean()
            assert ((ids_r >= 0) == (ids_p >= 0)).mean() >= 0.99
            hit = same & (ids_r[..., 0] >= 0)
            for a, b in zip(out["raster"][1:], out["preview"][1:], strict=True):
                np.testing.assert_allclose(a[hit], b[hit], rtol=1e-5, atol=1e-5 * city.scene.diagonal)
    finally:
        r.gbuffer_source = "raster"
        r.release()


def test_bench_gbuffer_reports_culling_and_refuses_to_overwrite(tmp_path):
    """`rtwalk bench-gbuffer`: the four configurations with ms and triangles per frame, occlusion
    drawing no more than the frustum culling and changing (almost) no pixel; a second run into the
    same folder is refused in one line."""
    import json
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "viewer.cli", "bench-gbuffer", "--frames", "3", "--first-frame", "100",
           "--size", "64x36", "--out", str(tmp_path), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((tmp_path / "gbuffer.json").read_text())
    assert (tmp_path / "gbuffer.png").exists() and (tmp_path / "gbuffer.md").exists()
    cfg = rep["configs"]
    assert set(cfg) == {"exact+frustum", "exact+occlusion", "preview+frustum", "preview+occlusion"}
    for kind in ("exact", "preview"):
        occ, fr = cfg[f"{kind}+occlusion"], cfg[f"{kind}+frustum"]
        assert len(occ["ms"]) == 3 and all(t > 0 for t in occ["ms"])
        assert all(0 < a <= b for a, b in zip(occ["triangles"], fr["triangles"], strict=True))
        assert occ["max_differing_pixels"] <= 0.01
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 2 and again.stderr.count("\n") == 1 and "--force" in again.stderr


class _Recorder:
    """Forwards to a GL object, recording the calls named in `watch` into `events`."""

    def __init__(self, obj, events: list, watch: tuple[str, ...]):
        self._obj, self._events, self._watch = obj, events, watch

    def __getattr__(self, name):
        attr = getattr(self._obj, name)
        if name not in self._watch:
            return attr

        def call(*args, **kw):
            self._events.append((name, args))
            return attr(*args, **kw)
        return call


def test_occlusion_host_updates_wait_for_the_selection_writes(gl_ctx, city, monkeypatch):
    """The selection shader writes `visible` and `stats`; a draw's seed upload and stats clear after
    it (glBufferSubData / glClearBufferData) come after a BUFFER_UPDATE barrier (glMemoryBarrier),
    whatever else the frame reads: a GPU may still hold last draw's writes (llvmpipe runs in order)."""
    import moderngl

    import viewer.passes.occlusion as occlusion
    from viewer.renderer import Renderer

    street = _cameras(city.scene)[1]
    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl")
    g = r.gbuffer
    try:
        g.occlusion = True
        g.render(street)
        occ = g._occluder
        events: list = []
        occ.ctx = _Recorder(occ.ctx, events, ("memory_barrier",))
        occ.stats = _Recorder(occ.stats, events, ("clear",))
        write = occlusion.glio.write
        monkeypatch.setattr(occlusion.glio, "write", lambda obj, *a, **kw: (events.append(("write", obj)),
                                                                              write(obj, *a, **kw)))
        eye, fwd = np.asarray(street.position), np.asarray(street.forward)
        g.render(Camera.look_at(eye, eye - fwd))  # a jump: the seed uploads `visible`
        assert occ.seeded > 0
        names = [e[0] for e in events]
        first_update = min(names.index("clear"), names.index("write"))
        assert any(n == "memory_barrier" and e[1][0] & moderngl.BUFFER_UPDATE_BARRIER_BIT
                   for n, e in zip(names[:first_update], events[:first_update], strict=True)), events[:first_update]
    finally:
        r.release()

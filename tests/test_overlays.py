"""Backend overlays in the renderer: the copy of the chosen pass equals what the backend produced
for that pass (and not another pass), subtree ids hold the pass's hit triangles, the heat map is
the documented colormap of the overdraw (so monotone), the subtree view and its tile counts, and
an overlay view without overlays fails with one clear error (window: a panel line)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.cli_runner import run_cli
from tests.conftest import prepared_scene
from tests.view_helpers import draw_views, image_gl, record_overlays, tile_edges
from viewer.effects import RayType, parse_effects
from viewer.errors import RtwalkError
from viewer.passes.overlay import (
    NO_DATA_GREY,
    heat_colors,
    heat_lut,
    heat_position,
    heat_ticks,
    nice_ceil,
)
from viewer.renderer import Renderer
from viewer.screen_tiles import tile_index

SIZE = (160, 90)
EFFECTS = "primary,shadows,ao:2"


@pytest.fixture(scope="module")
def city():
    return prepared_scene("city", 20_000)


@pytest.fixture(scope="module")
def chc(gl_ctx, city):
    """A chcrt renderer that has rendered two frames (temporal state in place)."""
    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "chcrt", parse_effects(EFFECTS))
    cam = city.scene.default_camera
    r.render(cam)
    r.render(cam)
    yield r, cam
    r.release()


def test_copy_equals_the_backend_overlays_of_the_chosen_pass(chc):
    r, cam = chc
    seen = record_overlays(r)
    try:
        r.view = "query_overdraw"
        r.overlay_pass = (RayType.AO, 0)
        r.render(cam)
        shown_only = set(r.read_overlays())  # the window copies the view it shows
        seen.clear()  # the backend's textures of the next frame only
        r.capture_overlays = True  # tools copy every view
        rep = r.render(cam, capture=True)
        ov = r.read_overlays()
    finally:
        del r.backend.trace
        r.overlay_pass = None
        r.view = "final"
        r.capture_overlays = False
    assert shown_only == {"query_overdraw", "ray", "hit"}
    assert rep.overlay_source == (RayType.AO, 0) and r.overlay_source == (RayType.AO, 0)
    want = seen[(RayType.AO, 0)]
    assert set(want) >= {"query_overdraw", "subtree_id"}
    specs = r.backend.info.overlays
    names = {s.texture for s in specs} | {s.counts for s in specs if s.counts}
    for name in names & set(want):
        if name in ov:
            np.testing.assert_array_equal(ov[name], want[name], err_msg=name)
        else:  # a counts texture is left out of the copy only when the backend reported none
            assert (want[name] < 0).all(), name
    assert ov["query_overdraw"].sum() > 0
    # the copy is of that pass, not of the last one or the first one
    others = [k for k in seen if k != (RayType.AO, 0)]
    assert any(not np.array_equal(seen[k]["query_overdraw"], want["query_overdraw"]) for k in others)
    assert not np.array_equal(seen[(RayType.PRIMARY, 0)]["subtree_id"], want["subtree_id"])
    # ray / hit flags are those of the same pass
    cp = next(c for c in rep.captured if (c.ray_type, c.sample) == (RayType.AO, 0))
    np.testing.assert_array_equal(ov["ray"], cp.rays.active)
    np.testing.assert_array_equal(ov["hit"], cp.tri >= 0)


@pytest.mark.parametrize("source", [None, (RayType.SHADOW, 0), (RayType.AO, 0)],
                         ids=["default-primary", "shadows", "ao"])
def test_subtree_ids_hold_the_pixels_hit_triangle(chc, city, source):
    r, cam = chc
    bvh = city.bvh
    r.view, r.overlay_pass = "subtree_batches", source
    try:
        rep = r.render(cam, capture=True)
        ov = r.read_overlays()
    finally:
        r.view, r.overlay_pass = "final", None
    src = source or (RayType.PRIMARY, 0)
    assert rep.overlay_source == src
    cp = next(c for c in rep.captured if (c.ray_type, c.sample) == src)
    sub, tri = ov["subtree_id"], cp.tri
    hit = tri >= 0
    assert hit.sum() > 100 and (~hit).sum() > 0
    assert (sub[~hit] == -1).all()
    s = sub[hit]
    assert ((s >= 0) & (s < len(bvh.node_first))).all()
    first, count = bvh.node_first[s], bvh.node_count[s]
    assert ((tri[hit] >= first) & (tri[hit] < first + count)).all()  # the hit lies in that subtree
    assert len(np.unique(s)) > 3  # several subtrees: the view has something to tell apart


def test_heat_map_is_the_colormap_of_the_overdraw(chc):
    r, cam = chc
    r.render(cam)
    final = image_gl(r)
    r.view = "query_overdraw"
    try:
        r.render(cam)
        img = image_gl(r)
        ov = r.read_overlays()
        vmax = r.overlay_scale_max()
        frame_max = r.overlay.read_max("query_overdraw")[0]
    finally:
        r.view = "final"
    od, ray = ov["query_overdraw"], ov["ray"]
    assert frame_max == od.max() and vmax == nice_ceil(frame_max) and vmax >= od.max()
    assert np.abs(img - final).mean() > 20  # not the final image
    assert len(np.unique(od)) >= 3
    nodata = (od == 0) & ~ray
    assert (img[nodata] == NO_DATA_GREY).all()
    data = ~nodata
    want = heat_colors(od[data], vmax, log=True).astype(np.int32)
    # the shader's float rounding may pick the neighbouring colormap entry at an exact .5
    lut = heat_lut().astype(np.int32)
    step = np.abs(np.diff(lut, axis=0)).max()
    assert (np.abs(img[data] - want).max(axis=1) <= step).all()
    assert (np.abs(img[data] - want).max(axis=1) == 0).mean() > 0.99
    # monotone: more query fragments never map to a lower colormap entry (so never darker: inferno's
    # lightness increases, up to 8-bit rounding); the entry is read back from the image itself
    cols, inv = np.unique(img[data], axis=0, return_inverse=True)
    entry = np.argmin(((cols[:, None, :] - lut[None]) ** 2).sum(axis=2), axis=1)[inv.reshape(-1)]
    vals = np.unique(od[data])
    lo = np.array([entry[od[data] == v].min() for v in vals])
    hi = np.array([entry[od[data] == v].max() for v in vals])
    assert (lo[1:] >= hi[:-1]).all(), list(zip(vals, lo, hi, strict=True))
    assert hi[-1] - lo[0] > 60
    lum = img[data] @ np.array([0.2126, 0.7152, 0.0722])
    assert lum[od[data] == vals[-1]].min() > lum[od[data] == vals[0]].max() + 30


def test_fixed_and_linear_scale(chc):
    r, cam = chc
    r.view, r.overlay_scale, r.overlay_log = "query_overdraw", 4, False
    try:
        r.render(cam)
        img = image_gl(r)
        od = r.read_overlays()["query_overdraw"]
        assert r.overlay_scale_max() == 4
    finally:
        r.view, r.overlay_scale, r.overlay_log = "final", 0, True
    top = od >= 4
    assert top.any()
    assert (img[top] == heat_lut()[255]).all()  # saturated at the user's maximum
    two = od == 2
    if two.any():
        np.testing.assert_array_equal(img[two], np.repeat(heat_lut()[128][None], two.sum(), axis=0))


def test_subtree_batches_view_and_tile_counts(chc):
    r, cam = chc
    r.view = "subtree_batches"
    try:
        r.render(cam)
        img = image_gl(r).reshape(SIZE[1], SIZE[0], 3)
        ov = r.read_overlays()
        level = r.overlay_tile_level()
        tiles = r.overlay_tiles()
    finally:
        r.view = "final"
    assert level >= 1
    n = 1 << level
    edge = tile_edges(SIZE, level)
    sub = ov["subtree_id"].reshape(SIZE[1], SIZE[0])
    grey = (img == NO_DATA_GREY).all(axis=2)
    assert grey[(sub < 0) & ~edge].all()  # no hit: dark grey
    assert not grey[(sub >= 0) & ~edge].any()  # hit: an id colour (bright: 0.3 + 0.7 * hash)
    assert not grey[edge].any()  # tile outlines drawn
    # same subtree -> same colour
    inside = (sub >= 0) & ~edge
    s_ids, first = np.unique(sub[inside], return_index=True)
    cols = img[inside][first]
    again = img[inside]
    np.testing.assert_array_equal(again, cols[np.searchsorted(s_ids, sub[inside])])
    rects, counts, from_counts = tiles
    assert rects.shape == (n * n, 4) and counts.shape == (n * n,)
    assert rects[:, 2].sum() == SIZE[0] * n and rects[:, 3].sum() == SIZE[1] * n
    # every subtree that produced a hit in a tile was in that tile's batches
    flat_t, flat_s = tile_index(SIZE, level).reshape(-1), ov["subtree_id"]
    keep = flat_s >= 0
    distinct = np.bincount(np.unique(flat_t[keep] * (flat_s.max() + 1) + flat_s[keep]) // (flat_s.max() + 1),
                           minlength=n * n)
    assert (counts >= distinct).all() and counts.sum() > 0
    if "batch_subtrees" in ov:
        assert from_counts
        b = ov["batch_subtrees"]
        lo = np.full(n * n, np.iinfo(np.int64).max)
        np.minimum.at(lo, flat_t, b.astype(np.int64))
        assert (lo == counts).all()  # one value per finest tile
        assert (b[ov["hit"]] >= 1).all()
    else:
        assert not from_counts
        assert (counts == distinct).all()


def test_no_copy_without_an_overlay_view(gl_ctx, city):
    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "chcrt", parse_effects("shadows"))
    try:
        rep = r.render(city.scene.default_camera)
        assert r._overlay is None and rep.overlay_source is None and "overlay" not in rep.gpu_ms
        assert r.read_overlays() == {} and r.backend_overlays
        r.capture_overlays = True  # tools that save overlays (bench) without showing them
        rep = r.render(city.scene.default_camera)
        assert rep.overlay_source == (RayType.SHADOW, 0) and "overlay" in rep.gpu_ms
        assert r.read_overlays()["subtree_id"].shape == (SIZE[0] * SIZE[1],)
    finally:
        r.release()


def test_overlay_view_without_overlays_is_an_error(gl_ctx, city):
    from viewer.ui.panel import overlay_missing_line

    r = Renderer(gl_ctx, city.scene, city.bvh, SIZE, "glsl", parse_effects("shadows"))
    cam = city.scene.default_camera
    try:
        r.render(cam)
        final = r.read_image()
        for view in ("query_overdraw", "subtree_batches"):
            r.view = view
            with pytest.raises(RtwalkError, match="overlay.*glsl.*backends that do: chcrt"):
                r.render(cam)
            r.strict_overlays = False  # the window: the final image, and the reason in the panel
            r.render(cam)
            assert "glsl" in r.overlay_missing and r.overlay_source is None
            # the panel's line names no backend
            assert overlay_missing_line(r) == f"view '{view}': not produced by this backend; final image shown"
            np.testing.assert_array_equal(r.read_image(), final)
            r.strict_overlays = True
        r.set_backend("chcrt")
        r.settings = parse_effects("none")
        with pytest.raises(RtwalkError, match="no pass traces rays"):
            r.render(cam)
        r.strict_overlays = False
        r.render(cam)
        assert overlay_missing_line(r) == "no traced pass: turn an effect on"
    finally:
        r.release()


def test_render_cli_overlay_view_with_glsl_fails_with_one_line(tmp_path):
    res = run_cli("render", "room", "--backend", "glsl", "--view", "query_overdraw", "--size", "64x36",
                  "-o", str(tmp_path / "o.png"), "--quiet")
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rtwalk: error: ") and "chcrt" in lines[0], res.stderr
    assert not (tmp_path / "o.png").exists()


def test_scale_helpers():
    assert [nice_ceil(n) for n in (0, 1, 2, 3, 5, 6, 11, 20, 21, 99, 101)] == [1, 1, 2, 5, 5, 10, 20, 20, 50, 100,
                                                                               200]
    v = np.arange(0, 51)
    p = heat_position(v, 50)
    assert p[0] == 0 and p[-1] == 1 and (np.diff(p) > 0).all()
    assert heat_position(100, 50) == 1.0  # saturates
    lum = heat_lut() @ np.array([0.2126, 0.7152, 0.0722])
    assert (np.diff(lum) >= -0.25).all() and lum[-1] - lum[0] > 200  # inferno: lightness increases (8-bit)
    assert heat_ticks(50) == [0, 1, 2, 5, 10, 20, 50]
    assert heat_ticks(7)[0] == 0 and heat_ticks(7)[-1] == 7
    t = heat_ticks(200, log=False)
    assert t[0] == 0 and t[-1] == 200 and len(t) <= 8


def test_panel_and_annotations_draw_headless(chc, gl_ctx, city):
    """The panel's chart, counters and overlay controls and the legend / tile labels run in a real
    imgui + implot frame (no window: the draw data is built, not rasterised)."""
    r, cam = chc
    hist, vtx, _ = draw_views(r, cam, ("query_overdraw", "subtree_batches", "final"))
    assert min(vtx.values()) > 1000
    names, table = hist.phase_table()
    assert names == ["chc:0-setup", "chc:1-intersect-visible", "chc:2-queries", "chc:3-traversal",
                     "chc:4-final-intersect"]
    assert table.shape == (5, 3) and (table >= 0).all()


@pytest.mark.parametrize("view, traced", [("depth", "none"), ("triangle_id", "none"), ("shadows", "shadows"),
                                          ("final", "shadows, soft, ao, diffuse, reflections")])
def test_render_traces_only_what_the_view_shows(tmp_path, view, traced):
    """`render --view depth` traced the shadow and reflection rays of the effects for a picture that
    shows none of them: a G-buffer view traces nothing, a pass view that pass alone, 'final' all.
    The picture is the one the view shows with only those effects on (byte for byte)."""
    import re

    from PIL import Image

    def render(effects: str, name: str) -> tuple[str, np.ndarray]:
        out = tmp_path / name
        res = run_cli("render", "room", "--size", "64x36", "--effects", effects, "--view", view, "--denoise", "off",
                      "-o", str(out))
        assert res.returncode == 0, res.stderr
        rays = re.search(r"rays: ([^;)]*)", res.stderr)
        return rays.group(1), np.asarray(Image.open(out))

    rays, img = render("all", "all.png")
    keys = [part.split(" ")[0] for part in rays.split(", ")] if rays != "none" else ["none"]
    assert ", ".join(keys) == traced, rays
    if view != "final":
        _, alone = render("none" if traced == "none" else traced, "alone.png")
        assert np.array_equal(img, alone)

"""The backend contract seen from the outside: a backend that only the tests register
(tests/fake_backend.py) is driven by the renderer, the overlay views, the panel helpers and the
bench harness through its `info` alone; and no generic module names a registered backend.

References are independent of the code under test: hits against Embree on the same rays, the
overlay copies against the backend's own textures read back right after the pass, ray counts
against the ray-generation counters, per-tile numbers against NumPy on the id image.
"""

from __future__ import annotations

import ast
import io
import keyword
import re
import tokenize
from pathlib import Path

import numpy as np
import pytest

from tests.fake_backend import FakeBackend, FakeParams
from tests.view_helpers import draw_views, image_gl, record_overlays, tile_edges
from viewer.accel.bvh import build_bvh
from viewer.backends import BACKENDS, backend_info, backend_names, check_params, registered_infos
from viewer.camera import Camera
from viewer.effects import RayType, parse_effects
from viewer.errors import RtwalkError
from viewer.passes.overlay import (
    NO_DATA_GREY,
    backends_with_view,
    check_view,
    cycled_views,
    heat_colors,
    heat_lut,
    ids_labels,
    nice_ceil,
    view_names,
)
from viewer.procedural import boxes_to_triangles
from viewer.renderer import Renderer
from viewer.scene import Material, PointLight, RectLight, Scene
from viewer.screen_tiles import tile_index
from viewer.session import PreparedScene

REPO = Path(__file__).resolve().parents[1]
SIZE = (64, 40)
EFFECTS = "primary,shadows,ao:1"


@pytest.fixture(scope="module", autouse=True)
def fake_registered():
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(BACKENDS, "fake", "tests.fake_backend:FakeBackend")
        mp.delenv(FakeBackend.info.env_var, raising=False)
        yield


def tiny_scene() -> PreparedScene:
    """A floor, a back wall and three boxes (40 triangles), a point and an area light."""
    floor = np.array([[[-4, 0, -4], [-4, 0, 4], [4, 0, 4]], [[-4, 0, -4], [4, 0, 4], [4, 0, -4]]], np.float32)
    wall = np.array([[[-4, 0, -4], [4, 0, -4], [4, 3, -4]], [[-4, 0, -4], [4, 3, -4], [-4, 3, -4]]], np.float32)
    lo = np.array([[-2.5, 0, -2], [0.2, 0, -1], [-0.5, 0, 1.2]], np.float32)
    hi = np.array([[-1.0, 1.8, -0.5], [1.8, 1.0, 0.6], [0.3, 0.6, 2.0]], np.float32)
    tris = np.concatenate([floor, wall, boxes_to_triangles(lo, hi)])
    mats = [Material("grey", np.array([0.7, 0.7, 0.7], np.float32)),
            Material("blue", np.array([0.2, 0.3, 0.7], np.float32))]
    mids = np.r_[np.zeros(4, np.int32), np.ones(len(tris) - 4, np.int32)]
    scene = Scene("tiny", tris, mids, mats,
                  point_lights=[PointLight(np.array([1.5, 2.8, 2.0], np.float32), np.full(3, 6.0, np.float32))],
                  rect_lights=[RectLight(np.array([-0.5, 2.9, -0.5], np.float32), np.array([1, 0, 0], np.float32),
                                         np.array([0, 0, 1], np.float32), np.full(3, 3.0, np.float32))],
                  default_camera=Camera.look_at((0.5, 2.2, 5.5), (0.0, 0.6, -1.0), fov_y=60.0),
                  identity={"builtin": "tiny"})
    bvh = build_bvh(scene.triangles)
    return PreparedScene(scene.reordered(bvh.tri_order), bvh)


@pytest.fixture(scope="module")
def tiny():
    return tiny_scene()


@pytest.fixture(scope="module")
def fake(gl_ctx, tiny):
    """A renderer on the fake backend that has rendered one frame."""
    r = Renderer(gl_ctx, tiny.scene, tiny.bvh, SIZE, "fake", parse_effects(EFFECTS), {"fake": "tile_level=2"})
    cam = tiny.scene.default_camera
    r.render(cam)
    yield r, cam
    r.release()


# --------------------------------------------------------------------------- registry and views


def test_registry_and_views_come_from_info():
    assert "fake" in backend_names() and backend_info("fake") is FakeBackend.info
    assert check_params("fake", "tile_level=1") == "tile_level=1,max_triangles=4096"
    with pytest.raises(RtwalkError, match="tile_level must be in 0..8"):
        check_params("fake", "tile_level=9")
    with pytest.raises(RtwalkError, match="expected key=value"):
        check_params("fake", "t_q=0.4")
    info = FakeBackend.info
    assert view_names(info)[0] == "final" and view_names(info)[-2:] == ["fake_crossings", "fake_tris"]
    assert cycled_views(info) == ["final", "fake_crossings", "fake_tris"]
    infos = registered_infos()
    assert backends_with_view("fake_tris", infos) == ["fake"]
    check_view("fake_tris", info, infos)
    check_view("normal", info, infos)
    for other in backend_names():
        if other != "fake":
            with pytest.raises(RtwalkError, match=rf"view 'fake_tris' .* backend '{other}' .*backends that do: fake"):
                check_view("fake_tris", backend_info(other), infos)
    with pytest.raises(RtwalkError, match="unknown view 'xray'"):
        check_view("xray", info, infos)
    spec = info.overlays[1]
    assert ids_labels(spec) == ("hit triangle", "distinct triangles hit in the tile")


# --------------------------------------------------------------------------- renderer


def test_renderer_traces_with_the_fake_backend(fake, tiny):
    """Hits agree with Embree on the same rays; counters are summed over the frame's passes and
    match the ray-generation counts; phases are timed under the backend's declared names."""
    from viewer.reference import EmbreeTracer, compare_hits

    if not EmbreeTracer.available():
        pytest.skip("embreex is not installed")
    r, cam = fake
    rep = r.render(cam, capture=True)
    assert [(c.ray_type, c.sample) for c in rep.captured] == [(RayType.PRIMARY, 0), (RayType.SHADOW, 0),
                                                             (RayType.AO, 0)]
    tracer = EmbreeTracer(tiny.scene.triangles)
    total_hits = 0
    for cp in rep.captured:
        act = cp.rays.active
        assert act.sum() > 50
        ray = cp.rays
        t_ref, id_ref = tracer.trace(ray.origins[act], ray.directions[act], ray.tmin[act], ray.tmax[act],
                                     any_hit=cp.ray_type.any_hit)
        st = compare_hits(cp.t[act], cp.tri[act], t_ref, id_ref, tiny.scene.triangles)
        assert st["hitmiss_agree"] >= 0.995, (cp.ray_type, st)
        if not cp.ray_type.any_hit:
            assert st["id_agree"] >= 0.995 and st["max_rel_err"] < 1e-4, st
        assert (cp.tri[~act] == -1).all() and np.isinf(cp.t[~act]).all()
        total_hits += int((cp.tri >= 0).sum())
    stats = rep.backend_stats
    assert stats["rays"] == sum(rep.rays.values()) > 0  # the raygen pass counted them independently
    assert stats["pair_tests"] == stats["rays"] * tiny.scene.triangle_count
    assert stats["hits"] == total_hits
    assert set(FakeBackend.info.phases) <= set(rep.gpu_ms)
    assert rep.trace_ms > 0 and set(rep.trace_ms_by_ray) == set(rep.rays)


def test_samples_that_share_origins_share_them(gl_ctx, tiny):
    """RayType.samples_share_origins is a promise backends build on (chcrt's AO samples share one
    cull): the sample passes of AO and diffuse give every pixel the same origin, tmin, tmax and
    activity, bit for bit, and other directions; soft shadows' samples (other tmax) do not."""
    r = Renderer(gl_ctx, tiny.scene, tiny.bvh, SIZE, "fake", parse_effects("soft:2,ao:3,diffuse:2"),
                 {"fake": "tile_level=2"})
    try:
        rep = r.render(tiny.scene.default_camera, capture=True)
    finally:
        r.release()
    by_type: dict[RayType, list] = {}
    for cp in rep.captured:
        by_type.setdefault(cp.ray_type, []).append(cp.rays)
    assert set(by_type) == {RayType.SOFT, RayType.AO, RayType.DIFFUSE}
    for ray_type, batches in by_type.items():
        first = batches[0]
        assert first.active.sum() > 100, ray_type
        same = all(np.array_equal(b.origins.view(np.int32), first.origins.view(np.int32))
                   and np.array_equal(b.tmin.view(np.int32), first.tmin.view(np.int32))
                   and np.array_equal(b.tmax.view(np.int32), first.tmax.view(np.int32)) for b in batches[1:])
        assert same == ray_type.samples_share_origins, ray_type
        for b in batches[1:] if same else []:
            moved = (b.directions != first.directions).any(axis=1)[first.active]
            assert moved.mean() > 0.9, ray_type


@pytest.mark.parametrize("slots", [None, 12])
def test_passes_carry_their_ray_count_on_the_device(slots, gl_ctx, tiny, monkeypatch):
    """PassInfo.ray_count, which a backend may copy instead of counting its rays again (chcrt's
    whole-BVH passes do): for every pass of a frame it holds that pass's active rays when the
    backend traces them, and the frame's counts per ray type are their sums; with fewer slots than
    passes (`slots`: 12, of which 8 are shared per ray type) the later passes have none, and the
    counts per type still add up, over two frames."""
    from viewer.gl import io as glio
    from viewer.passes.raygen import RayGenPass

    if slots is not None:
        monkeypatch.setattr(RayGenPass, "MAX_PASS_SLOTS", slots)
    r = Renderer(gl_ctx, tiny.scene, tiny.bvh, SIZE, "fake", parse_effects("primary,soft:2,ao:3,diffuse:2"))
    seen: list[int | None] = []
    trace = r.backend.trace

    def counting_trace(rays, pinfo, hits):
        c = pinfo.ray_count
        seen.append(None if c is None else int(np.frombuffer(glio.read(c.buffer, size=4, offset=c.offset),
                                                             np.uint32)[0]))
        return trace(rays, pinfo, hits)

    r.backend.trace = counting_trace
    try:
        for _ in range(2):
            seen.clear()
            rep = r.render(tiny.scene.default_camera, capture=True)
            active = [int(cp.rays.active.sum()) for cp in rep.captured]
            own = len(active) if slots is None else slots - RayGenPass.RAY_TYPES
            assert seen == active[:own] + [None] * (len(active) - own), (seen, active)
            assert min(active) > 0 and len(set(active)) > 1, active
            totals: dict[str, int] = {}
            for cp, n in zip(rep.captured, active, strict=True):
                totals[cp.ray_type.label] = totals.get(cp.ray_type.label, 0) + n
            assert rep.rays == totals
    finally:
        r.release()


def test_overlay_views_show_what_the_backend_wrote(fake):
    r, cam = fake
    seen = record_overlays(r)
    try:
        r.view, r.overlay_pass = "fake_crossings", (RayType.SHADOW, 0)
        rep = r.render(cam, capture=True)
        heat_img = image_gl(r)
        ov = r.read_overlays()
        vmax = r.overlay_scale_max()
        want = seen.pop((RayType.SHADOW, 0))
        primary = seen.pop((RayType.PRIMARY, 0))
        r.view = "fake_tris"
        rep2 = r.render(cam, capture=True)
        ids_img = image_gl(r).reshape(SIZE[1], SIZE[0], 3)
        ov2 = r.read_overlays()
        tiles = r.overlay_tiles()
        level = r.overlay_tile_level()
    finally:
        del r.backend.trace
        r.view, r.overlay_pass = "final", None
    assert rep.overlay_source == rep2.overlay_source == (RayType.SHADOW, 0)
    want2 = seen[(RayType.SHADOW, 0)]
    assert set(want) == set(want2) == {"crossings", "hit_tri", "tile_tris"}
    # the renderer's copy is exactly what the backend wrote for that pass, for the view shown
    assert set(ov) == {"crossings", "ray", "hit"} and set(ov2) == {"hit_tri", "tile_tris", "ray", "hit"}
    np.testing.assert_array_equal(ov["crossings"], want["crossings"])
    for name in ("hit_tri", "tile_tris"):
        np.testing.assert_array_equal(ov2[name], want2[name], err_msg=name)
    assert not np.array_equal(primary["hit_tri"], want["hit_tri"])  # not another pass
    cp = next(c for c in rep.captured if (c.ray_type, c.sample) == (RayType.SHADOW, 0))
    cp2 = next(c for c in rep2.captured if (c.ray_type, c.sample) == (RayType.SHADOW, 0))
    np.testing.assert_array_equal(ov2["hit_tri"], cp2.tri)  # the id overlay is the pass's hit buffer
    np.testing.assert_array_equal(ov["ray"], cp.rays.active)
    np.testing.assert_array_equal(ov["hit"], cp.tri >= 0)
    cross = ov["crossings"]
    assert (cross[cp.tri >= 0] >= 1).all() and (cross[~cp.rays.active] == 0).all() and cross.max() >= 2

    # heat view: the colormap of the backend's values, on the scale of the frame's maximum
    assert vmax == nice_ceil(cross.max())
    nodata = (cross == 0) & ~ov["ray"]
    assert (heat_img[nodata] == NO_DATA_GREY).all()
    want_rgb = heat_colors(cross[~nodata], vmax).astype(np.int32)
    step = np.abs(np.diff(heat_lut().astype(np.int32), axis=0)).max()
    diff = np.abs(heat_img[~nodata] - want_rgb).max(axis=1)
    assert (diff <= step).all() and (diff == 0).mean() > 0.99

    # id view: one colour per id, grey without a hit, tile outlines at the backend's tile level
    assert level == 2
    edge = tile_edges(SIZE, level)
    ids = ov2["hit_tri"].reshape(SIZE[1], SIZE[0])
    grey = (ids_img == NO_DATA_GREY).all(axis=2)
    assert grey[(ids < 0) & ~edge].all() and not grey[(ids >= 0) & ~edge].any() and not grey[edge].any()
    inside = (ids >= 0) & ~edge
    u, first = np.unique(ids[inside], return_index=True)
    np.testing.assert_array_equal(ids_img[inside], ids_img[inside][first][np.searchsorted(u, ids[inside])])
    assert len(u) >= 3
    # per-tile numbers: distinct hit triangles per tile, computed here from the id image
    rects, counts, from_counts = tiles
    assert from_counts and rects.shape == (16, 4) and counts.shape == (16,)
    flat_t, flat_i = tile_index(SIZE, level).reshape(-1), ov2["hit_tri"]
    keep = flat_i >= 0
    expect = np.bincount(np.unique(flat_t[keep] * 1000 + flat_i[keep]) // 1000, minlength=16)
    np.testing.assert_array_equal(counts, expect)


def test_views_the_backend_does_not_produce(gl_ctx, tiny):
    """Errors name the backends that do produce a view (from the registry); the panel's line names none."""
    from viewer.ui.panel import overlay_missing_line

    others = [n for n in backend_names() if n != "fake" and backend_info(n).overlays]
    r = Renderer(gl_ctx, tiny.scene, tiny.bvh, SIZE, "fake", parse_effects("shadows"))
    cam = tiny.scene.default_camera
    try:
        r.render(cam)
        final = r.read_image()
        for other in others:
            view = backend_info(other).overlays[0].name
            r.view = view
            with pytest.raises(RtwalkError, match=f"backend 'fake' does not produce.*{other}"):
                r.render(cam)
            r.strict_overlays = False
            r.render(cam)
            np.testing.assert_array_equal(r.read_image(), final)
            line = overlay_missing_line(r)
            assert line and view in line and not any(n in line for n in backend_names())
            r.strict_overlays = True
    finally:
        r.release()


# --------------------------------------------------------------------------- panel


def test_panel_helpers_and_panel_drive_the_fake_backend(fake):
    from viewer.ui.panel import counter_rows, phase_label

    r, cam = fake
    info = r.backend.info
    hist, vtx, rep = draw_views(r, cam, ("fake_crossings", "fake_tris", "final"))
    assert min(vtx.values()) > 1000
    assert vtx["fake_crossings"] > vtx["final"]  # the legend is drawn over the heat view
    names, table = hist.phase_table()
    assert names == list(info.phases) and table.shape == (3, 3) and (table > 0).all()
    assert [phase_label(n) for n in names] == ["read", "intersect", "write"]
    rows, others = counter_rows(rep.backend_stats, info.counters)
    assert rows == list(info.counters) and "rays" not in others
    assert hist.counter_mean("pair_tests") == pytest.approx(np.mean([c["pair_tests"] for c in hist.counters]))


# --------------------------------------------------------------------------- bench harness


def test_bench_harness_drives_the_fake_backend(gl_ctx, tiny, tmp_path):
    from PIL import Image

    from viewer.bench.replay import BenchOptions, print_summary, run_bench
    from viewer.recording import Keyframe, Recording

    cam0 = tiny.scene.default_camera
    cam1 = Camera.look_at((-1.5, 2.0, 5.0), (0.2, 0.5, -1.0), fov_y=60.0)
    rec = Recording({"builtin": "tiny"}, SIZE, 2.0,
                    [Keyframe(0.0, cam0.position, cam0.orientation, cam0.fov_y),
                     Keyframe(1.0, cam1.position, cam1.orientation, cam1.fov_y)])
    opts = BenchOptions(backend="fake", size=SIZE, reference="none", warmup=0, frames_dir=tmp_path, frame_every=1,
                        backend_options={"fake": "tile_level=1"})
    report = run_bench(tiny, rec, parse_effects("primary,shadows"), opts, gl_ctx, quiet=True)
    assert report["backend"] == "fake"
    assert report["backend_params"] == "tile_level=1,max_triangles=4096"  # the params text lands in the report
    assert len(report["frames"]) == 3
    for row in report["frames"]:
        st = row["backend_stats"]
        assert st["rays"] == sum(row["rays"].values()) > 0  # summed over the frame's passes
        assert st["pair_tests"] == st["rays"] * tiny.scene.triangle_count
        assert set(FakeBackend.info.phases) <= set(row["gpu_ms"])
        n = row["frame"]
        assert row["overlays"] == [f"fake_crossings_{n:05d}.png", f"fake_tris_{n:05d}.png"]
        final = np.asarray(Image.open(tmp_path / f"frame_{n:05d}.png").convert("RGB"))
        heat = np.asarray(Image.open(tmp_path / row["overlays"][0]).convert("RGB")).reshape(-1, 3).astype(np.int32)
        ids = np.asarray(Image.open(tmp_path / row["overlays"][1]).convert("RGB"))
        assert heat.shape == (SIZE[0] * SIZE[1], 3) and ids.shape == final.shape
        lut = np.vstack([heat_lut().astype(np.int32), np.full((1, 3), NO_DATA_GREY)])
        assert (heat[:, None, :] == lut[None]).all(axis=2).any(axis=1).all()  # only colormap entries and grey
        assert len(np.unique(heat, axis=0)) >= 2 and not np.array_equal(ids, final)
    out = io.StringIO()
    print_summary(report, out)
    assert "backend=fake" in out.getvalue()


# --------------------------------------------------------------------------- no backend names in generic code

GENERIC = ["viewer/renderer.py", "viewer/cli.py", "viewer/cli_args.py", "viewer/tracing.py", "viewer/progressive.py",
           "viewer/iostats.py",
           *sorted(str(p.relative_to(REPO)) for folder in ("passes", "ui", "gl", "cl")
                   for p in (REPO / "viewer" / folder).glob("*.py"))]
# benchmark modules that are one backend's (or one paper's) studies and so may name backends; every
# other module of viewer/bench is generic (an explicit list: a new study does not slip through by
# its file name)
BACKEND_STUDIES = {"chcrt.py", "chcrt_common.py", "chcrt_coherence.py", "chcrt_ooc.py", "chcrt_stages.py",
                   "chcrt_coldstart.py", "pgrid.py",
                   "pgrid_studies.py", "voxelwalk.py", "voxels.py", "gl_micro.py", "grids_far.py", "bvh_trace.py",
                   "__init__.py"}  # the benchmark registry names the studies, as the backend registry does
# names a generic module may use for something other than the backend: raw Embree (embreex) is the
# independent timing reference of bench-trace, not the `embree` backend
ALLOWED = {"viewer/bench/trace_vs_embree.py": {"embree"}}


def _bench_modules() -> list:
    return [str(p.relative_to(REPO)) for p in sorted((REPO / "viewer/bench").glob("*.py"))
            if p.name not in BACKEND_STUDIES]


# string literal tokens: Python 3.12 splits an f-string into FSTRING_START/MIDDLE/END (PEP 701),
# where 3.11 gives one STRING
STRING_TOKENS = {tokenize.STRING} | ({tokenize.FSTRING_MIDDLE} if hasattr(tokenize, "FSTRING_MIDDLE") else set())


def backend_names_in(source: str, names: list[str]) -> list[tuple[int, str]]:
    """(line, token) of every identifier or string literal naming a backend: an identifier equal
    to a name or with it as a '_'-separated part, a string with the name as a word (not a file
    extension such as '.glsl'). Comments and docstrings do not count."""
    found = []
    tree = ast.parse(source)
    doc_lines = {n.body[0].lineno for n in ast.walk(tree)
                 if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body
                 and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)
                 and isinstance(n.body[0].value.value, str)}
    alternatives = "|".join(map(re.escape, names))
    words = re.compile(rf"(?<![\w.])({alternatives})(?!\w)")
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.NAME and not keyword.iskeyword(tok.string):
            if any(n == tok.string or n in tok.string.split("_") for n in names):
                found.append((tok.start[0], tok.string))
        elif tok.type in STRING_TOKENS and tok.start[0] not in doc_lines and words.search(tok.string):
            found.append((tok.start[0], tok.string))
    return found


def test_the_name_check_finds_names():
    names = ["glsl", "chcrt"]
    src = 'x = "glsl"\nimport viewer.backends.chcrt_front\ny = f"use chcrt)"\n# chcrt in a comment\nz = "a.glsl"\n'
    assert [line for line, _ in backend_names_in(src, names)] == [1, 2, 3]


@pytest.mark.parametrize("path", GENERIC + _bench_modules())
def test_generic_modules_name_no_backend(path):
    names = sorted((set(BACKENDS) | {"fake"}) - ALLOWED.get(path, set()))
    found = backend_names_in((REPO / path).read_text(), names)
    assert not found, f"{path} names a backend: {found}"


def test_fake_params_defaults_validate():
    FakeParams().validate()
    with pytest.raises(RtwalkError, match="max_triangles"):
        FakeParams(max_triangles=0).validate("RTWALK_FAKE")


def test_every_parameter_is_documented():
    """Every parameter of every registered backend carries a help text (interface.param): it is
    what `rtwalk info --backend NAME` prints and the panel's tooltips show."""
    from viewer.backends import backend_info, backend_names
    from viewer.backends.interface import describe, param_docs

    for name in backend_names():
        info = backend_info(name)
        missing = [d.name for d in param_docs(info.params) if not d.help.strip()]
        assert not missing, f"{name}: parameters without help: {missing}"
        text = describe(info)
        assert all(f"{d.name}=" in text for d in param_docs(info.params))


def test_panel_lists_the_backend_parameters_with_their_help():
    from types import SimpleNamespace

    from viewer.ui.panel import param_rows

    backend = SimpleNamespace(info=FakeBackend.info, params=FakeParams(max_triangles=7))
    rows = dict(param_rows(backend))
    assert "max_triangles = 7" in rows

"""The CHC+RT backend: conservative mode returns exactly the glsl baseline's hits on every ray
type over a moving camera (so the temporal fronts change between frames), aggressive mode only
loses hits, counters and overlays are consistent, temporal coherence saves queries, and the
query-pair hierarchy keeps its invariants."""

from __future__ import annotations

import numpy as np
import pytest

from viewer.accel.bvh import build_bvh
from viewer.backends.chcrt.chcrt_front import (
    DEAD,
    INNER,
    INVISIBLE,
    VISIBLE,
    NodeTables,
    PairFront,
)
from viewer.camera import Camera
from viewer.effects import RayType, parse_effects
from viewer.paths import SHARED_SCENES
from viewer.rays import PassInfo
from viewer.renderer import Renderer
from viewer.screen_tiles import max_tile_level, tile_rects

SIZE = (128, 72)
ALL = "primary,shadows,soft:2,ao:2,diffuse:2,reflections"
_SCENES: dict = {}


def _load(name: str):
    """(scene in leaf order, bvh, camera path) for city / sponza / conference, cached."""
    if name in _SCENES:
        return _SCENES[name]
    spec = {"city": ("city", 40_000), "sponza": (SHARED_SCENES / "sponza-dabrovic" / "sponza.obj", None),
            "conference": (SHARED_SCENES / "conference" / "conference.ply", None)}[name]
    if name != "city" and not spec[0].exists():
        pytest.skip(f"{spec[0]} not present")
    try:
        from viewer.session import prepare_scene

        prep = prepare_scene(str(spec[0]), scene_size=spec[1], quiet=True)
        scene, bvh = prep.scene, prep.bvh
    except ImportError:  # viewer.scene_io not there yet: build the scene here
        scene, bvh = _fallback_scene(name, spec[0])
    if name == "city":  # make the commonest material a mirror: plenty of reflection rays
        from dataclasses import replace

        common = int(np.bincount(scene.material_ids).argmax())
        scene = replace(scene, materials=[replace(m, mirror=m.mirror or i == common)
                                          for i, m in enumerate(scene.materials)])
    lo, hi = scene.bounds
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    ext = hi - lo
    if name == "city":
        cam0 = scene.default_camera
        path = [Camera(cam0.position + np.array([1.5 * i, 0.4 * i, -4.0 * i]), cam0.orientation, cam0.fov_y)
                for i in range(4)]
    else:  # a short walk through the atrium / towards the conference table
        eye, target = {"sponza": ((0.2, 0.3, 0.5), (0.9, 0.25, 0.6)),
                       "conference": ((0.3, 0.5, 0.3), (0.75, 0.1, 0.6))}[name]
        eye, target = lo + np.array(eye) * ext, lo + np.array(target) * ext
        step = np.array([0.03, 0.005, 0.02]) * ext
        path = [Camera.look_at(eye + i * step, target) for i in range(4)]
    _SCENES[name] = (scene, bvh, path)
    return _SCENES[name]


def _fallback_scene(name: str, path):
    from viewer.scene import Material, PointLight, RectLight, Scene

    if name == "city":
        from viewer.procedural import make_city

        scene = make_city(40_000, 1)
    else:
        import trimesh

        mesh = trimesh.load(str(path), force="mesh")
        tris = np.asarray(mesh.triangles, np.float32)
        area = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        tris = np.ascontiguousarray(tris[area > 0])
        lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
        ext = hi - lo
        c = (lo + hi) / 2
        top = np.array([c[0], hi[1] - 0.1 * ext[1], c[2]], np.float32)
        grey = [Material("grey", np.full(3, 0.7, np.float32))]
        scene = Scene(name, tris, np.zeros(len(tris), np.int32), grey,
                      [PointLight(top, np.full(3, 50.0, np.float32))],
                      [RectLight((top - [0.1 * ext[0], 0, 0.1 * ext[2]]).astype(np.float32),
                                 np.array([0.2 * ext[0], 0, 0], np.float32),
                                 np.array([0, 0, 0.2 * ext[2]], np.float32), np.full(3, 5.0, np.float32))])
    bvh = build_bvh(scene.triangles)
    return scene.reordered(bvh.tri_order), bvh


_GLSL_FRAMES: dict = {}  # (scene, effects) -> the glsl reference frames (captured), rendered once


@pytest.fixture(scope="module", autouse=True)
def _sync_cold_start():
    """These tests count a front's passes from one refined by the paper's synchronous first pass
    (ChcrtParams.cold_start=sync; a test that names cold_start overrides it). The device cold start,
    the default where fronts live on the device, has its own tests below (test_device_cold_start_*),
    and the registry-wide agreement, hard-case and image tests run it."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RTWALK_CHCRT", "cold_start=sync")
        yield


@pytest.fixture(scope="module", autouse=True)
def _release_module_caches():
    """The scenes and reference frames cached here are dropped after this module (the session's
    peak memory is not this module's plus the next ones')."""
    yield
    _GLSL_FRAMES.clear()
    _SCENES.clear()


def _glsl_frames(ctx, name: str, effects: str) -> list:
    """The glsl frames along the scene's path: the reference every chcrt configuration of this
    module is compared with (the pipeline is deterministic, so one rendering serves them all)."""
    key = (name, effects)
    if key not in _GLSL_FRAMES:
        scene, bvh, path = _load(name)
        rg = Renderer(ctx, scene, bvh, SIZE, "glsl", parse_effects(effects))
        try:
            _GLSL_FRAMES[key] = [rg.render(cam, capture=True) for cam in path]
        finally:
            rg.release()
    return _GLSL_FRAMES[key]


def _front_params(params: str) -> str:
    """`params` with the work probe off unless they set it: these tests check the fronts' own path in
    every steady pass, and the probe may send a test scene's passes through the whole BVH (its own
    tests below set it)."""
    return params if "work_probe" in params else ",".join(p for p in ("work_probe=0", params) if p)


def _render_both(ctx, name: str, effects: str = ALL, params: str = ""):
    scene, bvh, path = _load(name)
    ref = _glsl_frames(ctx, name, effects)
    rc = Renderer(ctx, scene, bvh, SIZE, "chcrt", parse_effects(effects), {"chcrt": _front_params(params)})
    try:
        return [(a, rc.render(cam, capture=True)) for a, cam in zip(ref, path, strict=True)], scene, bvh
    finally:
        rc.release()


def _exact_t(triangles: np.ndarray, o: np.ndarray, d: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Float64 distance of each ray to the plane of its triangle."""
    v = triangles[tri].astype(np.float64)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return ((v[:, 0] - o) * n).sum(1) / (d.astype(np.float64) * n).sum(1)


def _check_exact(a, b, label: str, triangles: np.ndarray) -> dict:
    """chcrt == glsl on one pass; returns the number of ties.

    Closest-hit rays: same hit/miss and bitwise the same t, except on *ties*: two triangles at the
    same true distance (coplanar overlap, shared edges), where the float32 triangle test may give
    each a slightly different t and which one wins depends on the visiting order (the slab test
    prunes a box whose entry rounds beyond the first hit) in glsl as well. A tie must be certified
    in float64: both triangles' planes are met at the same distance (1e-5 relative, plus a few
    float32 ulps of the coordinates)."""
    assert a.ray_type == b.ray_type and a.sample == b.sample and a.light == b.light
    assert np.array_equal(a.rays.tmax, b.rays.tmax), label  # same rays (deterministic pipeline)
    act = a.rays.active
    ha, hb = (a.tri >= 0) & act, (b.tri >= 0) & act
    assert np.array_equal(ha, hb), (label, "hit/miss differs", int((ha != hb).sum()))
    assert (b.tri[~act] == -1).all() and np.isinf(b.t[~act]).all(), label
    if a.ray_type.any_hit:
        # which occluder an any-hit ray reports depends on the traversal order; it must be a hit
        t = b.t[hb]
        assert (t > b.rays.tmin[hb]).all() and (t < b.rays.tmax[hb]).all(), label
        return {"ties": 0}
    differ = ha & ((a.t.view(np.int32) != b.t.view(np.int32)) | (a.tri != b.tri))
    if differ.any():
        o, d = a.rays.origins[differ], a.rays.directions[differ]
        ta, tb = a.t[differ].astype(np.float64), b.t[differ].astype(np.float64)
        assert (a.tri[differ] != b.tri[differ]).all(), label  # one triangle always gives one t
        scale = max(float(np.abs(triangles).max()), float(np.abs(o).max()))
        tol = 1e-5 * np.maximum(ta, tb) + 8 * float(np.spacing(np.float32(scale)))
        ea = _exact_t(triangles, o, d, a.tri[differ])
        eb = _exact_t(triangles, o, d, b.tri[differ])
        assert (np.abs(ea - eb) <= tol).all(), (label, "not a tie", np.abs(ea - eb).max())
        assert (np.abs(ta - tb) <= tol).all(), (label, "distances differ", np.abs(ta - tb).max())
    ties = int(differ.sum())
    assert ties <= 0.1 * max(act.sum(), 1), (label, "too many ties", ties)
    return {"ties": ties}


@pytest.mark.parametrize("name,mode", [("city", "batched"), ("city", "hw"), ("sponza", "batched"),
                                       ("conference", "batched")])
def test_conservative_equals_glsl_every_ray_type(name, mode, gl_ctx):
    """Exact on every ray type, in both query modes (hardware occlusion queries, one draw each;
    instanced draws with shader-counted queries)."""
    frames, scene, bvh = _render_both(gl_ctx, name, params=f"query_mode={mode}")
    seen = set()
    ties = 0
    for k, (a, b) in enumerate(frames):
        assert len(a.captured) == len(b.captured)
        for pa, pb in zip(a.captured, b.captured, strict=True):
            if pa.rays.active.any():
                seen.add(pa.ray_type)
            ties += _check_exact(pa, pb, f"{name} frame {k} {pa.ray_type.label} sample {pa.sample} "
                                 f"light {pa.light}", scene.triangles)["ties"]
        st = b.backend_stats
        assert st["rays"] == sum(b.rays.values())
        assert st["queries"] >= st["multi_queries"] >= st["failed_multi_queries"] >= 0
    assert {RayType.PRIMARY, RayType.AO, RayType.DIFFUSE} <= seen
    if name == "city":
        assert seen >= {RayType.SHADOW, RayType.SOFT, RayType.REFLECT}
    # temporal coherence was exercised: later frames start from the previous fronts
    later = [b.backend_stats for _, b in frames[1:]]
    assert sum(s["phase1_subtrees"] for s in later) > 0
    # multi-queries (synchronous passes) or the GPU-driven pass, which tests every invisible pair
    assert sum(s["multi_queries"] + s["gpu_driven"] for s in later) > 0
    assert sum(s["query_waves"] + s["pull_ups"] + s["newly_visible_queries"] for s in later) > 0  # fronts moved
    print(f"{name}: {ties} tied closest hits over {len(frames)} frames")


@pytest.mark.parametrize("params", ["lca_pairs=1,full_bvh_fraction=0,lca_primary=true", "lca_pairs=1,lca_primary=true",
                                    "lca_pairs=8,cull_sublevels=2,cold_full_bvh=false", "lca_invisible=false",
                                    "hit_hint=false", "gap_order=false,count_due_only=false", "cone_cull=false"])
def test_lca_fallback_and_cull_tiles_are_exact(params, gl_ctx):
    """The GPU-driven pass's per-tile choices keep glsl's hits: a tile over `lca_pairs` pairs
    traverses the lowest common ancestor of all of them and its invisible pairs are not queried
    (lca_pairs=1 and lca_primary: every tile, so no pair is queried on a steady frame, and with
    full_bvh_fraction the pass runs the glsl traversal; 8: some tiles of the passes other than
    primary (whose tiles test their pairs), the cull per sub-tile, with every front refined past its
    first pass), and the older rule (only the visible pairs replaced, the invisible ones
    queried); without the hit hints; without the gap order of the records' items (and with every
    visible pair counted)."""
    frames, scene, _ = _render_both(gl_ctx, "city", "primary,shadows,ao:2,diffuse:2", params)
    for k, (a, b) in enumerate(frames):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"city {params} frame {k} {pa.ray_type.label} sample {pa.sample}",
                         scene.triangles)
    steady = [b.backend_stats for _, b in frames[1:]]
    assert all(s["gpu_driven"] > 0 for s in steady)
    if params.startswith("lca_pairs=1,full_bvh_fraction=0"):
        assert all(s["lca_tiles"] > 0 and s["query_records_drawn"] == 0 for s in steady)
    elif params.startswith("lca_pairs=1,"):  # every tile over the limit: every pass through the full traversal
        # (cold_full_bvh: the first pass stops refining at once, and its front stays full-BVH)
        assert all(b.backend_stats["full_bvh_passes"] > 0 for _, b in frames)
        assert all(s["full_bvh_passes"] > 0 and s["query_records_drawn"] == 0 for s in steady)
    elif params.startswith("lca_pairs=8"):
        assert sum(s["lca_tiles"] for s in steady) > 0


def test_cone_cull_drops_pairs_beside_the_tiles(gl_ctx):
    """cone_cull (exact: the default in every test here) tests fewer invisible pairs per pixel than
    the reach alone: pairs whose boxes lie beside a tile's rays are dropped by the cull."""
    on, _, _ = _render_both(gl_ctx, "city", "primary", "")
    off, _, _ = _render_both(gl_ctx, "city", "primary", "cone_cull=false")
    qon = sum(b.backend_stats["query_pixels"] for _, b in on[1:])
    qoff = sum(b.backend_stats["query_pixels"] for _, b in off[1:])
    assert qoff > 0 and qon < qoff, (qon, qoff)


def test_aggressive_mode_only_loses_hits(gl_ctx):
    cons, _, _ = _render_both(gl_ctx, "city", "primary,ao:2,diffuse:2")
    aggr, _, _ = _render_both(gl_ctx, "city", "primary,ao:2,diffuse:2", "visible_threshold=40")
    lost = 0
    for a, b in aggr:
        for pa, pb in zip(a.captured, b.captured, strict=True):
            act = pa.rays.active
            ha, hb = (pa.tri >= 0) & act, (pb.tri >= 0) & act
            assert not (hb & ~ha).any()  # never a hit that glsl lacks
            if not pa.ray_type.any_hit:
                both = ha & hb
                assert (pb.t[both] >= pa.t[both]).all()  # never nearer than the nearest hit
                lost += int((pb.t[both] > pa.t[both]).sum())
            lost += int((ha & ~hb).sum())
        st = b.backend_stats
        assert st["queries"] >= st["multi_queries"] >= st["failed_multi_queries"]
        assert st["rays"] == sum(b.rays.values())
    culled = sum(b.backend_stats["subtrees_scheduled"] for _, b in aggr)
    culled_cons = sum(c.backend_stats["subtrees_scheduled"] for _, c in cons)
    assert lost > 0 or culled < culled_cons  # the threshold culled something


def test_static_camera_second_frame_needs_fewer_queries(gl_ctx):
    # (one front per AO sample: with share_sample_fronts the first frame's second sample already
    # starts from the first sample's front, see test_sample_passes_share_one_front)
    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary,shadows,ao:2"),
                 {"chcrt": "share_sample_fronts=0"})
    try:
        first = r.render(path[0]).backend_stats
        second = r.render(path[0]).backend_stats
    finally:
        r.release()
    assert second["queries"] < first["queries"]
    assert second["phase1_subtrees"] > 0 and first["phase1_subtrees"] == 0


@pytest.mark.parametrize("mode", ["batched", "hw"])
def test_overlays_and_counters(mode, gl_ctx):
    from viewer.gl.textures import read_texture

    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary"), {"chcrt": f"query_mode={mode}"})
    r.capture_overlays = True
    try:
        r.render(path[0])
        rays = r.rays
        res = r.backend.trace(rays, PassInfo(RayType.PRIMARY), r.hits)
        t, tri = r.hits.read()
        stats = dict(res.stats)
        for k, v in r.backend.end_frame().items():  # a device front's counts come after the pass
            stats[k] = stats.get(k, 0) + v
        od = read_texture(res.overlays["query_overdraw"]).reshape(-1)
        sub = read_texture(res.overlays["subtree_id"]).reshape(-1)
    finally:
        r.release()
    assert res.overlays["query_overdraw"].size == SIZE and res.overlays["subtree_id"].size == SIZE
    assert int(od.sum()) == stats["query_pixels"]
    hit = tri >= 0
    assert hit.any() and (sub[hit] >= 0).all() and (sub[~hit] == -1).all()
    first, count = bvh.node_first[sub[hit]], bvh.node_count[sub[hit]]
    assert ((tri[hit] >= first) & (tri[hit] < first + count)).all()  # the hit lies in that subtree
    st = stats
    if mode == "hw":  # one draw per query and per batch
        assert st["draws"] >= st["queries"] + st["intersect_draws"] and st["intersect_draws"] == st["batches"]
    else:  # one instanced draw per query wave / intersection step; a device front's pass: a fixed chain
        fixed = 18 if st["device_front_passes"] else 8
        assert st["queries"] > st["query_waves"] + 2 and st["draws"] <= st["query_waves"] + fixed
        assert st["intersect_draws"] < st["batches"]
    assert st["subtrees_scheduled"] > 0


def test_params_from_env():
    from viewer.backends.chcrt import ChcrtParams
    from viewer.backends.interface import parse_params
    from viewer.errors import RtwalkError

    p = parse_params(ChcrtParams, "visible_threshold=20, t_q=0.25,overdraw_overlay=off", "RTWALK_CHCRT")
    assert p.visible_threshold == 20 and p.t_q == 0.25 and not p.overdraw_overlay
    assert parse_params(ChcrtParams, "", "RTWALK_CHCRT") == ChcrtParams()
    with pytest.raises(RtwalkError):
        parse_params(ChcrtParams, "tq=1", "RTWALK_CHCRT")
    with pytest.raises(RtwalkError):
        parse_params(ChcrtParams, "t_q=fast", "RTWALK_CHCRT")


def test_trace_rays_entry_point_matches_glsl():
    from viewer.procedural import make_city
    from viewer.tracing import trace_rays

    # random rays inside a small city: many subtrees per tile and per ray (this caught a Mesa
    # llvmpipe miscompilation of repeated traversal loops, see backends/chcrt/chc_intersect_record.glsl)
    tris = make_city(20_000, 1).triangles
    n = 50_000
    rng = np.random.default_rng(1)
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    o = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(1, 50, n), 1e30).astype(np.float32)
    tmax[::10] = -1.0  # some inactive rays
    for any_hit in (False, True):
        tg, ig = trace_rays(tris, o, d, 0.0, tmax, any_hit=any_hit, backend="glsl")
        tc, ic = trace_rays(tris, o, d, 0.0, tmax, any_hit=any_hit, backend="chcrt")
        assert np.array_equal(ig >= 0, ic >= 0)
        if not any_hit:
            assert np.array_equal(tg, tc)
            assert ((ig == ic) | (ig < 0)).mean() > 0.999  # ids may differ on exact ties only


# -- the pair hierarchy without GL ---------------------------------------------------------------------


def test_tiles_partition_the_screen_and_levels():
    size = (160, 90)
    assert max_tile_level(size, 0.015) == 3  # 1/64 of the screen is the smallest tile
    assert max_tile_level((1920, 1080), 200 * 200 / (1920 * 1080)) == 2
    for level in range(4):
        n = 1 << level
        gx, gy = np.meshgrid(np.arange(n), np.arange(n))
        r = tile_rects(np.full(n * n, level), gx.ravel(), gy.ravel(), size)
        cover = np.zeros(size[::-1], int)
        for x, y, w, h in r:
            cover[y:y + h, x:x + w] += 1
        assert (cover == 1).all()


def _assert_leaves_partition(f: PairFront, bvh, leaves: np.ndarray) -> None:
    """Leaf pairs `leaves` partition (screen x scene): on every finest tile, the leaves over it cover
    each triangle (leaf order) exactly once."""
    top = f.max_level
    for tx in range(1 << top):
        for ty in range(1 << top):
            cover = np.zeros(bvh.stats.triangles, int)
            for i in leaves:
                shift = top - int(f.level[i])
                if (tx >> shift) == f.tx[i] and (ty >> shift) == f.ty[i]:
                    a = bvh.node_first[f.node[i]]
                    cover[a:a + bvh.node_count[f.node[i]]] += 1
            assert (cover == 1).all()


def test_front_split_rule_subdivide_pull_up_and_compact():
    from viewer.procedural import make_city

    bvh = build_bvh(make_city(3000, 1).triangles)
    nt = NodeTables.from_bvh(bvh)
    f = PairFront((64, 64), 2, np.random.default_rng(0), 3)
    # refine everything down to termination
    wave = np.array([0])
    while len(wave):
        term, obj, ray = f.classify(wave, nt, 0.5, 8, 1000)
        assert (term.astype(int) + obj + ray == 1).all()
        f.state[wave[term]] = VISIBLE
        wave = f.subdivide(wave[~term], obj[~term], nt)
    f.check(nt)
    vis = f.leaves(VISIBLE)
    assert (f.level[vis] == 2).all()  # terminated only at the smallest tile
    assert (nt.height[f.node[vis]] <= 8).all() and (nt.count[f.node[vis]] <= 1000).all()
    # the rule: terminated pairs are small relative to their tile, or BVH leaves
    nd = f.node[vis]
    assert (nt.is_leaf[nd] | (nt.area_ratio[nd] <= 0.5 / 16)).all()
    _assert_leaves_partition(f, bvh, vis)
    # everything invisible: pulled up one level per call, down to the root
    f.state[vis] = INVISIBLE
    calls = 0
    while (f.state[: f.n] == INNER).any():
        f.pull_up()
        f.check(nt)
        calls += 1
    assert calls > 1
    f.compact()
    assert f.n == 1 and f.state[0] == INVISIBLE and not (f.state[: f.n] == DEAD).any()


@pytest.mark.parametrize("max_pairs", [1, 6, 64, 100_000])
def test_presplit_keeps_the_partition_within_its_budget(max_pairs):
    """A device cold start's front, split by the rule as if every pair were entered (PairFront.presplit):
    within its pair budget, its leaves all invisible and untested, partitioning (screen x scene); with
    room enough, every pair the rule would terminate is reached (the same leaves as refining down to
    termination)."""
    from viewer.procedural import make_city

    bvh = build_bvh(make_city(3000, 1).triangles)
    nt = NodeTables.from_bvh(bvh)
    f = PairFront((64, 64), 2, np.random.default_rng(0), 3)
    waves = f.presplit(nt, 0.5, 8, 1000, max_pairs)
    f.check(nt)
    assert f.n <= max(max_pairs, 1) and (waves > 0) == (max_pairs >= 6)
    leaves = f.leaves(INVISIBLE)
    assert len(leaves) + len(f.leaves(INNER)) == f.n and (f.pixels[leaves] == 0).all() and (f.age[leaves] == 0).all()
    _assert_leaves_partition(f, bvh, leaves)
    if max_pairs == 100_000:
        term, _, _ = f.classify(leaves, nt, 0.5, 8, 1000)
        assert term.all()


def test_multi_query_groups_follow_chcpp():
    from viewer.procedural import make_city

    bvh = build_bvh(make_city(3000, 1).triangles)
    nt = NodeTables.from_bvh(bvh)
    f = PairFront((64, 64), 0, np.random.default_rng(0), 3)
    wave = np.array([0])
    for _ in range(5):  # a few object-space levels on the single tile
        wave = f.subdivide(wave, ~nt.is_leaf[f.node[wave]], nt)
    inv = f.leaves(INVISIBLE)
    f.age[inv] = 10  # long invisible: big groups
    groups = f.multi_query_groups(inv, 24)
    assert sorted(np.concatenate(groups).tolist()) == sorted(inv.tolist())
    # q = 0.99: the expected pairs per query k / (1 + (1 - q^k) k) peaks at k = 11
    assert max(len(g) for g in groups) == 11 and len(groups) == 3
    assert max(len(g) for g in f.multi_query_groups(inv, 4)) == 4
    f.age[inv] = 0  # just became invisible: q = 0.29, not worth grouping
    assert all(len(g) == 1 for g in f.multi_query_groups(inv, 24))


def test_headless_resize_rebuilds_chcrt_targets(gl_ctx):
    """Renderer.resize works without a default framebuffer (EGL), and chcrt restarts its fronts at
    the new size: still exactly the glsl hits."""
    scene, bvh, path = _load("city")
    settings = parse_effects("primary,ao:1")
    rg = Renderer(gl_ctx, scene, bvh, SIZE, "glsl", settings)
    rc = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", settings)
    try:
        rc.render(path[0])
        small = (SIZE[0] // 2 + 3, SIZE[1] // 2 + 1)
        for r in (rg, rc):
            r.resize(small)
        a, b = rg.render(path[1], capture=True), rc.render(path[1], capture=True)
        assert b.rays["primary"] == small[0] * small[1]
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"resized {pa.ray_type.label}", scene.triangles)
    finally:
        rg.release()
        rc.release()


@pytest.mark.parametrize("name,cache", [("city", 1), ("city", 2), ("city", 4), ("sponza", 3)])
def test_leaf_cache_is_exact(name, cache, gl_ctx):
    """The leaf cache (paper 5.2) only delays ray-triangle tests: the same hits as glsl for every
    cache size, including sizes that do not divide the leaf counts a ray meets, in both query modes.
    hw mode (one draw per query: 2.5x the time) runs on city, where it takes a third of sponza's time;
    the leaf cache is the same intersection shader in both modes. Sponza runs once, with the size
    that divides no leaf count (3; its size 2 repeated city's cases at 8 s)."""
    mode = "hw" if (name, cache) == ("city", 2) else "batched"
    frames, scene, _ = _render_both(gl_ctx, name, params=f"leaf_cache={cache},query_mode={mode}")
    seen = set()
    for k, (a, b) in enumerate(frames):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            if pa.rays.active.any():
                seen.add(pa.ray_type)
            _check_exact(pa, pb, f"{name} cache {cache} frame {k} {pa.ray_type.label} sample {pa.sample}",
                         scene.triangles)
        assert b.backend_stats["rays"] == sum(b.rays.values())
    assert {RayType.PRIMARY, RayType.SHADOW, RayType.AO, RayType.DIFFUSE} <= seen
    assert sum(b.backend_stats["phase1_subtrees"] for _, b in frames[1:]) > 0  # temporal fronts used


def test_leaf_cache_param_checked():
    from viewer.backends.chcrt import MAX_LEAF_CACHE, ChcrtParams
    from viewer.backends.interface import parse_params
    from viewer.errors import RtwalkError

    assert parse_params(ChcrtParams, "leaf_cache=2", "--chcrt").leaf_cache == 2
    for bad in (-1, MAX_LEAF_CACHE + 1):
        with pytest.raises(RtwalkError, match="leaf_cache"):
            ChcrtParams(leaf_cache=bad).validate()


@pytest.mark.parametrize("name,params", [
    ("city", "gpu_budget_fraction=0.47"),
    ("city", "gpu_budget_fraction=0.2,leaf_cache=2,query_mode=hw"),  # evicts too (1,718 over the walk)
    ("city", "gpu_budget_fraction=0.05,max_subtree_tris=256"),  # tiny: the cache thrashes
    ("sponza", "gpu_budget_fraction=0.1,max_subtree_tris=512"),
])
def test_out_of_core_is_exact(name, params, gl_ctx):
    """Out-of-core (paper 5.4): with the BVH and triangles read only from the round-robin subtree
    cache, the hits stay those of glsl on the in-core scene for every budget; what is uploaded is
    counted, and small budgets evict and re-upload subtrees. The hw query mode (one draw per query
    and per batch) with a cache that evicts runs on city: on sponza it took 42 s of the suite."""
    frames, scene, _ = _render_both(gl_ctx, name, "primary,shadows,ao:2,diffuse:2", params)
    up = ev = 0.0
    for k, (a, b) in enumerate(frames):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"{name} {params} frame {k} {pa.ray_type.label} sample {pa.sample}",
                         scene.triangles)
        st = b.backend_stats
        assert st["rays"] == sum(b.rays.values())
        up += st["upload_bvh_mb"] + st["upload_geom_mb"]
        ev += st["cache_evictions"]
    assert up > 0
    if "0.05" in params or "0.1" in params or "hw" in params:
        assert ev > 0


def test_out_of_core_budget_checked(gl_ctx):
    from viewer.errors import RtwalkError

    scene, bvh, _ = _load("city")
    with pytest.raises(RtwalkError, match="too small"):
        Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary"), {"chcrt": "gpu_budget_mb=0.01"})


def test_round_robin_ring_never_overlaps_live_entries():
    """The cache's ring allocator against a slot-owner array: every live entry keeps its slots,
    would_evict() predicts place(), and entries are evicted only when overwritten or at a wrap."""
    from viewer.backends.chcrt.chcrt_cache import Entry, RingAllocator

    rng = np.random.default_rng(0)
    for cap in (10, 37, 100):
        ring, owner, live = RingAllocator(cap), np.full(cap, -1), {}
        evicted = 0
        for i in range(1500):
            size = int(rng.integers(0, cap // 2 + 1))
            pred = ring.would_evict(size)
            start, ev = ring.place(size, Entry(i, 0, 0, 0, size))
            assert [id(x) for x in pred] == [id(x) for x in ev]
            assert 0 <= start and start + size <= cap
            for x in ev:
                live.pop(x.node)
            evicted += len(ev)
            owner[start:start + size] = i
            if size:
                live[i] = (start, size)
            for k, (s, n) in live.items():
                assert (owner[s:s + n] == k).all()
            assert sum(n for s, n in live.values()) <= cap
        assert evicted > 100


def _submission_counts(ctx, size: tuple[int, int], params: str) -> tuple[int, int]:
    """(gl_draws + gl_queries, host_syncs) of chcrt on a steady frame (the fourth of a short walk)."""
    from viewer.procedural import make_city

    if "small-city" not in _SCENES:
        scene = make_city(3_000, 2)
        bvh = build_bvh(scene.triangles)
        _SCENES["small-city"] = (scene.reordered(bvh.tri_order), bvh, None)
    scene, bvh, _ = _SCENES["small-city"]
    lo, hi = scene.triangles.reshape(-1, 3).min(0), scene.triangles.reshape(-1, 3).max(0)
    ext = hi - lo
    eye, target = lo + np.array([0.1, 0.1, 0.1]) * ext, lo + np.array([0.6, 0.02, 0.7]) * ext
    r = Renderer(ctx, scene, bvh, size, "chcrt", parse_effects("primary"), {"chcrt": params})
    try:
        for i in range(4):
            io = r.render(Camera.look_at(eye + i * 0.01 * ext, target)).io
    finally:
        r.release()
    return io.gl_draws + io.gl_queries, io.host_syncs


def test_submission_does_not_grow_with_the_image(gl_ctx):
    """GPU-shaped submission (viewer.iostats): on a steady frame, the draws and queries of a pass
    are a fixed number, not one per tile, query wave or visible subtree, so 640x360 with 16x the
    tiles needs at most 1.3x the count at 320x180; the host waits for the device a fixed small
    number of times. 640x360 suffices: what could grow the submission is the tiles (and the pairs
    on them), and min_tile_fraction=0.0009 gives the same 1,024 finest tiles (level 5) as 1280x720
    did, at a quarter of the pixels (the test took 26 s of the suite at 1280x720)."""
    assert max_tile_level((640, 360), 0.0009) == max_tile_level((320, 180), 0.015) + 2  # 16x the tiles
    # (the work probe off: the fronts' own passes at both sizes, not a whole-BVH pass at one of them)
    small, small_syncs = _submission_counts(gl_ctx, (320, 180), "work_probe=0")
    big, big_syncs = _submission_counts(gl_ctx, (640, 360), "work_probe=0,min_tile_fraction=0.0009")
    assert 0 < big <= 1.3 * small, (small, big)
    # the frame's waits (the profiler's per-phase finishes on llvmpipe, the G-buffer and shade passes,
    # chcrt's one count read per pass) are a fixed number: 16x the tiles adds none
    assert big_syncs == small_syncs <= 24, (small_syncs, big_syncs)


# -- device-resident fronts (chcrt_devfront.py) ------------------------------------------------------
FRONT_STATS = ("visible_pairs", "invisible_pairs", "inner_pairs", "queries", "subtrees_scheduled", "lca_tiles",
               "newly_visible_queries", "requeries", "pull_ups", "rays", "query_pixels", "phase1_subtrees",
               "batches", "full_bvh_passes")


def _walk(ctx, params: str, effects: str, frames: int = 6, backend: str = "chcrt"):
    """chcrt (or `backend`) frames along a longer city walk (the fronts split, merge and re-query),
    captured."""
    scene, bvh, path = _load("city")
    cam0 = path[0]
    cams = [Camera(cam0.position + np.array([0.9 * i, 0.25 * i, -2.5 * i]), cam0.orientation, cam0.fov_y)
            for i in range(frames)]
    r = Renderer(ctx, scene, bvh, SIZE, backend, parse_effects(effects), {"chcrt": _front_params(params)})
    try:
        return [r.render(cam, capture=True) for cam in cams]
    finally:
        r.release()


@pytest.mark.parametrize("extra", ["", "visible_threshold=3", "cull_sublevels=1,lca_pairs=24"])
def test_device_front_is_the_host_front(extra, gl_ctx):
    """The device front plans, refines and pulls up exactly as the host front does: with every
    visible leaf re-queried each frame (the re-query phases are random and drawn differently), the
    same pairs, queries, scheduled subtrees and LCA tiles every frame, and the same hits bit for bit
    (both list a tile's pairs in the same order). Also in aggressive mode and with sub-tile culls.
    (merge_kept off: the host front has no merged kept pairs, whose counts take the ray's final hit.)"""
    effects = "primary,ao:2,diffuse:1"
    # (share_sample_fronts off: the host front refines after every sample pass, a shared device front
    # once a frame)
    base = "requery_interval=1,merge_kept=0,share_sample_fronts=0" + ("," + extra if extra else "")
    host = _walk(gl_ctx, base + ",device_front=0", effects)
    dev = _walk(gl_ctx, base, effects)
    assert sum(b.backend_stats.get("device_front_passes", 0) for b in dev) > 0
    assert sum(b.backend_stats.get("device_front_passes", 0) for b in host) == 0
    # A pixel that several records of one draw cover counts their pairs against the nearest hit so
    # far (bestBits), so the counts depend on the order those fragments run in: llvmpipe shades a
    # draw's primitives in order, a GPU overlaps them. Elsewhere the fronts may drift apart, and only
    # the hits must agree (chcrt's exactness: _check_exact, ties certified).
    in_order = "llvmpipe" in str(gl_ctx.info.get("GL_RENDERER", "")).lower()
    triangles = _load("city")[0].triangles
    moved = 0
    for i, (h, d) in enumerate(zip(host, dev, strict=True)):
        for k in FRONT_STATS if in_order else ():
            assert h.backend_stats.get(k, 0) == d.backend_stats.get(k, 0), (i, k, h.backend_stats, d.backend_stats)
        moved += d.backend_stats.get("newly_visible_queries", 0) + d.backend_stats.get("pull_ups", 0)
        for a, b in zip(h.captured, d.captured, strict=True):
            if in_order:
                same = np.array_equal(a.tri, b.tri) and np.array_equal(a.t.view(np.int32), b.t.view(np.int32))
                assert same, (i, a.ray_type)
            else:
                _check_exact(a, b, f"device front {extra} frame {i} {a.ray_type.label}", triangles)
    assert moved > 0  # the fronts did change on the device


@pytest.mark.parametrize("extra", ["", "max_batch=4"])
def test_merged_kept_pairs_keep_the_hits(extra, gl_ctx):
    """merge_kept: tiles test their kept invisible pairs in their last visible record's fragments
    instead of a survivors' draw. The same closest hits bit for bit, and the same any-hit answers,
    as the survivors' draw on every frame of the walk (the fronts may differ: a merged kept pair
    counts a ray entering it before the ray's final hit), and almost no survivors' records are left
    to draw. Also where small records (max_batch=4) give most tiles several (the same hits; there
    many tiles keep more pairs than a record holds and draw them as survivors)."""
    effects = "primary,ao:2,diffuse:1"
    off = _walk(gl_ctx, ",".join(filter(None, ["merge_kept=0", extra])), effects)
    on = _walk(gl_ctx, extra, effects)
    records = {"off": 0.0, "on": 0.0}
    for i, (a_rep, b_rep) in enumerate(zip(off, on, strict=True)):
        if i > 0:  # steady frames (the first builds the fronts synchronously)
            records["off"] += a_rep.backend_stats.get("query_records_drawn", 0)
            records["on"] += b_rep.backend_stats.get("query_records_drawn", 0)
        for a, b in zip(a_rep.captured, b_rep.captured, strict=True):
            assert a.ray_type == b.ray_type
            if a.ray_type == RayType.AO:  # any hit: which triangle depends on the order
                assert np.array_equal(a.tri >= 0, b.tri >= 0), (i, a.ray_type)
            else:
                assert np.array_equal(a.t.view(np.int32), b.t.view(np.int32)), (i, a.ray_type)
                assert np.mean(a.tri == b.tri) > 0.999, (i, a.ray_type)  # ties at equal t may differ
    assert 4 * records["on"] < records["off"] or extra, records


def test_sample_passes_share_one_front(gl_ctx):
    """share_sample_fronts: an effect's sample passes share one front, and on device fronts only the
    first of them in a frame refines it (four launches fewer for each other one); any-hit ones also
    take its plan (one dispatch instead of five: four more), and AO's, whose samples share their
    origins, its cull by reach too (its rays' bestBits copied instead of their tile bounds and cull:
    one more, less the first pass's copy). They still answer exactly as the glsl baseline
    (conservative mode) and as one front per sample does; one front for ao:4 instead of four."""
    effects = "primary,shadows,ao:4,diffuse:2"
    keep = "full_bvh_fraction=0"  # (the diffuse rays' front stays on the device, not on full traversals)
    own = _walk(gl_ctx, keep + ",share_sample_fronts=0", effects)
    shared = _walk(gl_ctx, keep, effects)
    ref = _walk(gl_ctx, "", effects, backend="glsl")
    passes = 0
    for i, (o, s, g) in enumerate(zip(own, shared, ref, strict=True)):
        for a, b, c in zip(o.captured, s.captured, g.captured, strict=True):
            assert a.ray_type == b.ray_type == c.ray_type
            if a.ray_type.any_hit:  # which triangle depends on the order
                assert np.array_equal(b.tri >= 0, c.tri >= 0), (i, a.ray_type)
                assert np.array_equal(a.tri >= 0, b.tri >= 0), (i, a.ray_type)
            else:
                assert np.array_equal(b.t.view(np.int32), c.t.view(np.int32)), (i, a.ray_type)
        fronts = s.backend_stats.get("shared_front_passes", 0)
        plans = s.backend_stats.get("shared_plan_passes", 0)
        culls = s.backend_stats.get("shared_cull_passes", 0)
        assert o.backend_stats.get("shared_front_passes", 0) == 0
        assert o.backend_stats.get("shared_cull_passes", 0) == 0
        if i >= 2:  # steady (frame 0 builds the fronts, frame 1 attaches them to the device)
            # AO samples 1-3 (shared plans and culls) and diffuse sample 1; the one shadow pass is its
            # front's first
            assert (fronts, plans, culls) == (4, 3, 3), (i, s.backend_stats)
            assert o.backend_stats["full_bvh_passes"] == s.backend_stats["full_bvh_passes"] == 0
            assert o.io.gl_draws - s.io.gl_draws == 4 * fronts + 4 * plans + culls - 1, (i, o.io, s.io)
        passes += fronts
    assert passes > 0
    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("ao:4"))
    try:
        r.render(path[0])
        assert len(r.backend.fronts) == 1
    finally:
        r.release()


@pytest.mark.parametrize("extra", ["", "max_batch=4"])
def test_merged_kept_pairs_are_always_drawn(extra, gl_ctx):
    """A tile's merged kept pairs ride in its last visible record (chc_front.glsl keptCarrier), so
    that record must draw even when the cone cull (chc_visorder.comp) leaves none of its own items:
    after every pass each tile with merged kept pairs has its carrier drawn, and the walk does
    produce records kept only for them; with small records (max_batch=4), also in tiles of several
    records."""
    from viewer.backends.chcrt.chcrt_devfront import TILE_PLAN_DTYPE
    from viewer.backends.chcrt.chcrt_layout import DRAW_DTYPE

    scene, bvh, path = _load("city")
    cam0 = path[0]
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary"),
                 {"chcrt": ",".join(filter(None, ["work_probe=0", extra]))})
    kept_only = merged_tiles = multi = 0
    try:
        n_tiles = 1 << (2 * r.backend.tile_level(SIZE))
        for i in range(8):
            r.render(Camera(cam0.position + np.array([0.9 * i, 0.25 * i, -2.5 * i]), cam0.orientation, cam0.fov_y))
            dv = r.backend.devfronts
            if dv is None or dv.last_plan is None:
                continue  # no plan of a front in the buffers this frame: they hold nothing written
            n = int(np.frombuffer(dv.args.read(size=8), np.uint32)[1])
            rec = np.frombuffer(dv.records.read(size=max(n, 1) * DRAW_DTYPE.itemsize), DRAW_DTYPE)[:n]
            plans = np.frombuffer(dv.tiles.read(size=n_tiles * TILE_PLAN_DTYPE.itemsize), TILE_PLAN_DTYPE)
            merged = np.flatnonzero(plans["keptCount"] > 0)
            carrier = plans["recBase"][merged] + plans["nrec"][merged] - 1
            assert (plans["nrec"][merged] > 0).all() and (carrier < n).all(), i
            assert np.array_equal(rec["info"][carrier, 3], merged), i  # the tile's own record
            drawn = (rec["rect"][:, 2] > 0) & (rec["rect"][:, 3] > 0)
            assert drawn[carrier].all(), (i, merged[~drawn[carrier]])
            merged_tiles += len(merged)
            multi += int(np.sum(plans["nrec"][merged] > 1))
            is_carrier = np.zeros(n, bool)
            is_carrier[carrier] = True
            kept_only += int(np.sum((rec["info"][:, 1] == 0) & is_carrier))
    finally:
        r.release()
    assert merged_tiles > 0 and kept_only > 0, (merged_tiles, kept_only)
    assert multi > 0 or not extra, multi


def test_device_front_frame_crosses_nothing(gl_ctx, monkeypatch):
    """A steady frame on device fronts sends the backend's nothing to the device and reads no pass's counts: it
    waits exactly as often as glsl's frame (timer phase timing: no per-phase finishes), and what it
    reads back beyond glsl's is one META read after the frame's finish."""
    from viewer.backends.chcrt.chcrt_devfront import META_INTS

    monkeypatch.setenv("RTWALK_PHASE_TIMING", "timer")
    scene, bvh, path = _load("city")
    ios = {}
    for backend, params in (("glsl", {}), ("chcrt", {"chcrt": ""}), ("chcrt-host", {"chcrt": "device_front=0"})):
        r = Renderer(gl_ctx, scene, bvh, SIZE, backend.split("-")[0], parse_effects("primary,shadows,ao:4"), params)
        try:
            for cam in path[:3]:
                rep = r.render(cam)
            ios[backend] = rep.io
            if backend == "chcrt":
                meta_bytes = r.backend.devfronts.meta_slots * META_INTS * 4
        finally:
            r.release()
    g, c, h = ios["glsl"], ios["chcrt"], ios["chcrt-host"]
    assert c.bytes_to_device == g.bytes_to_device, (g, c)  # the frame's own (no backend sends anything)
    assert c.bytes_to_host - g.bytes_to_host == meta_bytes, (g, c)
    assert c.host_syncs == g.host_syncs, (g, c)
    assert h.host_syncs == g.host_syncs + 6 and h.bytes_to_device > 0  # the host plan: a count read per pass


@pytest.mark.parametrize("params", ["", "device_front=0"])
def test_device_writes_are_fenced_before_fetches_and_copies(params, gl_ctx, monkeypatch):
    """What llvmpipe forgives and GL does not, in chcrt's pass sequence:
    - the intersection reads its items through a buffer texture (chc_common.glsl loadItem), and
      compute shaders write them (the device fronts' plan, the cull, the visible order): a texel
      fetch sees storage writes only after glMemoryBarrier(GL_TEXTURE_FETCH_BARRIER_BIT);
    - bestBits is written by shader image stores and atomics (tile bounds, intersection) and by
      copies (an AO sample takes the first pass's, glCopyImageSubData): a copy is ordered after
      shader writes only by GL_TEXTURE_UPDATE_BARRIER_BIT.
    Checked on the recorded dispatches, draws, copies and barriers of a short walk, without the loop
    limit (RTWALK_LOOP_LIMIT=none, as on a GPU: no counter read, whose barrier hides a missing one)."""
    import moderngl

    import viewer.backends.chcrt.chcrt_pass_device as pass_device

    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    events: list[tuple[str, int]] = []  # (what, program or texture id, or barrier bits)

    def recording(method, kind: str):
        def wrapped(self, *a, **k):
            if kind == "barrier":
                events.append((kind, int(a[0] if a else k.get("barrier", moderngl.ALL_BARRIER_BITS))))
            else:
                events.append((kind, id(self)))
            return method(self, *a, **k)
        return wrapped

    for cls, name, kind in ((moderngl.ComputeShader, "run", "dispatch"),
                            (moderngl.ComputeShader, "run_indirect", "dispatch"),
                            (moderngl.VertexArray, "render", "draw"), (moderngl.VertexArray, "render_indirect", "draw"),
                            (moderngl.Context, "memory_barrier", "barrier")):
        monkeypatch.setattr(cls, name, recording(getattr(cls, name), kind))
    copy = pass_device.copy_texture

    def recorded_copy(dst, src):
        events.append(("copy", id(dst)))
        copy(dst, src)

    monkeypatch.setattr(pass_device, "copy_texture", recorded_copy)
    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary,ao:3"), {"chcrt": _front_params(params)})
    try:
        for cam in path[:4]:
            r.render(cam)
        be = r.backend
        item_writers = {id(p) for p in (be.querycull, be.visorder, be.visorder_dev) if p is not None}
        if be.devfronts is not None:
            item_writers |= {id(p) for p in be.devfronts.prog.values()}
        image_writers = {id(be.tilebounds), id(be.tilebounds_init), id(be.vao_isect_g)}
        isect = id(be.vao_isect_g)
    finally:
        r.release()
    items_fenced = images_fenced = True
    counted = {"isect": 0, "isect after item writes": 0, "copies after image writes": 0}
    for i, (kind, what) in enumerate(events):
        if kind == "dispatch" and what in item_writers:
            items_fenced = False
        if what in image_writers and kind in ("dispatch", "draw"):
            images_fenced = False
        if kind == "barrier":
            items_fenced |= bool(what & moderngl.TEXTURE_FETCH_BARRIER_BIT)
            images_fenced |= bool(what & moderngl.TEXTURE_UPDATE_BARRIER_BIT)
        elif kind == "draw" and what == isect:
            counted["isect"] += 1
            counted["isect after item writes"] += int(any(k == "dispatch" and w in item_writers for k, w in events[:i]))
            assert items_fenced, (i, events[max(0, i - 8):i + 1])
        elif kind == "copy":
            counted["copies after image writes"] += int(any(w in image_writers for _, w in events[:i]))
            assert images_fenced, (i, events[max(0, i - 8):i + 1])
    assert counted["isect"] > 0 and counted["isect after item writes"] > 0, counted
    if not params:  # (AO's later samples take the first's bestBits on device fronts)
        assert counted["copies after image writes"] > 0, counted


def test_device_front_overflow_stays_exact(gl_ctx, monkeypatch):
    """Fronts and items over their device capacity: splits are refused (the pair's subtree is
    intersected whole) and every tile traverses its lowest common ancestor, both exact; the overflow
    is counted, and the host grows the buffers after the frame."""
    from viewer.backends.chcrt import chcrt_devfront as D

    monkeypatch.setattr(D, "MIN_CAPACITY", 16)
    orig = D.DeviceFronts.ensure

    def tiny(self, tiles=0, copies=0, pairs=0, cull_tiles=0):  # item capacity without the 2x margin
        orig(self, tiles=tiles, copies=0, pairs=pairs, cull_tiles=cull_tiles)

    monkeypatch.setattr(D.DeviceFronts, "ensure", tiny)
    monkeypatch.setattr(D, "_pow2", lambda n: max(int(n), 1))
    rows, scene, _ = _render_both(gl_ctx, "city", "primary,ao:2", "")
    assert sum(b.backend_stats.get("front_overflows", 0) for _, b in rows) > 0
    for a, b in rows:
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, "overflow", scene.triangles)


def test_device_front_unreported_pass_counts_nothing(gl_ctx):
    """A pass nobody reports (PassInfo.report=False: the traced G-buffer's rays) adds nothing to
    the statistics the frame reads after its finish; a reported one does."""
    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary"))
    try:
        r.render(path[0])  # the cold pass: the front moves to the device
        be = r.backend
        be.begin_frame(be.frame + 1)  # (each its own frame: a shared front refines once a frame)
        be.trace(r.rays, PassInfo(RayType.PRIMARY, report=False), r.hits)
        gl_ctx.finish()
        quiet = be.end_frame()
        be.begin_frame(be.frame + 1)
        be.trace(r.rays, PassInfo(RayType.PRIMARY), r.hits)
        gl_ctx.finish()
        loud = be.end_frame()
    finally:
        r.release()
    assert quiet.get("rays", 0) == 0 and quiet.get("visible_pairs", 0) == 0, quiet
    assert loud["rays"] > 0 and loud["visible_pairs"] > 0, loud


def test_full_bvh_passes_count_their_work(gl_ctx, monkeypatch):
    """The work counters (RTWALK_COUNT_WORK=1) include the glsl traversal chcrt falls back to: a
    chcrt pass that traces the whole BVH (every tile over lca_pairs=1) reports glsl's nodes, box and
    triangle tests, not zero (the tuning study's tests per ray once read 0 for such passes). A
    regular GPU-driven pass counts fewer nodes than glsl's full traversal."""
    monkeypatch.setenv("RTWALK_COUNT_WORK", "1")
    scene, bvh, path = _load("city")
    stats = {}
    for label, backend, params in [("glsl", "glsl", ""), ("full", "chcrt", "lca_pairs=1,lca_primary=true"),
                                   ("chcrt", "chcrt", "work_probe=0")]:
        r = Renderer(gl_ctx, scene, bvh, SIZE, backend, parse_effects("primary,ao:1"), {"chcrt": params})
        try:
            stats[label] = [r.render(cam).backend_stats for cam in path[:3]]
        finally:
            r.release()
    for g, f, c in zip(stats["glsl"], stats["full"], stats["chcrt"], strict=True):
        assert f["full_bvh_passes"] > 0 and c["full_bvh_passes"] == 0
        for key in ("work_invocations", "work_nodes", "work_box_tests", "work_tri_tests"):
            assert g[key] > 0 and f[key] == g[key], (key, g[key], f[key])
    steady = stats["chcrt"][-1]
    assert 0 < steady["work_nodes"] < stats["glsl"][-1]["work_nodes"], steady
    # the per-pixel images (lane statistics) hold the same nodes and triangle tests as the totals,
    # and lane groups of 8 and 32 pixels (nested: a 8x4 group is four 4x2 ones) pay at least them
    for frame in (*stats["glsl"], *stats["full"], *stats["chcrt"]):
        for key in ("nodes", "tri_tests"):
            assert frame[f"work_pixel_{key}"] == frame[f"work_{key}"], (key, frame)
            assert frame[f"work_{key}"] <= frame[f"work_simd8_{key}"] <= frame[f"work_simd32_{key}"], (key, frame)


@pytest.mark.parametrize("given", [True, False])
def test_whole_bvh_passes_take_the_ray_generations_count(given, gl_ctx, monkeypatch):
    """A device pass that traces the whole BVH counts its rays only for the statistics: it copies the
    ray generation's count (PassInfo.ray_count) into its ray slots with one invocation of
    chc_count_rays.comp instead of a dispatch that reads every ray, and rays without such a count
    (`given` False) are counted by that dispatch; either way the statistics count every ray."""
    import moderngl

    from viewer.passes.raygen import RayGenPass

    if not given:
        generate = RayGenPass.generate
        monkeypatch.setattr(RayGenPass, "generate", lambda self, *a, **k: (generate(self, *a, **k), None)[1])
    dispatched: list[tuple[int, tuple]] = []  # (program, work groups)
    run = moderngl.ComputeShader.run
    monkeypatch.setattr(moderngl.ComputeShader, "run",
                        lambda self, *a, **k: (dispatched.append((id(self), a)), run(self, *a, **k))[1])
    scene, bvh, path = _load("city")
    cam0 = path[0]
    params = "work_probe=4,work_ratio_full=0.001,work_ratio_full_any=0.001"
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary,ao:2"), {"chcrt": params})
    try:
        frames = [r.render(Camera(cam0.position + np.array([0.9 * i, 0.25 * i, -2.5 * i]), cam0.orientation,
                                  cam0.fov_y)) for i in range(6)]
        counter = id(r.backend.count_rays)
        groups = [a for prog, a in dispatched if prog == counter]
    finally:
        r.release()
    assert sum(b.backend_stats.get("wasted_front_passes", 0) for b in frames) > 0
    for b in frames:
        assert b.backend_stats["rays"] == sum(b.rays.values())
    copies = [a for a in groups if tuple(a) == (1, 1)]  # (SIZE is more than one 64x64 region)
    assert groups and ((len(copies) == len(groups)) if given else not copies), groups


def test_lane_group_work_matches_a_loop_over_the_groups():
    """lane_group_work against plain Python loops over the lane groups, on an odd-sized screen whose
    edge groups are partly off it (idle lanes)."""
    from viewer.backends.base import lane_group_work

    rng = np.random.default_rng(5)
    per_pixel = rng.integers(0, 50, size=(13, 22))
    for gw, gh in ((4, 2), (8, 4), (1, 1), (3, 5)):
        want = 0
        for y0 in range(0, 13, gh):
            for x0 in range(0, 22, gw):
                want += gw * gh * max(int(per_pixel[y, x]) for y in range(y0, min(y0 + gh, 13))
                                      for x in range(x0, min(x0 + gw, 22)))
        assert lane_group_work(per_pixel, (gw, gh)) == want, (gw, gh)
    assert lane_group_work(per_pixel, (1, 1)) == per_pixel.sum()
    assert lane_group_work(np.full((4, 8), 3), (4, 2)) == 3 * 32  # equally busy lanes: nothing wasted


@pytest.mark.parametrize("passes,wave", [(1, 5.5), (4, 5.5), (4, 0.0)])
def test_cold_refinement_goes_on_after_its_budget(passes, wave, gl_ctx):
    """cold_full_bvh: a front's first pass that runs out of query budget (cold_query_budget) traces
    the whole BVH, and with cold_passes > 1 the front's next passes go on refining from where it
    stopped until the front is complete and moves to the device (a deep BVH, city 10 M, needs that:
    its first pass's refinement alone costs more than the budget). With cold_passes=1, or when the
    refinement cost more query fragments per ray and wave than cold_wave_queries (incoherent rays),
    every pass stays on the full traversal. Every frame keeps glsl's hits."""
    scene, bvh, _ = _load("city")
    params = f"cold_query_budget=8,cold_passes={passes},cold_wave_queries={wave}"
    frames = _walk(gl_ctx, params, "primary,ao:1")
    ref = _walk(gl_ctx, "", "primary,ao:1", backend="glsl")
    for k, (a, b) in enumerate(zip(ref, frames, strict=True)):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"city {params} frame {k} {pa.ray_type.label}", scene.triangles)
    full = [b.backend_stats["full_bvh_passes"] for b in frames]
    device = [b.backend_stats["device_front_passes"] for b in frames]
    assert full[0] == 2, full  # both fronts stopped on the budget in their first pass
    if passes == 1 or wave == 0:
        assert all(n == 2 for n in full) and not any(device), (full, device)
    else:
        assert full[-1] == 0 and device[-1] == 2, (full, device)  # refined to the end, then GPU-driven
        assert sum(n > 0 for n in full) <= passes, full
        # no front is on the device while its refinement goes on
        assert all(d == 0 for n, d in zip(full, device, strict=True) if n > 0), (full, device)


def test_work_probe_counts_what_both_traversals_do(gl_ctx, monkeypatch):
    """work_probe, sampling every pixel (work_probe_stride=1): the full traversal's side
    (chc_probe.comp) counts exactly what the glsl backend's own shader counts for the same rays
    (RTWALK_COUNT_WORK=1: box and triangle tests plus one per ray), and the front's side exactly
    what chcrt's work counters count for its pass (plus one per fragment)."""
    monkeypatch.setenv("RTWALK_COUNT_WORK", "1")
    scene, bvh, path = _load("city")
    stats = {}
    for backend in ("glsl", "chcrt"):
        r = Renderer(gl_ctx, scene, bvh, SIZE, backend, parse_effects("primary"),
                     {"chcrt": "work_probe=8,work_probe_stride=1"})
        try:
            stats[backend] = [r.render(cam).backend_stats for cam in path[:2]]
        finally:
            r.release()
    g, c = stats["glsl"][1], stats["chcrt"][1]  # frame 1: the front's first device pass measures
    assert "work_probe_rays" not in stats["chcrt"][0]  # the cold (synchronous) pass does not
    assert c["work_probe_passes"] == 1 and c["resumed_rays"] == 0 and g["work_invocations"] > 0
    assert c["work_probe_rays"] == g["work_invocations"], (c, g)
    assert c["work_probe_full"] == g["work_invocations"] + g["work_box_tests"] + g["work_tri_tests"], (c, g)
    assert c["work_probe_front"] == c["work_invocations"] + c["work_box_tests"] + c["work_tri_tests"], c
    assert c["work_probe_ratio"] == pytest.approx(c["work_probe_front"] / c["work_probe_full"])


def _walk_exact(ctx, params: str, effects: str, frames: int):
    """chcrt's frames of the city walk (_walk), each pass checked against glsl's (_check_exact)."""
    scene, _, _ = _load("city")
    out = _walk(ctx, params, effects, frames=frames)
    ref = _walk(ctx, "", effects, frames=frames, backend="glsl")
    for k, (a, b) in enumerate(zip(ref, out, strict=True)):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"city {params} frame {k} {pa.ray_type.label}", scene.triangles)
    return out


@pytest.mark.parametrize("limit", [0.001, 100.0])
def test_work_probe_sends_fronts_that_save_nothing_through_the_whole_bvh(limit, gl_ctx):
    """A front measured to do more than work_ratio_full(_any) of the full traversal's work traces
    the whole BVH (exact: glsl's traversal) until its next measurement, and the pass before that
    measurement runs the front again to bring it up to date; under the limit nothing changes. With
    work_probe=4: measurements at a front's device passes 0, 3, 7, ...; the warm-up at 2, 6, ..."""
    params = f"work_probe=4,work_ratio_full={limit},work_ratio_full_any={limit}"
    frames = _walk_exact(gl_ctx, params, "primary,ao:1", 7)
    probes = [b.backend_stats["work_probe_passes"] for b in frames]
    wasted = [b.backend_stats["wasted_front_passes"] for b in frames]
    n = probes[1]  # the device fronts (frame 0 builds them synchronously)
    assert n >= 1 and probes == [0, n, 0, 0, n, 0, 0], probes
    assert frames[1].backend_stats["work_probe_fronts"] == n
    for b in frames:  # counted by the init draw, the tile bounds or (whole-BVH passes) chc_count_rays.comp
        assert b.backend_stats["rays"] == sum(b.rays.values())
    if limit < 1:
        assert wasted == [0, 0, n, 0, 0, n, n], wasted
        assert all(frames[k].backend_stats["full_bvh_passes"] >= n for k in (2, 5, 6))
    else:
        assert not any(wasted), wasted


def test_shared_front_measures_once_a_frame_with_hints(gl_ctx):
    """share_sample_fronts with the work probe: a shared front measures in the first pass of a frame
    only, and the frame's other sample passes follow its decision (all trace the whole BVH, or
    none), except that once the front was measured wasteful they trace the whole BVH also while the
    first pass brings it up to date (warm-up) or measures it again. Its first measurement waits for
    a pass with hit hints: in the frame that builds the front, sample 1's first device pass has none
    (it would measure more work than any later pass). With work_probe=4: measurements at the
    front's passes 0 and 3 (frames 1 and 4), a warm-up at 2 (frame 3)."""
    frames = _walk_exact(gl_ctx, "work_probe=4,work_ratio_full_any=0.001", "ao:2", 7)  # any front is wasteful
    probes = [b.backend_stats["work_probe_passes"] for b in frames]
    wasted = [b.backend_stats["wasted_front_passes"] for b in frames]
    shared = [b.backend_stats["shared_plan_passes"] for b in frames]
    assert probes == [0, 1, 0, 0, 1, 0, 0], probes
    # ... and the measurements arrive: the later sample pass keeps the front's META row
    assert [b.backend_stats.get("work_probe_fronts", 0) for b in frames] == [0, 1, 0, 0, 1, 0, 0]
    assert wasted == [0, 0, 2, 1, 1, 2, 2], wasted
    # (frame 0: sample 0 builds the front synchronously, sample 1 plans its first device pass; frame 1:
    # sample 1 shares the plan of the first measurement; a whole-BVH pass plans nothing to share)
    assert shared == [0, 1, 0, 0, 0, 0, 0], shared
    # a whole-BVH sample pass keeps the ray counts the frame's first pass left (AO's samples share
    # their rays' activity) instead of counting again; the statistics still count every ray
    assert [b.backend_stats.get("shared_ray_counts", 0) for b in frames] == [0, 0, 1, 1, 1, 1, 1]
    assert [b.backend_stats["rays"] for b in frames] == [sum(b.rays.values()) for b in frames]


def test_shared_closest_hit_front_keeps_its_measurement(gl_ctx):
    """A shared closest-hit front's later sample pass plans again (its own visible order): that plan
    must keep what the frame's first pass measured (the work probe) in the front's META row, or the
    front is never measured. Diffuse fronts kept on the device (no cold or LCA switch to the whole
    BVH), any front wasteful: measured at frames 1 and 4, whole-BVH samples as designed, exact."""
    params = "work_probe=4,work_ratio_full=0.001,cold_full_bvh=0,lca_pairs=100000,full_bvh_fraction=1"
    frames = _walk_exact(gl_ctx, params, "diffuse:2", 7)
    st = [b.backend_stats for b in frames]
    assert [s["device_front_passes"] for s in st[1:]] == [2] * 6  # (frame 0 builds the front)
    assert [s["work_probe_passes"] for s in st] == [0, 1, 0, 0, 1, 0, 0]
    assert [s.get("work_probe_fronts", 0) for s in st] == [0, 1, 0, 0, 1, 0, 0]
    assert [s["wasted_front_passes"] for s in st] == [0, 0, 2, 1, 1, 2, 2]


def test_work_probe_params_checked():
    from viewer.backends.chcrt.chcrt_params import ChcrtParams
    from viewer.errors import RtwalkError

    for bad in ({"work_probe": -1}, {"work_probe_stride": 0}, {"work_ratio_full": 0.0}, {"work_ratio_full_any": -1.0}):
        with pytest.raises(RtwalkError):
            ChcrtParams(**bad).validate()


def test_tile_bounds_are_the_same_bits_for_every_group_size(gl_ctx):
    """chc_tilebounds.comp runs 8 invocations a tile on a CPU rasterizer and 64 on a GPU
    (chcrt_layout.tile_bounds_group): both builds (and 16, 32) give every tile the same bounds, ray
    count and bestBits bits on the same rays, with and without CHC_INIT_RAYS, so the GPU's build is
    checked where no GPU is."""
    from viewer.backends.chcrt import chcrt_layout as L
    from viewer.gl.programs import compute_shader

    scene, bvh, path = _load("city")
    r = Renderer(gl_ctx, scene, bvh, (200, 120), "chcrt", parse_effects("ao:1"))
    try:
        for cam in path[:3]:
            r.render(cam)  # (rays of the last AO pass stay in r.rays; bestBits as its pass left them)
        be = r.backend
        level = be.tile_level((200, 120))
        tiles = 1 << (2 * level)
        best0 = np.frombuffer(be.targets.best.read(), np.int32).copy()
        outs = {}
        for init in (0, 1):
            for group in (8, 16, 32, 64):
                defs = {**L.BINDINGS, "TILE_BOUNDS_GROUP": group, **({"CHC_INIT_RAYS": 1} if init else {})}
                comp = compute_shader(gl_ctx, "chc_tilebounds.comp", defs, (L.HERE,))
                be.targets.best.write(best0.tobytes())
                r.rays.origin.use(0)
                r.rays.direction.use(1)
                be.targets.best.bind_to_image(L.BIND_IMG_CHC_BEST, read=True, write=True)
                be.tile_bounds.bind_to_storage_buffer(L.BIND_CHC_TILES)
                be.gpu_counts.write(bytes(L.COUNT_BYTES))
                be.gpu_counts.bind_to_storage_buffer(L.BIND_CHC_COUNT, 0, L.COUNT_BYTES)
                comp["rayOrigin"], comp["rayDir"] = 0, 1
                comp["raySize"], comp["level"] = (200, 120), level
                comp.run(tiles)
                gl_ctx.finish()
                counts = np.frombuffer(be.gpu_counts.read(size=L.COUNT_BYTES), np.uint32)
                outs[init, group] = (be.tile_bounds.read(size=tiles * L.TILE_BOUND_BYTES),
                                     int(counts.sum()), be.targets.best.read())
                comp.release()
        for init in (0, 1):
            ref = outs[init, 64]
            bounds = np.frombuffer(ref[0], np.float32).reshape(tiles, -1)
            assert (bounds[:, 7] > 0).any()  # some tile has active rays (omax.w)
            for group in (8, 16, 32):
                assert outs[init, group][0] == ref[0], (init, group)
                assert outs[init, group][2] == ref[2], (init, group)
                if init:
                    assert outs[init, group][1] == ref[1] > 0, (init, group)
    finally:
        r.release()


def test_subtree_triangle_bound_by_ray_type_and_budget():
    """max_subtree_tris=0 (auto): out of core every front's subtrees fit a cache entry (4096
    triangles); in core only shadow-ray fronts keep that bound, the others have none; a number
    given is every front's bound."""
    from viewer.backends.chcrt.chcrt_params import NO_TRI_BOUND, OOC_SUBTREE_TRIS, ChcrtParams

    auto = ChcrtParams()
    bounded = {t for t in RayType if auto.subtree_tri_bound(t) == OOC_SUBTREE_TRIS}
    assert bounded == {RayType.SHADOW, RayType.SOFT}
    assert {auto.subtree_tri_bound(t) for t in RayType if t not in bounded} == {NO_TRI_BOUND}
    ooc = ChcrtParams(gpu_budget_fraction=0.2)
    assert {ooc.subtree_tri_bound(t) for t in RayType} | {ooc.subtree_tri_bound()} == {OOC_SUBTREE_TRIS}
    given = ChcrtParams(max_subtree_tris=777)
    assert {given.subtree_tri_bound(t) for t in RayType} | {given.subtree_tri_bound()} == {777}
    assert NO_TRI_BOUND < 2**31  # (a GLSL int uniform: chc_front_refine.comp maxTris)


def test_device_cold_start_is_exact_every_ray_type(gl_ctx):
    """cold_start=device: a new front is a device front from its first pass, (screen, root) refined a
    level a pass; every pass of every ray type is exact while the fronts settle (glsl's hits), and no
    pass runs the synchronous waves."""
    frames, scene, _ = _render_both(gl_ctx, "city", params="cold_start=device")
    for k, (a, b) in enumerate(frames):
        for pa, pb in zip(a.captured, b.captured, strict=True):
            _check_exact(pa, pb, f"city cold_start=device frame {k} {pa.ray_type.label} sample {pa.sample} "
                         f"light {pa.light}", scene.triangles)
        st = b.backend_stats
        assert st["query_waves"] == 0 and st["multi_queries"] == 0, (k, st)
        assert st["device_front_passes"] == st["gpu_driven"] > 0, (k, st)  # every chcrt pass, from frame 0
        assert st["rays"] == sum(b.rays.values())
    assert frames[0][1].backend_stats["settling_fronts"] > 0  # (a young front: it settles over later frames)


def test_device_cold_start_waits_for_nothing(gl_ctx, monkeypatch):
    """The cold frame of a device cold start waits and reads back exactly what a steady frame does
    (timer phase timing: no per-phase finishes): glsl's host syncs, and one META read after the
    frame's finish; the synchronous cold start waits for every wave of queries."""
    monkeypatch.setenv("RTWALK_PHASE_TIMING", "timer")
    scene, bvh, path = _load("city")
    ios = {}
    for label, backend, params in (("glsl", "glsl", ""), ("device", "chcrt", "cold_start=device"),
                                   ("sync", "chcrt", "cold_start=sync")):
        r = Renderer(gl_ctx, scene, bvh, SIZE, backend, parse_effects("primary,ao:2"), {"chcrt": params})
        try:
            ios[label] = [r.render(cam).io for cam in path[:2]]
            if label == "device":
                meta_bytes = r.backend.devfronts.meta_slots * 16 * 4
        finally:
            r.release()
    (g0, g1), (d0, d1), (s0, _) = ios["glsl"], ios["device"], ios["sync"]
    assert d0.host_syncs == d1.host_syncs == g0.host_syncs == g1.host_syncs, (g0, d0, d1)
    assert d0.bytes_to_host - g0.bytes_to_host == meta_bytes == d1.bytes_to_host - g1.bytes_to_host
    assert s0.host_syncs > d0.host_syncs + 2 and s0.bytes_to_host > d0.bytes_to_host, (s0, d0)


def test_device_cold_front_settles_before_it_is_measured(gl_ctx):
    """A device cold start's front refines a level a pass until a pass splits at most settle_splits
    of its pairs (then `settling_fronts` drops); the work probe measures only settled fronts (a young
    front, about the root, would measure as wasteful and stop refining). A static camera: the fronts
    settle within the frames and then hold visible pairs."""
    scene, bvh, path = _load("city")
    params = _front_params("cold_start=device,work_probe=2")
    r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary,ao:1"), {"chcrt": params})
    try:
        st = [r.render(path[0]).backend_stats for _ in range(24)]
    finally:
        r.release()
    settling = [s["settling_fronts"] for s in st]
    assert settling[0] == 2 and settling[-1] == 0, settling
    assert all(a >= b for a, b in zip(settling, settling[1:], strict=False)), settling  # fronts settle for good
    first = settling.index(0) if 0 in settling else len(settling)
    assert 2 <= first <= 20, settling  # a level a pass: not at once, but within the walk
    probes = [s["work_probe_passes"] for s in st]
    young = [k for k in range(1, len(st)) if settling[k - 1] == 2]  # both fronts settling before frame k
    assert all(probes[k] == 0 for k in [0, *young]), (probes, settling)
    assert sum(probes) > 0, probes  # measured once settled
    assert st[-1]["visible_pairs"] > 0 and st[-1]["device_front_passes"] == 2


@pytest.mark.parametrize("params", ["work_ratio_full_any=0.001", "work_ratio_full_any=100",
                                    "work_ratio_full_any=0.001,settle_probe=0"])
def test_settling_shared_front_is_measured_every_frame(params, gl_ctx):
    """settle_probe: a device cold start's front shared by sample passes (ao:2) is presumed wasteful
    until measured, so its later sample passes trace the whole BVH (frames 0 and 1); its first pass
    in each frame still runs and refines it, and measures it while it settles from the first frame
    with hit hints (frame 1); the later samples follow the last measurement (a limit of 100: none
    is wasteful from frame 2). Without settle_probe no settling pass measures or traces the whole
    BVH. Exact every pass (_walk_exact)."""
    frames = _walk_exact(gl_ctx, f"cold_start=device,work_probe=16,{params}", "ao:2", 6)
    st = [b.backend_stats for b in frames]
    settling = [s["settling_fronts"] for s in st]
    probes = [s["work_probe_passes"] for s in st]
    wasted = [s["wasted_front_passes"] for s in st]
    young = [k for k in range(1, len(st)) if settling[k - 1] > 0]  # the front settling as frame k starts
    assert 2 in young, settling  # (a front that settles later than frame 1: the measurements are seen)
    assert all(s["device_front_passes"] == 2 for s in st)  # both samples on the device front, every frame
    if "settle_probe=0" in params:
        assert all(probes[k] == wasted[k] == 0 for k in [0, *young]), (probes, wasted, settling)
        return
    assert probes[0] == 0 and all(probes[k] == 1 for k in young), (probes, settling)
    assert wasted[:2] == [1, 1], wasted  # presumed wasteful: sample 1 through the whole BVH
    want = 1 if "0.001" in params else 0
    assert all(wasted[k] == want for k in young if k >= 2), (wasted, settling)
    assert settling[-1] <= settling[0], settling  # the front still settles: its first pass refines it


def test_cold_start_resolves_where_fronts_live(gl_ctx):
    """cold_start=auto takes the device where fronts live on the device and are kept between frames;
    without device fronts, or with temporal=0, the synchronous passes; a bad value is one line."""
    from viewer.backends.chcrt.chcrt_params import ChcrtParams
    from viewer.errors import RtwalkError

    scene, bvh, path = _load("city")
    for params, want in (("cold_start=auto", True), ("cold_start=auto,temporal=0", False),
                         ("cold_start=device,device_front=0", False), ("cold_start=sync", False)):
        r = Renderer(gl_ctx, scene, bvh, SIZE, "chcrt", parse_effects("primary"), {"chcrt": params})
        try:
            assert r.backend.device_cold is want, params
            st = r.render(path[0]).backend_stats
            assert (st["query_waves"] == 0) is want, (params, st["query_waves"])
        finally:
            r.release()
    with pytest.raises(RtwalkError, match="cold_start"):
        ChcrtParams(cold_start="lazy").validate()

"""voxelwalk beyond the registry-driven tests (which run its defaults: IVW for primary and any-hit
rays, EC for other closest hits; viewer.tracing traces closest hits as primary rays, so the EC
shapes here say primary=ec): every mode and parameter shape against Embree, EC's determinism
whatever the chunk size and sort (one launch, or global with an atomic minimum on packed keys),
the walk statistics against a float64 NumPy 3D-DDA and a brute-force tile count, and the
overlays through `render --view`."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from tests.cli_runner import run_cli
from tests.conftest import opencl_missing
from viewer.errors import RtwalkError

pytestmark = pytest.mark.skipif(opencl_missing() is not None, reason=str(opencl_missing()))


def _scene() -> np.ndarray:
    """Two nested spheres and a floor quad: closed surfaces, shared edges, rays in every direction."""
    s = trimesh.creation.icosphere(3)
    floor = np.array([[[-2, -1.2, -2], [2, -1.2, -2], [2, -1.2, 2]], [[-2, -1.2, -2], [2, -1.2, 2], [-2, -1.2, 2]]])
    return np.concatenate([s.vertices[s.faces], s.vertices[s.faces] * 0.4 + 0.2, floor]).astype(np.float32)


def _rays(n: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    o = rng.uniform(-1.6, 1.6, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d[: n // 8, 1] = 0.0  # axis-parallel components
    return o, d, np.zeros(n, np.float32), np.full(n, np.inf, np.float32)


@pytest.fixture(scope="module")
def reference():
    from viewer.tracing import trace_rays

    tris = _scene()
    o, d, lo, hi = _rays(6000)
    return tris, (o, d, lo, hi), trace_rays(tris, o, d, lo, hi, backend="embree"), \
        trace_rays(tris, o, d, lo, hi, any_hit=True, backend="embree")


EC = "mode=ec,primary=ec"


def _big_chunk() -> int:
    """The largest chunk this OpenCL device's local memory holds (256 on PoCL, 128 on NVIDIA's 48 KiB)."""
    from viewer.backends.voxelwalk.engine import largest_chunk
    from viewer.cl import cl_context
    from viewer.cl.limits import local_mem

    return largest_chunk(local_mem(cl_context())) or 16


@pytest.mark.parametrize("params", ["mode=ivw", "mode=ec", EC, f"{EC},sort=global", f"{EC},cells=0",
                                    f"{EC},cells=3,chunk=16", f"{EC},chunk=BIG,resolution=4",
                                    f"{EC},chunk=16,resolution=40", "mode=ivw,resolution=300",
                                    f"{EC},resolution=1", f"{EC},sort=global,resolution=1"])
def test_modes_match_embree(monkeypatch, reference, params):
    from viewer.tracing import trace_rays

    monkeypatch.setenv("RTWALK_VOXELWALK", params.replace("BIG", str(_big_chunk())))
    tris, rays, (t0, i0), (ta, ia) = reference
    t1, i1 = trace_rays(tris, *rays, backend="voxelwalk")
    assert ((i0 >= 0) == (i1 >= 0)).all()
    hit = i0 >= 0
    assert hit.mean() > 0.3
    np.testing.assert_allclose(t1[hit], t0[hit], rtol=1e-5)
    assert (i1 == i0).mean() > 0.999  # the rest: ties on shared edges
    t2, i2 = trace_rays(tris, *rays, any_hit=True, backend="voxelwalk")
    assert ((i2 >= 0) == (ia >= 0)).all()


def test_ec_is_deterministic_across_chunk_sizes(monkeypatch):
    """Duplicated triangles (every hit is a tie between two slots): EC gives the same bits for every
    chunk size, sort and window, as IVW does, and the id is one of the tied pair."""
    from viewer.tracing import trace_rays

    base = _scene()
    tris = np.concatenate([base, base])  # triangle k and k + len(base) coincide
    o, d, lo, hi = _rays(3000, seed=5)
    out = []
    for params in (f"{EC},chunk=16", f"{EC},chunk={_big_chunk()}", f"{EC},sort=global,chunk=64",
                   f"{EC},cells=0,chunk=64", f"{EC},cells=4,chunk=32", "mode=ivw"):
        monkeypatch.setenv("RTWALK_VOXELWALK", params)
        out.append(trace_rays(tris, o, d, lo, hi, backend="voxelwalk"))
    for t, i in out[1:]:
        assert np.array_equal(t.view(np.uint32), out[0][0].view(np.uint32))
        assert np.array_equal(i, out[0][1])
    t0, i0 = trace_rays(tris, o, d, lo, hi, backend="embree")
    hit = i0 >= 0
    assert ((out[0][1] >= 0) == hit).all()
    assert (out[0][1][hit] % len(base) == i0[hit] % len(base)).mean() > 0.999


def _two_level_walker(tris: np.ndarray, big: float, chunk: int, skip: str, **kw):
    """A two-level grid with sub-grids forced (a 3-cell top grid, every occupied cell a sub-grid;
    with big=0.25 the longer triangles in the cells' big lists) and a walker over it."""
    from viewer.accel.grid import GridSpec, scene_box, triangles_f4
    from viewer.accel.grid2 import SubSpec, TwoLevelGrid
    from viewer.backends.voxelwalk import VoxelWalker
    from viewer.cl import cl_context
    from viewer.cl import io as clio

    ctx = cl_context()
    grid = TwoLevelGrid(ctx, sub=SubSpec(min_small=1, big_frac=big, density=4.0))
    tb = clio.upload(ctx, triangles_f4(tris), what="test triangles")
    st = grid.build(tb, len(tris), *scene_box(tris), GridSpec(resolution=3))
    assert st.subgrids > 0 and (st.big > 0) == (big < 1.0)
    return ctx, grid, tb, VoxelWalker(ctx, grid, chunk=chunk, window=1, skip=skip, **kw)


@pytest.mark.parametrize("big,chunk,skip,kw", [(1e9, 64, "none", {}), (0.25, 16, "none", {}), (0.25, 64, "all", {}),
                                               (1e9, 64, "none", {"inline": 0}), (0.25, 64, "none", {"inline": 0}),
                                               (0.25, 32, "none", {"inline": 16, "tail": 100}),
                                               (0.25, 64, "none", {"inline": 4096})])
def test_ec_walks_the_sub_grids_bit_for_bit_as_ivw(reference, big, chunk, skip, kw):
    """The one-launch EC on a two-level grid sorts rays by sub-cell (and big list) and returns IVW's
    hits bit for bit, with IVW's per-ray iterations (non-empty top cells) and first cells; both
    match Embree. So it does with units of up to `inline` triangles tested in the walk (0: every
    unit sorted; 4096: none), and with partitions finishing their last rays alone (`tail`)."""
    from viewer.cl import HitStage, RayStage

    tris, (o, d, _, _), (t0, i0), _ = reference
    ctx, grid, tb, walker = _two_level_walker(tris, big, chunk, skip, **kw)
    n = len(o)
    size = (100, n // 100)
    rs, hs = RayStage(size, ctx), HitStage(size, ctx)
    rs.upload_arrays(np.c_[o, np.zeros(n, np.float32)], np.c_[d, np.full(n, 1e30, np.float32)])
    ivw = walker.trace_ivw(tb, rs.origin, rs.dir, hs.t, hs.tri, n, False, stats=True)
    t_ivw, id_ivw = hs.read()
    ec = walker.trace_ec(tb, rs.origin, rs.dir, hs.t, hs.tri, n, stats=True, size=size)
    t_ec, id_ec = hs.read()
    t_ivw, id_ivw, t_ec, id_ec = (np.asarray(a).reshape(-1)[:n] for a in (t_ivw, id_ivw, t_ec, id_ec))
    assert np.array_equal(t_ec.view(np.uint32), t_ivw.view(np.uint32)) and np.array_equal(id_ec, id_ivw)
    assert np.array_equal(ec.iters, ivw.iters) and np.array_equal(ec.first_cell, ivw.first_cell)
    assert ec.pairs >= int(ec.iters.sum())  # sub-cells and big lists: more units than top cells
    assert ec.pairs >= ec.sorted_pairs >= ec.sorted_rays and ec.rays >= ec.sorted_rays
    if kw.get("inline") == 0:  # every unit sorted, by every ray that walks
        assert ec.sorted_pairs == ec.pairs and 0 < ec.sorted_rays <= int((ec.iters > 0).sum())
    if kw.get("inline") == 4096:  # none sorted
        assert ec.sorted_pairs == 0 == ec.iterations
    hit = i0 >= 0
    assert ((id_ec >= 0) == hit).all()
    np.testing.assert_allclose(t_ec[hit], t0[hit], rtol=1e-5)
    for x in (rs, hs, walker, grid, tb):
        x.release()


@pytest.mark.parametrize("text", ["mode=fast", "chunk=48", "resolution=big", "resolution=0", "cells=-1",
                                  "density=-1", "colour=red", "sort=random", "primary=maybe",
                                  "skip=some", "levels=3", "inline=-1", "tail=-1"])
def test_bad_parameters_raise(text):
    from viewer.backends import check_params

    with pytest.raises(RtwalkError):
        check_params("voxelwalk", text)


def test_bad_parameters_cli_one_line():
    r = subprocess.run([sys.executable, "-m", "viewer.cli", "render", "room", "--backend", "voxelwalk",
                        "--backend-params", "mode=sideways", "-o", "/nonexistent/x.png"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and r.stderr.startswith("rtwalk: error:") and "mode" in r.stderr


# ----------------------------------------------------------------------------------------------
# statistics against independent computations
# ----------------------------------------------------------------------------------------------

def _walker(tris: np.ndarray, resolution: int, chunk: int = 64, skip: str = "none"):
    from viewer.accel.grid import GridSpec, UniformGrid, scene_box, triangles_f4
    from viewer.backends.voxelwalk import VoxelWalker
    from viewer.cl import cl_context

    ctx = cl_context()
    cl = ctx.cl
    grid = UniformGrid(ctx)
    tb = cl.Buffer(ctx.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=triangles_f4(tris))
    grid.build(tb, len(tris), *scene_box(tris), GridSpec(resolution=resolution))
    return ctx, grid, tb, VoxelWalker(ctx, grid, chunk=chunk, window=1, skip=skip)


def _dda_float64(header, cells, o, d, tmax):
    """Cells each ray's segment visits, in order, by a float64 3D-DDA (vectorised over rays):
    list of (ray, step, cell id) rows, plus per ray the smallest distance of its path to a cell
    boundary crossing corner (rays near corners may order ties differently)."""
    lo, cell, res = header["lo"][0, :3].astype(np.float64), header["cell"][0, :3].astype(np.float64), \
        header["res"][0, :3].astype(np.int64)
    hi = lo + cell * res
    o, d = o.astype(np.float64), d.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0, t1 = (lo - o) * inv, (hi - o) * inv
    tn = np.nanmax(np.where(np.isnan(np.minimum(t0, t1)), -np.inf, np.minimum(t0, t1)), axis=1)
    tf = np.nanmin(np.where(np.isnan(np.maximum(t0, t1)), np.inf, np.maximum(t0, t1)), axis=1)
    enter = np.maximum(tn, 0.0)
    alive = enter < np.minimum(tf, tmax)
    enter = np.where(alive, enter, 0.0)
    p = o + enter[:, None] * d
    c = np.clip(np.floor((p - lo) / cell), 0, res - 1).astype(np.int64)
    step = np.sign(d).astype(np.int64)
    rows = []
    for k in range(int(res.sum()) + 3):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        cid = c[idx, 0] + res[0] * (c[idx, 1] + res[1] * c[idx, 2])
        rows.append(np.stack([idx, np.full(len(idx), k), cid], 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            plane = lo + (c + (step > 0)) * cell
            tnext = np.where(step != 0, (plane - o) * inv, np.inf)
        ax = np.argmin(tnext, axis=1)
        tstep = tnext[np.arange(len(c)), ax]
        c[np.arange(len(c)), ax] += step[np.arange(len(c)), ax]
        inside = ((c >= 0) & (c < res)).all(1)
        alive &= inside & (tstep < np.minimum(tf, tmax))
    return np.concatenate(rows) if rows else np.zeros((0, 3), np.int64)


@pytest.mark.parametrize("resolution,skip", [(12, "all"), (64, "all"), (64, "none")])
def test_first_cells_and_iterations_match_a_float64_walk(resolution, skip):
    """IVW and the one-launch EC with skip=all skip empty 8^3 blocks (walk.cl); the global-sort EC
    walks cell by cell: all three visit the same non-empty cells, and the first ones are the
    float64 walk's."""
    from viewer.backends.voxelwalk import VoxelWalker

    tris = _scene()
    ctx, grid, tb, walker = _walker(tris, resolution=resolution, skip=skip)
    from viewer.cl import HitStage, RayStage

    n = 4096
    o, d, _, _ = _rays(n, seed=7)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    size = (64, 64)
    rs, hs = RayStage(size, ctx), HitStage(size, ctx)
    o4 = np.concatenate([o, np.zeros((n, 1), np.float32)], 1)
    d4 = np.concatenate([d, np.full((n, 1), 1e30, np.float32)], 1)
    rs.upload_arrays(o4, d4)
    ivw = walker.trace_ivw(tb, rs.origin, rs.dir, hs.t, hs.tri, n, False, stats=True)
    t_ivw, id_ivw = hs.read()
    ec = walker.trace_ec(tb, rs.origin, rs.dir, hs.t, hs.tri, n, stats=True, size=size)
    t_ec, id_ec = hs.read()
    glob = VoxelWalker(ctx, grid, chunk=64, window=1, ec_sort="global")
    ecg = glob.trace_ec(tb, rs.origin, rs.dir, hs.t, hs.tri, n, stats=True, size=size)
    t_g, id_g = hs.read()
    glob.release()
    assert np.array_equal(ivw.iters, ecg.iters) and np.array_equal(ivw.first_cell, ecg.first_cell)
    assert np.array_equal(t_g, t_ivw) and ((id_g == id_ivw) | (id_g >= 0)).all()
    # same hits, and the same walk: per ray the same iterations and the same first non-empty cell
    assert np.array_equal(t_ivw, t_ec) and np.array_equal(id_ivw, id_ec)
    assert np.array_equal(ivw.iters, ec.iters)
    assert np.array_equal(ivw.first_cell, ec.first_cell)
    # first non-empty cell against the float64 walk (rays passing near a cell corner excepted)
    header, cells, _ = grid.to_numpy()
    rows = _dda_float64(header, cells, o, d, np.full(n, np.inf))
    nonempty = cells[rows[:, 2], 1] > 0
    r = rows[nonempty]
    first = np.full(n, 0xFFFFFFFF, np.uint32)
    order = np.lexsort((r[:, 1], r[:, 0]))
    r = r[order]
    keep = np.ones(len(r), bool)
    keep[1:] = r[1:, 0] != r[:-1, 0]
    first[r[keep, 0]] = r[keep, 2]
    agree = (first == ivw.first_cell).mean()
    assert agree > 0.995, agree
    # resolved per iteration: per EC iteration the rays dropped equal the per-ray counts
    frac = ec.resolved_fraction()
    resolved = [row["resolved"] for row in ec.per_iter]
    with_cell = int((ec.iters > 0).sum())
    assert sum(resolved) == ec.per_iter[0]["active"] >= with_cell
    assert abs(frac.sum() * ec.rays - with_cell) < 0.5
    # rays per cell at the first iteration: every ray with a first cell, once
    assert ec.rays_per_cell.sum() == with_cell == ec.per_iter[0]["pairs"]
    assert ec.pairs == int(ec.iters.sum())
    rs.release()
    hs.release()
    walker.release()
    grid.release()
    tb.release()


def test_tile_divergence_brute_force():
    from viewer.backends.voxelwalk import tile_divergence

    rng = np.random.default_rng(2)
    w, h = 37, 21
    cells = rng.integers(0, 6, w * h).astype(np.uint32)
    cells[rng.random(w * h) < 0.2] = 0xFFFFFFFF
    per_pixel, per_tile = tile_divergence(cells, (w, h))
    expect = {}
    for i, c in enumerate(cells):
        key = ((i % w) // 8, (i // w) // 8)
        expect.setdefault(key, set())
        if c != 0xFFFFFFFF:
            expect[key].add(int(c))
    for i in range(w * h):
        assert per_pixel[i] == len(expect[((i % w) // 8, (i // w) // 8)])
    assert sorted(per_tile) == sorted(len(s) for s in expect.values() if s)


@pytest.mark.parametrize("view", ["tile_divergence", "iterations"])
def test_render_view_overlays(tmp_path, view):
    from PIL import Image

    out = tmp_path / f"{view}.png"
    r = subprocess.run([sys.executable, "-m", "viewer.cli", "render", "room", "--backend", "voxelwalk",
                        "--effects", "reflections", "--mirror", "*", "--size", "160x90", "--view", view,
                        "-o", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    img = np.asarray(Image.open(out).convert("RGB"), np.int32)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 4  # a heat map, not one flat colour


def test_counters_per_ray_type_agree_between_modes(gl_ctx):
    """The room with every material a mirror: IVW and EC walk the same cells, so their statistics
    per ray type agree; the grid figures are reported once per frame (the renderer sums passes)."""
    from dataclasses import replace

    from tests.conftest import prepared_scene
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer

    ps = prepared_scene("room")
    scene = replace(ps.scene, materials=[replace(m, mirror=True) for m in ps.scene.materials])
    got = {}
    for mode in ("ec", "ivw"):
        r = Renderer(gl_ctx, scene, ps.bvh, (96, 64), "voxelwalk", parse_effects("shadows,reflections"),
                     backend_options={"voxelwalk": f"mode={mode},stats=true"})
        r.render(scene.default_camera)
        got[mode] = r.render(scene.default_camera).backend_stats
        res = r.backend.resolution
        r.release()
    ec, ivw = got["ec"], got["ivw"]
    assert (ec["res_x"], ec["res_y"], ec["res_z"]) == tuple(float(x) for x in res)
    assert ec["grid_build_ms"] == 0.0  # no rebuild on the second frame
    for key in ("iterations_mean_reflections", "rays_per_cell_reflections", "resolved_first_pct_reflections",
                "tile_divergence_reflections", "tile_divergence_shadows"):
        assert ec[key] == pytest.approx(ivw[key]), key
    assert ec["pairs"] > 0 and ec["workgroups"] > 0 and "pairs" not in ivw
    assert 1.0 <= ec["tile_divergence_reflections"] <= 64.0


def test_bench_voxelwalk_end_to_end(tmp_path):
    """The study on the room: tables, JSON and plots written; IVW and EC agree with clbvh on the rays."""
    import json

    r = subprocess.run([sys.executable, "-m", "viewer.cli", "bench-voxelwalk", "--scenes", "room", "--sizes", "96x54",
                        "--repeats", "1", "--resolutions", "8,16", "--out", str(tmp_path), "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    for study in ("table51", "iterations", "resolution"):
        for ext in ("json", "md", "png"):
            assert (tmp_path / f"{study}.{ext}").stat().st_size > 100, (study, ext)
    rows = json.loads((tmp_path / "table51.json").read_text())["rows"]
    (row,) = rows
    assert row["reflection_rays"] > 0 and row["agreement"] == {"ivw": 1.0, "ec": 1.0, "ec_global": 1.0, "ec_all": 1.0}
    w = row["walk"]
    assert w["pairs"] >= w["rays"] > 0 and w["workgroups"] >= len(w["rays_per_cell"]) > 0
    assert abs(sum(w["resolved"]) - 1.0) < 1e-9  # every active reflection ray resolved at some iteration
    pts = json.loads((tmp_path / "resolution.json").read_text())["scenes"][0]["points"]
    assert [p["resolution"] for p in pts][:2] == [8, 16] and sum(p["auto"] for p in pts) == 1


def test_bench_voxelwalk_bad_sizes_is_one_line():
    rb = run_cli("bench-voxelwalk", "--sizes", "big")
    err = rb.stderr.strip().splitlines()
    assert rb.returncode == 2 and len(err) == 1 and err[0].startswith("rtwalk: error: ") and "--sizes" in err[0]


def test_tile_order_is_a_permutation_of_square_tiles():
    """The one-launch EC's ray order: every ray once, pixels grouped in tiles of p (32x32 for 1024;
    16x32 for 512), rays past the image last; partitions fit half the device's local memory."""
    from viewer.backends.voxelwalk.engine import tile_order, tile_partition

    w, h, n = 100, 70, 7100
    order = tile_order((w, h), n, 1024)
    assert np.array_equal(np.sort(order), np.arange(n))
    assert np.array_equal(order[w * h:], np.arange(w * h, n))
    first = order[:1024].astype(np.int64)  # the first full tile
    assert set(first % w) == set(range(32)) and set(first // w) == set(range(32))
    second = tile_order((w, h), w * h, 512)[:512].astype(np.int64)
    assert set(second % w) == set(range(32)) and set(second // w) == set(range(16))
    assert tile_partition(512 * 1024, 64) == 1024
    assert tile_partition(48 * 1024, 64) == 128  # a 48 KiB GPU: 72 B x 128 + 172 B x 64 <= 24 KiB
    assert tile_partition(1024, 256) == 256  # never below one ray per work-item

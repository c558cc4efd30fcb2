"""The `voxels` backend (approximate by design, so not in the exact registry-driven tests): its
parameters, and its hits on the renderer's own rays against Embree: primary hits land on the
voxel surface in front of the true hit, the image error shrinks with the resolution, and the
three structures return the same voxels."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import opencl_missing
from viewer.backends import backend_info, check_params
from viewer.errors import RtwalkError

pytestmark = pytest.mark.skipif(opencl_missing() is not None, reason=opencl_missing() or "")

SIZE = (160, 90)


def test_info_and_params():
    info = backend_info("voxels")
    assert info.exact is False and info.device == "cl"
    assert check_params("voxels", "structure=kd,resolution=64,stack=4") == \
        "structure=kd,resolution=64,stack=4,bias=1.5,leave=False,gap=0.5"
    for bad, msg in (("structure=grid", "structure must be"), ("resolution=100", "power of two"),
                     ("stack=0", "stack must be"), ("bias=-1", "bias"), ("gap=-1", "gap")):
        with pytest.raises(RtwalkError, match=msg):
            check_params("voxels", bad)


@pytest.fixture(scope="module")
def renders(gl_ctx):
    from tests.conftest import prepared_scene
    from viewer.effects import parse_effects
    from viewer.renderer import Renderer

    prep = prepared_scene("room")
    out = {}
    for backend, params in (("embree", ""), ("voxels", "resolution=32"), ("voxels", "resolution=128")):
        r = Renderer(gl_ctx, prep.scene, prep.bvh, SIZE, backend, parse_effects("primary,shadows,ao:1"),
                     backend_options={backend: params})
        try:
            rep = r.render(prep.scene.default_camera, capture=True)
            out[(backend, params)] = (r.read_image().astype(np.float64), rep.captured)
        finally:
            r.release()
    return prep, out


def test_primary_hits_and_image_error(renders):
    from viewer.reference import EmbreeTracer

    prep, out = renders
    emb = EmbreeTracer(prep.scene.triangles)
    ref_img = out[("embree", "")][0]
    errors, within = {}, {}
    for res in (32, 128):
        img, captured = out[("voxels", f"resolution={res}")]
        errors[res] = float(np.abs(img - ref_img).mean())
        cp = next(c for c in captured if c.ray_type.label == "primary")
        act = cp.rays.active
        o, d = cp.rays.origins[act], cp.rays.directions[act]
        t_ref, id_ref = emb.trace(o, d, cp.rays.tmin[act], cp.rays.tmax[act])
        hv, hr = cp.tri[act] >= 0, id_ref >= 0
        assert (hr & ~hv).mean() < 0.002  # a closed-ish surface is not missed
        both = hv & hr
        # mostly the voxel holding the true hit point (or one before it) is met first; six-separating
        # sets leave out slivers of triangles near their edges (conservative ones would not), so a
        # ray may go on to the next voxel, but never by more than a voxel diagonal
        voxel = 1.0 / vox_scale(prep, res)
        early = cp.t[act][both] <= t_ref[both] + 1e-4 * prep.scene.diagonal
        assert early.mean() > 0.98
        assert np.all(cp.t[act][both] <= t_ref[both] + np.sqrt(3) * voxel)
        assert np.all(cp.tri[act][hv] < len(prep.scene.triangles))
        # how far before the true surface, measured along its normal: within the voxel layer around it
        tri = prep.scene.triangles[id_ref[both]].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        cos = np.abs(np.einsum("ij,ij->i", n, d[both])) / np.linalg.norm(n, axis=1)
        ahead = (t_ref[both] - cp.t[act][both]) * cos
        # (rays passing within a voxel of another object's silhouette meet that object: fewer at finer grids)
        within[res] = float(np.mean(ahead < np.sqrt(3) * voxel))
    assert within[32] > 0.8 and within[128] > 0.95 and within[128] > within[32]
    assert errors[128] < errors[32]


def vox_scale(prep, res: int) -> float:
    from viewer.backends.voxels import voxels_for

    return voxels_for(prep.scene.triangles, res, quiet=True).grid.scale


@pytest.mark.parametrize("stack", [4, 8])
def test_structures_agree_on_renderer_rays(renders, stack):
    from viewer.backends.voxels import voxels_for
    from viewer.backends.voxels.scene import VoxelTracer, build_structure

    prep, out = renders
    _, captured = out[("voxels", "resolution=128")]
    vox = voxels_for(prep.scene.triangles, 128, quiet=True)
    g = vox.grid
    results = {}
    for cp in captured:
        act = cp.rays.active
        o4 = np.concatenate([cp.rays.origins[act], cp.rays.tmin[act, None]], axis=1)
        d4 = np.concatenate([cp.rays.directions[act], cp.rays.tmax[act, None]], axis=1)
        for kind in ("bvh", "kd", "octree"):
            tr = VoxelTracer(build_structure(kind, vox), g.origin, g.scale, stack)
            res = tr.trace_arrays(o4, d4, any_hit=cp.ray_type.any_hit, bias=0.0)
            results.setdefault(cp.ray_type.label, {})[kind] = res
            tr.release()
    for label, by in results.items():
        if label == "primary":
            for kind in ("kd", "octree"):
                assert np.mean(by[kind].tri == by["bvh"].tri) > 0.999, (label, kind)
                both = by[kind].tri >= 0
                np.testing.assert_allclose(by[kind].t[both], by["bvh"].t[both], rtol=1e-5)
        else:  # any hit: occluded or not
            for kind in ("kd", "octree"):
                assert np.mean((by[kind].tri >= 0) == (by["bvh"].tri >= 0)) > 0.999, (label, kind)

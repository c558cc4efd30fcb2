"""The one table of SSBO, image and fixed texture binding points, for Python and GLSL alike.

Python binds with these constants; every shader gets them as `#define BIND_...` (shader_header(),
injected by viewer.gl.programs after #version) and writes `layout(std430, binding = BIND_NODES)`
instead of a number, so a binding point is decided here once. SSBO and image units are separate
GL namespaces: numbers may repeat between the two tables, never within one.

A backend that needs binding points of its own declares them beside its code (a module constant)
and gets them checked against this table with `backend_bindings`; its programs receive them as
`#define`s, so generic code never names them. The numbers this table leaves free are the
backends' (BACKEND_SSBO, BACKEND_IMAGE).
"""

from __future__ import annotations

# shader storage buffers
SSBO: dict[str, int] = {
    "BIND_NODES": 0,  # BVH nodes (scene.glsl)
    "BIND_TRIS": 1,  # leaf-ordered triangles (scene.glsl)
    "BIND_MATERIALS": 2,  # albedo table (scene.glsl)
    "BIND_COUNTERS": 3,  # ray counters of ray generation (raygen.frag)
    "BIND_WORK": 9,  # shader work counters (RTWALK_COUNT_WORK=1, intersect.glsl)
    "BIND_RESUME_COUNTERS": 10,  # glsl resumable traversal: unfinished rays, slots allocated
    "BIND_RESUME_STATE": 11,  # glsl resumable traversal: saved traversal states
    "BIND_MICRO": 15,  # the GL micro-benchmark's per-instance counts
    "BIND_CULL_NODES": 16,  # G-buffer occlusion culling: the cut's boxes and slot ranges
    "BIND_CULL_VISIBLE": 17,  # G-buffer occlusion culling: visible last frame, per cut node
    "BIND_CULL_CMDS": 18,  # G-buffer occlusion culling: the indirect draw commands written
    "BIND_CULL_STATS": 19,  # G-buffer occlusion culling: triangles and nodes drawn per phase
    "BIND_TRACE_HITS": 36,  # glsl traversal, compute stage: hits per pixel before the resolve draw
    "BIND_STAGE_PROBE": 37,  # the fragment-or-compute probe's output (viewer/gl/stages.py)
}

# image units (imageLoad/imageStore/imageAtomic*)
IMAGE: dict[str, int] = {
    "BIND_IMG_RESUME": 4,  # glsl resumable traversal: resume slot per pixel (-1 finished)
    "BIND_IMG_HIZ": 5,  # G-buffer occlusion culling: the level of the distance pyramid written
    "BIND_IMG_WORK_NODES": 6,  # shader work counters per pixel: BVH nodes (RTWALK_COUNT_WORK=1, intersect.glsl)
    "BIND_IMG_WORK_TRIS": 7,  # shader work counters per pixel: triangle tests
}

# texture units bound for the whole frame (buffer textures: viewer.gl.textures.TexelView; shaders
# write `layout(binding = BIND_TEX_NODES) uniform usamplerBuffer ...`). Units below 16 are the
# passes' and backends' own (moderngl `texture.use(n)`); moderngl keeps the last unit for itself.
TEXTURE: dict[str, int] = {
    "BIND_TEX_NODES": 28,  # BVH nodes, 4 texels a node (scene.glsl loadNode, SCENE_TEXELS)
    "BIND_TEX_TRIS": 29,  # leaf-ordered triangles, 3 texels a triangle (scene.glsl loadTri, SCENE_TEXELS)
}

BIND_NODES = SSBO["BIND_NODES"]
BIND_TRIS = SSBO["BIND_TRIS"]
BIND_MATERIALS = SSBO["BIND_MATERIALS"]
BIND_COUNTERS = SSBO["BIND_COUNTERS"]
BIND_WORK = SSBO["BIND_WORK"]
BIND_MICRO = SSBO["BIND_MICRO"]
BIND_RESUME_COUNTERS = SSBO["BIND_RESUME_COUNTERS"]
BIND_RESUME_STATE = SSBO["BIND_RESUME_STATE"]
BIND_IMG_RESUME = IMAGE["BIND_IMG_RESUME"]
BIND_TRACE_HITS = SSBO["BIND_TRACE_HITS"]
BIND_STAGE_PROBE = SSBO["BIND_STAGE_PROBE"]
BIND_CULL_NODES = SSBO["BIND_CULL_NODES"]
BIND_CULL_VISIBLE = SSBO["BIND_CULL_VISIBLE"]
BIND_CULL_CMDS = SSBO["BIND_CULL_CMDS"]
BIND_CULL_STATS = SSBO["BIND_CULL_STATS"]
BIND_IMG_HIZ = IMAGE["BIND_IMG_HIZ"]
BIND_IMG_WORK_NODES = IMAGE["BIND_IMG_WORK_NODES"]
BIND_IMG_WORK_TRIS = IMAGE["BIND_IMG_WORK_TRIS"]
BIND_TEX_NODES = TEXTURE["BIND_TEX_NODES"]
BIND_TEX_TRIS = TEXTURE["BIND_TEX_TRIS"]

# SSBO binding points left to backends' own names (GL 4.5 drivers offer 80 or more: llvmpipe 80, NVIDIA 96)
BACKEND_SSBO = (*range(4, 9), *range(12, 15), *range(20, 36))
BACKEND_IMAGE = range(0, 4)  # image units left to backends' own names


def backend_bindings(ssbo: dict[str, int], image: dict[str, int]) -> dict[str, int]:
    """A backend's own binding points, checked (BIND_ names, unique, in the ranges this table leaves
    free, no name of this table); returns them as `#define`s for its programs."""
    for table, free in ((ssbo, BACKEND_SSBO), (image, BACKEND_IMAGE)):
        assert len(set(table.values())) == len(table), table
        for k, v in table.items():
            assert k.startswith("BIND_") and k not in SSBO and k not in IMAGE and k not in TEXTURE and v in free, (k, v)
    assert not set(ssbo) & set(image)
    return {**ssbo, **image}


def shader_header() -> str:
    """`#define BIND_... N` lines for every binding point (inserted after #version)."""
    return "".join(f"#define {k} {v}\n" for k, v in {**SSBO, **IMAGE, **TEXTURE}.items())

"""The one table of SSBO and image binding points, for Python and GLSL alike.

Python binds with these constants; every shader gets them as `#define BIND_...` (shader_header(),
injected by viewer.gl.programs after #version) and writes `layout(std430, binding = BIND_NODES)`
instead of a number, so a binding point is decided here once. SSBO and image units are separate
GL namespaces: numbers may repeat between the two tables, never within one.
"""

from __future__ import annotations

# shader storage buffers
SSBO: dict[str, int] = {
    "BIND_NODES": 0,  # BVH nodes (scene.glsl)
    "BIND_TRIS": 1,  # leaf-ordered triangles (scene.glsl)
    "BIND_MATERIALS": 2,  # albedo table (scene.glsl)
    "BIND_COUNTERS": 3,  # ray counters of ray generation (raygen.frag)
    "BIND_CHC_ITEMS": 5,  # chcrt: (tile, node) items of a batch draw
    "BIND_CHC_COUNT": 6,  # chcrt: active ray count
    "BIND_CHC_DRAWS": 7,  # chcrt: per-instance tile draws
    "BIND_CHC_QUERY_COUNTS": 8,  # chcrt: per-query passed-fragment counts
    "BIND_WORK": 9,  # shader work counters (RTWALK_COUNT_WORK=1, intersect.glsl)
    "BIND_RESUME_COUNTERS": 10,  # glsl resumable traversal: unfinished rays, slots allocated
    "BIND_RESUME_STATE": 11,  # glsl resumable traversal: saved traversal states
    "BIND_MICRO": 15,  # the GL micro-benchmark's per-instance counts
}

# image units (imageLoad/imageStore/imageAtomic*)
IMAGE: dict[str, int] = {
    "BIND_IMG_CHC_BEST": 0,  # chcrt: packed closest hit per pixel
    "BIND_IMG_CHC_OVERDRAW": 1,  # chcrt: query fragments per pixel (overlay)
    "BIND_IMG_CHC_BATCH": 2,  # chcrt: subtrees in the pixel's batches (overlay)
    "BIND_IMG_RESUME": 4,  # glsl resumable traversal: resume slot per pixel (-1 finished)
}

BIND_NODES = SSBO["BIND_NODES"]
BIND_TRIS = SSBO["BIND_TRIS"]
BIND_MATERIALS = SSBO["BIND_MATERIALS"]
BIND_COUNTERS = SSBO["BIND_COUNTERS"]
BIND_CHC_ITEMS = SSBO["BIND_CHC_ITEMS"]
BIND_CHC_COUNT = SSBO["BIND_CHC_COUNT"]
BIND_CHC_DRAWS = SSBO["BIND_CHC_DRAWS"]
BIND_CHC_QUERY_COUNTS = SSBO["BIND_CHC_QUERY_COUNTS"]
BIND_WORK = SSBO["BIND_WORK"]
BIND_MICRO = SSBO["BIND_MICRO"]
BIND_IMG_CHC_BEST = IMAGE["BIND_IMG_CHC_BEST"]
BIND_IMG_CHC_OVERDRAW = IMAGE["BIND_IMG_CHC_OVERDRAW"]
BIND_IMG_CHC_BATCH = IMAGE["BIND_IMG_CHC_BATCH"]
BIND_RESUME_COUNTERS = SSBO["BIND_RESUME_COUNTERS"]
BIND_RESUME_STATE = SSBO["BIND_RESUME_STATE"]
BIND_IMG_RESUME = IMAGE["BIND_IMG_RESUME"]


def shader_header() -> str:
    """`#define BIND_... N` lines for every binding point (inserted after #version)."""
    return "".join(f"#define {k} {v}\n" for k, v in {**SSBO, **IMAGE}.items())

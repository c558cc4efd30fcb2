"""View-frustum culling of the G-buffer raster by BVH subtrees.

The raster's vertices are the leaf-ordered triangles, so every BVH subtree is one contiguous range
of triangle slots ([node_first, node_first + node_count)). A fixed cut of the tree (`bvh_cut`:
the highest nodes holding at most ~N / target triangles, plus the larger leaves) partitions the
slots into a few thousand ranges (more in scenes over 1 M triangles: `cut_target`); each frame
one vectorised NumPy pass tests the cut's boxes against the four side planes of the view pyramid
(`visible_ranges`), adjacent visible ranges are merged, and the G-buffer draws them with ONE
multi-draw-indirect call. No Python loop per node or per triangle.

Conservative by construction: a box is dropped only when it lies wholly outside a side plane by
more than the rounding of the shaders' float32 camera (apex moved by a few ulps of its position,
directions by ~1e-7, the pyramid widened by WIDEN); every pixel-centre ray lies inside the pyramid
(the outermost centres are half a pixel inside the image edge), and a pyramid through the apex
with four inward side planes holds only points in front of the camera, so boxes behind the
camera are dropped too. Triangles dropped can produce no fragment: the G-buffer is unchanged
(tests/test_gbuffer_cull.py compares it id for id with the unculled raster).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from viewer.accel.bvh import BVH
from viewer.camera import Camera

CUT_NODES = 4096  # at least about this many subtrees in the cut (a ~0.1 ms NumPy pass per frame)
TRIANGLES_PER_CUT_NODE = 256  # larger scenes get a finer cut, about this many triangles a subtree,
MAX_CUT_NODES = 65536  # up to this many subtrees (city 10 M: occlusion-culled raster 0.30 -> 0.21 s at
# 320x180 and 0.52 -> 0.42 s at 1280x720, 4096 vs 39,062, medians of 11 frames of city-near)


def cut_target(triangles: int) -> int:
    """Subtrees wanted in the cut of a scene: CUT_NODES, finer for scenes over 1 M triangles (a
    subtree of thousands of triangles is drawn whole when a corner of it shows)."""
    return int(min(max(CUT_NODES, triangles // TRIANGLES_PER_CUT_NODE), MAX_CUT_NODES))
WIDEN = 1e-4  # relative widening of the pyramid's half-angle tangents (float32 camera uniforms)


@dataclass
class Cut:
    """Subtrees partitioning the triangle slots, sorted by first slot."""

    nodes: np.ndarray  # int64 (K,) node indices into the BVH arrays
    first: np.ndarray  # int64 (K,) first triangle slot
    count: np.ndarray  # int64 (K,) triangles


def bvh_cut(bvh: BVH, target: int = CUT_NODES) -> Cut:
    """The nodes holding at most T = ceil(N / target) triangles whose parent holds more (the root
    when N <= T), plus the leaves larger than T: disjoint, covering every slot once. Found from
    the nodes holding more than T (their small children, their leaves), so only one comparison
    touches every node: at 10 M triangles a whole-tree parent gather took 0.5 s of the first frame."""
    count = bvh.node_count
    n = int(count[0]) if count.size else 0
    limit = max(1, -(-n // max(int(target), 1)))
    big = np.flatnonzero(count > limit)  # a parent's count is at least its children's: a subtree
    if big.size == 0:
        nodes = np.zeros(1 if n > 0 else 0, np.int64)  # the root alone
    else:
        inner = bvh.node_left[big] >= 0
        kids = np.concatenate([bvh.node_left[big[inner]], bvh.node_right[big[inner]]]).astype(np.int64)
        nodes = np.concatenate([kids[count[kids] <= limit], big[~inner]])
        nodes = nodes[count[nodes] > 0]
    first = bvh.node_first[nodes].astype(np.int64)
    order = np.argsort(first, kind="stable")
    return Cut(nodes[order], first[order], count[nodes][order].astype(np.int64))


def frustum_planes(camera: Camera, aspect: float, widen: float = WIDEN) -> np.ndarray:
    """(4, 3) float64 inward unit normals of the view pyramid's side planes through the camera:
    a point p is inside when n . (p - eye) >= 0 for all four."""
    t = float(np.tan(np.radians(camera.fov_y) / 2))
    tx, ty = t * aspect * (1 + widen), t * (1 + widen)
    # camera space: right, up, forward (= -z); inside when |x| <= tx * depth and |y| <= ty * depth
    cam = np.array([[-1.0, 0.0, tx], [1.0, 0.0, tx], [0.0, -1.0, ty], [0.0, 1.0, ty]])
    r = camera.rotation
    basis = np.stack([r[:, 0], r[:, 1], -r[:, 2]])  # rows: right, up, forward in world space
    n = cam @ basis
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def visible_ranges(cut: Cut, node_min: np.ndarray, node_max: np.ndarray, camera: Camera,
                   aspect: float) -> np.ndarray:
    """int64 (R, 2) [first slot, count] of the cut's subtrees that may be seen, adjacent ones merged."""
    if cut.nodes.size == 0:
        return np.zeros((0, 2), np.int64)
    eye = np.asarray(camera.position, np.float64)
    lo = node_min[cut.nodes].astype(np.float64) - eye  # (K, 3), camera-relative
    hi = node_max[cut.nodes].astype(np.float64) - eye
    planes = frustum_planes(camera, aspect)  # (4, 3)
    # the box corner farthest along each plane's normal, and its signed distance
    far = np.where(planes[None, :, :] >= 0, hi[:, None, :], lo[:, None, :])  # (K, 4, 3)
    dist = np.einsum("kpj,pj->kp", far, planes)
    # rounding of the float32 camera: the apex (a few ulps of the position) and the directions
    extent = np.abs(far).max(axis=2)
    tol = 4.0 * float(np.spacing(np.float32(np.abs(eye).max()))) + 1e-6 * extent
    keep = (dist >= -tol).all(axis=1)
    first, count = cut.first[keep], cut.count[keep]
    if first.size == 0:
        return np.zeros((0, 2), np.int64)
    end = first + count
    starts = np.concatenate([[True], first[1:] != end[:-1]])  # a gap: a new range begins
    idx = np.flatnonzero(starts)
    merged_first = first[idx]
    merged_end = end[np.concatenate([idx[1:] - 1, [first.size - 1]])]
    return np.stack([merged_first, merged_end - merged_first], axis=1)


def indirect_commands(ranges: np.ndarray) -> np.ndarray:
    """uint32 (R, 5): DrawArraysIndirectCommand {count, instanceCount, first, baseInstance} of the
    ranges' vertices (3 per triangle) plus a padding word: moderngl's render_indirect steps 20 bytes
    per command for non-indexed draws too (tests/test_gbuffer_cull.py would show a wrong stride)."""
    cmd = np.zeros((len(ranges), 5), np.uint32)
    cmd[:, 0] = ranges[:, 1] * 3
    cmd[:, 1] = 1
    cmd[:, 2] = ranges[:, 0] * 3
    return cmd

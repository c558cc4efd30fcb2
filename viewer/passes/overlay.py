"""Backend overlays shown live: CHC+RT query overdraw (heat map) and subtree batches.

A backend's overlay textures (TraceResult.overlays) are overwritten by its next trace() call, and
a frame has many passes, so the renderer copies the overlays of one chosen pass into this pass's
capture texture right after that pass is traced: one full-screen draw on the GPU, no readback.
The views are then drawn from the capture in place of the final image.

Capture layout (RGBA32I, row 0 = bottom; shaders/overlay.glsl): r = query fragments drawn at the
pixel, g = canonical BVH node of the subtree that produced the hit (-1 none), b = subtrees in the
batches of the pixel's tile (-1 when the backend does not report it), a = flags (FLAG_RAY, FLAG_HIT).

The heat map's scale maximum comes from the frame itself: a max-reduction on the GPU (render to
texture, 16x16 per step) that the view shader reads directly, rounded up to 1-2-5 steps so that the
colours of a walkthrough do not flicker. The CPU only reads that 1x1 result (8 bytes) for the
legend's labels, after the frame's glFinish, and only while the view is on. A fixed scale can be
set instead (compare frames). The NumPy functions below mirror the shader (legend, tests).
"""

from __future__ import annotations

from functools import lru_cache

import moderngl
import numpy as np

from viewer.gpu import FullscreenQuad, ProgramCache, read_texture
from viewer.passes.targets import SizedTargets
from viewer.rays import HitBuffer, RayBatch

# view name -> overlays (TraceResult.overlays keys) it needs from the backend
OVERLAY_VIEWS: dict[str, tuple[str, ...]] = {"query_overdraw": ("query_overdraw",),
                                             "subtree_batches": ("subtree_id",)}
OVERLAY_NAMES = ("query_overdraw", "subtree_id", "batch_subtrees")  # capture channels r, g, b
FLAG_RAY = 1
FLAG_HIT = 2
NO_DATA_GREY = 46  # uint8 grey of pixels without data (OVERLAY_NO_DATA in overlay.glsl)
REDUCE_BLOCK = 16  # BLOCK in overlay_reduce.frag


# --------------------------------------------------------------------------- NumPy mirrors


@lru_cache(maxsize=1)
def heat_lut() -> np.ndarray:
    """uint8 (256, 3): the heat map's colormap (matplotlib's inferno; lightness increases)."""
    from matplotlib import colormaps

    return np.ascontiguousarray(colormaps["inferno"](np.linspace(0.0, 1.0, 256), bytes=True)[:, :3])


def nice_ceil(n: int) -> int:
    """Smallest of 1, 2, 5, 10, 20, 50, ... >= n (overlayNiceCeil)."""
    d = 1
    for _ in range(9):
        for m in (1, 2, 5):
            if n <= m * d:
                return m * d
        d *= 10
    return int(n)


def heat_position(v, vmax: int, log: bool = True) -> np.ndarray:
    """Position of v on the heat scale [0, vmax] in [0, 1] (overlayHeatPos, float32 like GLSL)."""
    x = np.maximum(np.asarray(v, np.float32), np.float32(0))
    m = np.float32(max(int(vmax), 1))
    one = np.float32(1)
    p = np.log2(one + x) / np.log2(one + m) if log else x / m
    return np.clip(p, 0.0, 1.0).astype(np.float32)


def heat_colors(v, vmax: int, log: bool = True) -> np.ndarray:
    """uint8 (..., 3) heat-map colours of the values v (overlayHeatColor)."""
    idx = np.floor(heat_position(v, vmax, log) * np.float32(255) + np.float32(0.5)).astype(np.int64)
    return heat_lut()[np.clip(idx, 0, 255)]


def heat_ticks(vmax: int, log: bool = True, most: int = 7) -> list[int]:
    """Legend ticks: 0, then 1-2-5 steps up to vmax (thinned to at most `most`), and vmax."""
    vmax = max(int(vmax), 1)
    steps, d = [], 1
    while d <= vmax:
        steps += [s for s in (d, 2 * d, 5 * d) if s <= vmax]
        d *= 10
    if not log:  # evenly spaced: the largest 1-2-5 step giving at most `most` intervals
        step = next((s for s in steps if vmax / s <= most - 1), vmax)
        return sorted(set(range(0, vmax + 1, step)) | {vmax})
    ticks = [0, *steps]
    while len(ticks) > most:  # keep 0 and vmax, drop every other one in between
        ticks = [ticks[0], *ticks[1:-1][1::2], ticks[-1]]
    return sorted(set(ticks) | {vmax})


def tile_index(size: tuple[int, int], level: int) -> np.ndarray:
    """int64 (H, W): finest CHC+RT tile (ty * 2^level + tx) of each pixel (overlayTileOf)."""
    w, h = size
    tx = (((np.arange(w, dtype=np.int64) + 1) << level) - 1) // w
    ty = (((np.arange(h, dtype=np.int64) + 1) << level) - 1) // h
    return ty[:, None] * (1 << level) + tx[None, :]


def tile_counts(overlay: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Per finest tile: (rects int64 (K, 4) x, y, w, h in pixels, counts (K,), what the counts are).

    `overlay` is the capture read back, (H, W, 4). With the backend's batch_subtrees overlay the
    count is the number of subtrees in the tile's intersection batches; without it, the number of
    distinct subtrees among the tile's hits (what the image can tell)."""
    from viewer.backends.chcrt_front import tile_rects

    h, w = overlay.shape[:2]
    n = 1 << level
    ty, tx = np.divmod(np.arange(n * n, dtype=np.int64), n)
    rects = tile_rects(np.full(n * n, level), tx, ty, (w, h))
    tiles = tile_index((w, h), level).reshape(-1)
    batch = overlay[..., 2].reshape(-1)
    if (batch >= 0).any():
        counts = np.zeros(n * n, np.int64)
        np.maximum.at(counts, tiles, np.maximum(batch, 0).astype(np.int64))
        return rects, counts, "subtrees in the tile's batches"
    sub = overlay[..., 1].reshape(-1).astype(np.int64)
    keep = sub >= 0
    keys = np.unique(tiles[keep] * (int(sub.max(initial=0)) + 1) + sub[keep])
    counts = np.bincount(keys // (int(sub.max(initial=0)) + 1), minlength=n * n)
    return rects, counts, "distinct subtrees hit in the tile"


# --------------------------------------------------------------------------- the pass


class OverlayPass(SizedTargets):
    """Capture of one pass's overlays, their max-reduction, and the overlay views."""

    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int]):
        self.ctx = ctx
        self.quad = quad
        self.copy_prog = programs.get("fullscreen.vert", "overlay_copy.frag")
        for i, name in enumerate(["srcOverdraw", "srcSubtree", "srcBatch", "rayOrigin", "rayDir", "hitId"]):
            self.copy_prog[name] = i
        self.reduce_prog = programs.get("fullscreen.vert", "overlay_reduce.frag")
        self.reduce_prog["src"] = 0
        self.view_prog = programs.get("fullscreen.vert", "overlay_view.frag")
        for i, name in enumerate(["overlay", "reduced", "lut"]):
            self.view_prog[name] = i
        lut = np.concatenate([heat_lut(), np.full((256, 1), 255, np.uint8)], axis=1)
        self.lut = ctx.texture((256, 1), 4, lut.tobytes(), dtype="f1")
        self.lut.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.captured: tuple[str, ...] = ()  # overlay names in the capture (empty: nothing this frame)
        self._reduced = False
        self.resize(size)

    def create_targets(self, size: tuple[int, int]) -> None:
        self.texture = self.ctx.texture(size, 4, dtype="i4")
        self.texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.fbo = self.ctx.framebuffer(color_attachments=[self.texture])
        self.steps: list[tuple[moderngl.Texture, moderngl.Framebuffer]] = []
        w, h = size
        while True:
            w, h = -(-w // REDUCE_BLOCK), -(-h // REDUCE_BLOCK)
            tex = self.ctx.texture((w, h), 2, dtype="i4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self.steps.append((tex, self.ctx.framebuffer(color_attachments=[tex])))
            if (w, h) == (1, 1):
                break
        self.captured = ()

    def release_targets(self) -> None:
        for tex, fbo in self.steps:
            fbo.release()
            tex.release()
        self.fbo.release()
        self.texture.release()

    def release(self) -> None:
        self.release_targets()
        self.lut.release()

    def begin_frame(self) -> None:
        self.captured = ()
        self._reduced = False

    def capture(self, overlays: dict[str, moderngl.Texture], rays: RayBatch, hits: HitBuffer) -> None:
        """Copy the backend's overlays of the pass just traced (plus its ray/hit flags)."""
        present = tuple(n for n in OVERLAY_NAMES if n in overlays)
        stand_in = overlays[present[0]] if present else hits.id  # integer texture on unused units
        p = self.copy_prog
        for i, name in enumerate(OVERLAY_NAMES):
            overlays.get(name, stand_in).use(i)
        p["hasOverdraw"], p["hasSubtree"], p["hasBatch"] = (int(n in overlays) for n in OVERLAY_NAMES)
        rays.origin.use(3)
        rays.direction.use(4)
        hits.id.use(5)
        self.fbo.use()
        self.fbo.scissor = None
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        self.quad.render(p)
        self.captured = present
        self._reduced = False

    def _reduce(self) -> None:
        if self._reduced:
            return
        p = self.reduce_prog
        src, first = self.texture, 1
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        for tex, fbo in self.steps:
            src.use(0)
            p["srcSize"] = src.size
            p["firstStep"] = first
            fbo.use()
            self.quad.render(p)
            src, first = tex, 0
        self._reduced = True

    def render_view(self, fbo: moderngl.Framebuffer, view: str, tile_level: int, fixed_max: int,
                    log: bool) -> None:
        """Draw `view` from the capture into `fbo` (the shade pass's image)."""
        self._reduce()
        p = self.view_prog
        self.texture.use(0)
        self.steps[-1][0].use(1)
        self.lut.use(2)
        p["mode"] = list(OVERLAY_VIEWS).index(view)
        p["fixedMax"] = int(max(fixed_max, 0))
        p["logScale"] = int(log)
        p["tileLevel"] = int(tile_level)
        fbo.use()
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        self.quad.render(p)

    def read_max(self) -> tuple[int, int]:
        """(max query fragments, max batch subtrees) over the capture: 8 bytes read back."""
        self._reduce()
        v = np.frombuffer(self.steps[-1][0].read(), np.int32)
        return int(v[0]), int(v[1])

    def read(self) -> np.ndarray:
        """The capture, int32 (H, W, 4), row 0 = bottom."""
        return read_texture(self.texture).copy()

"""Backend overlay views, driven by what the active backend declares (BackendInfo.overlays).

Every `OverlaySpec` of the backend is one view (`render --view NAME`, the window's View combo).
Its kind decides how it is captured and drawn, never its name:

* "heat": the spec's texture holds a count per pixel, drawn as a heat map with a legend
  (`OverlaySpec.label` is the legend's title) whose maximum comes from a max-reduction;
* "ids": the texture holds an id per pixel (-1 none), drawn in a colour per id with screen-tile
  outlines (the backend's `tile_level`); the optional `counts` texture holds a value per pixel that
  is printed once per tile (its maximum over the tile). The label reads "colour; numbers", e.g.
  "hit subtree; subtrees in the tile's batches" (`ids_labels`).

A backend's overlay textures are overwritten by its next trace() call, and a frame has many
passes, so the renderer copies the overlays of one chosen pass right after that pass is traced:
one full-screen draw per view into that view's capture texture (RGBA32I, layout in
shaders/overlay.glsl: r = value, g = counts, a = ray/hit flags), no readback. The views are then
drawn from the capture in place of the final image.

The heat map's scale maximum comes from the frame itself: a max-reduction on the GPU (render to
texture, 16x16 per step) that the view shader reads directly, rounded up to 1-2-5 steps so that the
colours of a walkthrough do not flicker. The CPU only reads that 1x1 result (8 bytes) for the
legend's labels, after the frame's glFinish, and only while the view is on. A fixed scale can be
set instead (compare frames). The NumPy functions below mirror the shader (legend, tests).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import moderngl
import numpy as np

from viewer.backends.interface import BackendInfo, OverlaySpec
from viewer.errors import RtwalkError
from viewer.gl import io as glio
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.textures import read_texture
from viewer.passes.shade import SHADE_MODES
from viewer.rays import HitBuffer, RayBatch
from viewer.screen_tiles import level_rects, tile_index

FLAG_RAY = 1
FLAG_HIT = 2
NO_DATA_GREY = 46  # uint8 grey of pixels without data (OVERLAY_NO_DATA in overlay.glsl)
REDUCE_BLOCK = 16  # BLOCK in overlay_reduce.frag
VIEW_SHADER_MODES = {"heat": 0, "ids": 1}  # OverlaySpec.kind -> `mode` of overlay_view.frag
CAPTURE_VALUE, CAPTURE_COUNTS, CAPTURE_FLAGS = 0, 1, 3  # channels of a capture texture


# --------------------------------------------------------------------------- views of a backend


def overlay_spec(info: BackendInfo, view: str) -> OverlaySpec | None:
    """The backend's overlay called `view` (None: not one of its overlays)."""
    return next((s for s in info.overlays if s.name == view), None)


def overlay_view_names(info: BackendInfo) -> list[str]:
    """The backend's overlay views, in its declared order."""
    return [s.name for s in info.overlays if s.name not in SHADE_MODES]


def view_names(info: BackendInfo) -> list[str]:
    """Every view `render --view` / the window offers with this backend: the shade pass's views
    ('final', 'albedo', ..., one pass alone), then the backend's overlay views."""
    return list(SHADE_MODES) + overlay_view_names(info)


def cycled_views(info: BackendInfo) -> list[str]:
    """The window's V key: 'final', then the backend's overlay views."""
    return ["final", *overlay_view_names(info)]


def backends_with_view(view: str, infos: Sequence[BackendInfo]) -> list[str]:
    """The backends among `infos` (the registry's: viewer.backends.registered_infos) that produce
    the overlay view `view`."""
    return [info.name for info in infos if overlay_spec(info, view) is not None]


def all_view_names(infos: Sequence[BackendInfo]) -> list[str]:
    """The shade pass's views and every overlay view of `infos` (no duplicates)."""
    out = list(SHADE_MODES)
    for info in infos:
        out += [n for n in overlay_view_names(info) if n not in out]
    return out


def view_unavailable(view: str, info: BackendInfo, infos: Sequence[BackendInfo] = ()) -> str:
    """Why backend `info` cannot show `view` ('' when it can): an unknown view, or an overlay
    that other backends of `infos` produce (named in the message)."""
    if view in SHADE_MODES or overlay_spec(info, view) is not None:
        return ""
    producers = backends_with_view(view, infos)
    if not producers:
        return f"unknown view '{view}' (choose from {', '.join(view_names(info))})"
    return (f"view '{view}' is an overlay that backend '{info.name}' does not produce "
            f"(backends that do: {', '.join(producers)})")


def check_view(view: str, info: BackendInfo, infos: Sequence[BackendInfo] = ()) -> None:
    """RtwalkError unless backend `info` can show `view` (the CLI's check before loading a scene)."""
    msg = view_unavailable(view, info, infos)
    if msg:
        raise RtwalkError(msg)


def check_view_effect(view: str, settings, effects_text: str) -> None:
    """A pass view (shadows, soft, ao, diffuse, reflections) needs that effect computed: without it
    `render --effects primary --view shadows` wrote an all-black image."""
    from viewer.effects import EFFECT_NAMES

    if view in EFFECT_NAMES and view != "primary" and not getattr(settings, view):
        raise RtwalkError(f"--view {view} shows the {view} pass, which --effects '{effects_text}' does not "
                          f"compute; add {view} to --effects")


def ids_labels(spec: OverlaySpec) -> tuple[str, str]:
    """(what the colours are, what the per-tile numbers are) of an "ids" view, from its label
    "colour; numbers"; without a counts texture the numbers are the distinct ids in the tile."""
    colour, _, numbers = (spec.label or "").partition(";")
    colour, numbers = colour.strip() or "id", numbers.strip()
    if spec.counts is None:
        numbers = "distinct ids in the tile"
    elif not numbers:
        numbers = f"{spec.counts.replace('_', ' ')} (max in the tile)"
    return colour, numbers


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


def tile_counts(capture: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """Per screen tile of `level`: (rects int64 (K, 4) x, y, w, h in pixels, counts (K,), from_counts).

    `capture` is an "ids" view's capture read back, (H, W, 4). Where the backend reported its
    counts texture (any value >= 0), a tile's number is the maximum of those values over the
    tile (from_counts True); otherwise it is the number of distinct ids in the tile."""
    h, w = capture.shape[:2]
    n = 1 << level
    rects = level_rects((w, h), level)
    tiles = tile_index((w, h), level).reshape(-1)
    reported = capture[..., CAPTURE_COUNTS].reshape(-1)
    if (reported >= 0).any():
        counts = np.zeros(n * n, np.int64)
        np.maximum.at(counts, tiles, np.maximum(reported, 0).astype(np.int64))
        return rects, counts, True
    ids = capture[..., CAPTURE_VALUE].reshape(-1).astype(np.int64)
    keep = ids >= 0
    span = int(ids.max(initial=0)) + 1
    keys = np.unique(tiles[keep] * span + ids[keep])
    return rects, np.bincount(keys // span, minlength=n * n), False


# --------------------------------------------------------------------------- the pass


class _Capture:
    """One view's capture texture and its max-reduction chain."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]):
        self.texture = ctx.texture(size, 4, dtype="i4")
        self.texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.fbo = ctx.framebuffer(color_attachments=[self.texture])
        self.steps: list[tuple[moderngl.Texture, moderngl.Framebuffer]] = []
        w, h = size
        while True:
            w, h = -(-w // REDUCE_BLOCK), -(-h // REDUCE_BLOCK)
            tex = ctx.texture((w, h), 2, dtype="i4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self.steps.append((tex, ctx.framebuffer(color_attachments=[tex])))
            if (w, h) == (1, 1):
                break
        self.reduced = False

    def release(self) -> None:
        for tex, fbo in self.steps:
            fbo.release()
            tex.release()
        self.fbo.release()
        self.texture.release()


class OverlayPass:
    """Capture of one pass's overlays (one texture per view), their max-reduction, and the views."""

    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, quad: FullscreenQuad,
                 size: tuple[int, int]):
        self.ctx = ctx
        self.quad = quad
        self.size = tuple(size)
        self.copy_prog = programs.get("fullscreen.vert", "overlay_copy.frag")
        for i, name in enumerate(["srcValue", "srcCounts", "rayOrigin", "rayDir", "hitId"]):
            self.copy_prog[name] = i
        self.reduce_prog = programs.get("fullscreen.vert", "overlay_reduce.frag")
        self.reduce_prog["src"] = 0
        self.view_prog = programs.get("fullscreen.vert", "overlay_view.frag")
        for i, name in enumerate(["overlay", "reduced", "lut"]):
            self.view_prog[name] = i
        lut = np.concatenate([heat_lut(), np.full((256, 1), 255, np.uint8)], axis=1)
        self.lut = ctx.texture((256, 1), 4, lut.tobytes(), dtype="f1")
        self.lut.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.targets: dict[str, _Capture] = {}  # view name -> capture (created on first use)
        self.captured: dict[str, OverlaySpec] = {}  # views copied this frame (empty: nothing)

    def resize(self, size: tuple[int, int]) -> None:
        if tuple(size) == self.size:
            return
        self._release_targets()
        self.size = tuple(size)

    def _release_targets(self) -> None:
        for cap in self.targets.values():
            cap.release()
        self.targets = {}
        self.captured = {}

    def release(self) -> None:
        self._release_targets()
        self.lut.release()

    def begin_frame(self) -> None:
        self.captured = {}

    def capture(self, specs: tuple[OverlaySpec, ...], overlays: dict[str, moderngl.Texture], rays: RayBatch,
                hits: HitBuffer) -> None:
        """Copy the views `specs` from the backend's textures of the pass just traced (plus the
        pass's ray/hit flags); a spec whose texture the backend did not return is skipped."""
        p = self.copy_prog
        # a backend's overlay textures are written with image stores / atomics (chcrt's overdraw):
        # sampling them here needs the barrier (by the spec; llvmpipe has not needed it so far)
        self.ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT)
        rays.origin.use(2)
        rays.direction.use(3)
        hits.id.use(4)
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        for spec in specs:
            src = overlays.get(spec.texture)
            if src is None:
                continue
            counts = overlays.get(spec.counts) if spec.counts else None
            src.use(0)
            (counts or src).use(1)  # an integer texture on the unit even when unused
            p["hasCounts"] = int(counts is not None)
            cap = self.targets.get(spec.name)
            if cap is None:
                cap = self.targets[spec.name] = _Capture(self.ctx, self.size)
            cap.fbo.use()
            cap.fbo.scissor = None
            self.quad.render(p)
            cap.reduced = False
            self.captured[spec.name] = spec

    def _reduce(self, cap: _Capture) -> None:
        if cap.reduced:
            return
        p = self.reduce_prog
        src = cap.texture
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        for tex, fbo in cap.steps:
            src.use(0)
            p["srcSize"] = src.size
            fbo.use()
            self.quad.render(p)
            src = tex
        cap.reduced = True

    def _captured(self, view: str) -> _Capture:
        if view not in self.captured:
            raise KeyError(f"overlay view '{view}' was not captured this frame")
        return self.targets[view]

    def render_view(self, fbo: moderngl.Framebuffer, view: str, tile_level: int, fixed_max: int,
                    log: bool) -> None:
        """Draw the captured `view` into `fbo` (the shade pass's image)."""
        cap = self._captured(view)
        self._reduce(cap)
        p = self.view_prog
        cap.texture.use(0)
        cap.steps[-1][0].use(1)
        self.lut.use(2)
        p["mode"] = VIEW_SHADER_MODES[self.captured[view].kind]
        p["fixedMax"] = int(max(fixed_max, 0))
        p["logScale"] = int(log)
        p["tileLevel"] = int(tile_level)
        fbo.use()
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        self.quad.render(p)

    def read_max(self, view: str) -> tuple[int, int]:
        """(max value, max counts) over the view's capture, at least 0: 8 bytes read back."""
        cap = self._captured(view)
        self._reduce(cap)
        v = np.frombuffer(glio.read(cap.steps[-1][0]), np.int32)
        return int(v[0]), int(v[1])

    def read(self, view: str) -> np.ndarray:
        """The view's capture, int32 (H, W, 4), row 0 = bottom (layout: overlay.glsl)."""
        return read_texture(self._captured(view).texture).copy()

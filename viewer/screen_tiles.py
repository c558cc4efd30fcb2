"""Quadtree screen tiles over a ray batch: the tile (level L, x, y) covers the pixels
[x*W >> L, (x+1)*W >> L) x [y*H >> L, (y+1)*H >> L) (row 0 = bottom).

Generic: a backend that works per screen tile (and says so through `tile_level`) uses these, and
the overlay views draw the same tiles' outlines and per-tile numbers (shaders/overlay.glsl
`overlayTileOf` is the shader's copy of `tile_index`). Integer arithmetic only, so the tiles
partition the screen exactly for any size.
"""

from __future__ import annotations

import numpy as np


def tile_rects(level: np.ndarray, tx: np.ndarray, ty: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """int64 (K, 4) pixel rectangles (x, y, w, h) of quadtree tiles."""
    w, h = size
    level = np.asarray(level, np.int64)
    tx = np.asarray(tx, np.int64)
    ty = np.asarray(ty, np.int64)
    x0 = (tx * w) >> level
    x1 = ((tx + 1) * w) >> level
    y0 = (ty * h) >> level
    y1 = ((ty + 1) * h) >> level
    return np.stack([x0, y0, x1 - x0, y1 - y0], axis=1)


def level_rects(size: tuple[int, int], level: int) -> np.ndarray:
    """int64 (4^level, 4) rectangles of every tile of one level, tile index ty * 2^level + tx."""
    n = 1 << int(level)
    ty, tx = np.divmod(np.arange(n * n, dtype=np.int64), n)
    return tile_rects(np.full(n * n, level), tx, ty, size)


def max_tile_level(size: tuple[int, int], min_tile_fraction: float, min_tile_pixels: int = 4) -> int:
    """Deepest quadtree level whose tiles still cover at least `min_tile_fraction` of the screen
    (tiles of level L cover 4^-L of it), and at least `min_tile_pixels` pixels on each side."""
    level = 0
    while (4.0 ** -(level + 1) >= min_tile_fraction * (1 - 1e-9)
           and min(size) >> (level + 1) >= min_tile_pixels):
        level += 1
    return level


def tile_index(size: tuple[int, int], level: int) -> np.ndarray:
    """int64 (H, W): the tile (ty * 2^level + tx) of each pixel at `level` (overlayTileOf):
    pixel x lies in tile t iff t*W >> L <= x < (t+1)*W >> L."""
    w, h = size
    tx = (((np.arange(w, dtype=np.int64) + 1) << level) - 1) // w
    ty = (((np.arange(h, dtype=np.int64) + 1) << level) - 1) // h
    return ty[:, None] * (1 << level) + tx[None, :]

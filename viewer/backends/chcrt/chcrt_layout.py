"""What chcrt's shaders and passes share: binding points and texture units, the item and draw
records (chc_records.glsl), and the sizes of the GPU-driven pass's buffers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from viewer.backends.chcrt.chcrt_devfront import FRONT_SSBO
from viewer.gl.bindings import backend_bindings
from viewer.gl.limits import is_software_renderer

HERE = Path(__file__).resolve().parent  # the chc_* shaders

# chcrt's own binding points (viewer.gl.bindings.backend_bindings checks them against the table)
SSBO = {"BIND_CHC_ITEMS": 5,  # (tile, node) items of a batch draw
        "BIND_CHC_COUNT": 6,  # active ray count
        "BIND_CHC_DRAWS": 7,  # per-instance tile draws
        "BIND_CHC_QUERY_COUNTS": 8,  # per-query passed-fragment counts
        "BIND_CHC_CANDIDATES": 4,  # GPU-driven: the invisible pairs the cull kept (items)
        "BIND_CHC_INDIRECT": 12,  # GPU-driven: the indirect draw command being built
        "BIND_CHC_QUERIES": 13,  # GPU-driven: every query record of the pass, before the coarse cull
        "BIND_CHC_TILES": 14,  # GPU-driven: per finest tile, ray origin box and farthest reach
        "BIND_CHC_VIS_HITS": 34}  # visible_stage=compute: hits per pixel before the resolve draw
IMAGE = {"BIND_IMG_CHC_BEST": 0,  # packed closest hit per pixel
         "BIND_IMG_CHC_OVERDRAW": 1,  # query fragments per pixel (overlay)
         "BIND_IMG_CHC_BATCH": 2}  # subtrees in the pixel's batches (overlay)
HINT_UNIT = 2  # texture unit of the hit hints (rays: units 0 and 1)
ITEM_UNIT = 3  # texture unit of the items' buffer texture (chc_common.glsl loadItem)
# with the device fronts' (chcrt_devfront.py), and the items' texture unit
BINDINGS = {**backend_bindings({**SSBO, **FRONT_SSBO}, IMAGE), "BIND_TEX_CHC_ITEMS": ITEM_UNIT}
(BIND_CHC_ITEMS, BIND_CHC_COUNT, BIND_CHC_DRAWS, BIND_CHC_QUERY_COUNTS, BIND_CHC_CANDIDATES, BIND_CHC_INDIRECT,
 BIND_CHC_QUERIES, BIND_CHC_TILES, BIND_CHC_VIS_HITS) = SSBO.values()
BIND_IMG_CHC_BEST, BIND_IMG_CHC_OVERDRAW, BIND_IMG_CHC_BATCH = IMAGE.values()

# gap: written by chc_querycull.comp for the invisible pairs' items (a lower bound of the distance from
# every ray origin of the tile to the box, world units); 0 in host-made items
# (chc_records.glsl ChcItem: p2 = the pair's count slot, p0/p1 = its triangle range, id = its node)
ITEM_DTYPE = np.dtype([("bmin", "<f4", 3), ("gap", "<f4"), ("bmax", "<f4", 3), ("count", "<i4"),
                       ("ref", "<i4"), ("p2", "<i4"), ("p0", "<i4"), ("p1", "<i4"), ("id", "<i4"), ("pad2", "<i4", 3)])
assert ITEM_DTYPE.itemsize == 64
DRAW_DTYPE = np.dtype([("rect", "<i4", 4), ("info", "<i4", 4)])  # x, y, w, h; item base, count, query slot
COUNT_SLOTS = 64
COUNT_BYTES = 4 * COUNT_SLOTS  # GPU-driven counts buffer: ray counts, then query counts from this offset
MAX_BOXES = 48  # boxes per query draw (max_multi pairs x 2 child boxes)
TILE_BOUND_BYTES = 112  # chc_tilecone.glsl TileBound: origin box + reach, direction cone, side planes


def tile_bounds_group(renderer: str | None) -> int:
    """Invocations per tile of chc_tilebounds.comp on the device named `renderer` (GL_RENDERER): 8 on
    a CPU rasterizer (one SIMD vector of llvmpipe's, so three reduction rounds instead of six: 0.99
    against 1.51 ms a dispatch for city-near's AO rays at 640x360), 64 on a GPU (a tile's pixels
    spread over more threads). The bounds are the same bits either way (min, max and counts)."""
    return 8 if is_software_renderer(renderer) else 64

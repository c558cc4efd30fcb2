"""Helpers the overlay and panel tests of every backend share: record the overlays a backend returns,
read the shaded image in GL row order, the tile outline pixels, draw the panel headless."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from viewer.gl.textures import read_texture


def record_overlays(r) -> dict:
    """Wrap the backend's trace() of Renderer `r`: read its overlay textures back after the first pass
    of each (ray type, sample), i.e. what it wrote for the pass the renderer copies."""
    seen: dict = {}
    orig = r.backend.trace

    def trace(rays, pinfo, hits):
        res = orig(rays, pinfo, hits)
        key = (pinfo.ray_type, int(pinfo.sample))
        if key not in seen:
            seen[key] = {k: read_texture(t).reshape(-1).copy() for k, t in res.overlays.items()}
        return res

    r.backend.trace = trace
    return seen


def tile_edges(size: tuple[int, int], level: int) -> np.ndarray:
    """(H, W) bool: pixels on either side of a border between the screen tiles of `level` (where the
    overlay views draw tile outlines)."""
    from viewer.screen_tiles import tile_index

    tid = tile_index(size, level)
    edge = np.zeros(tid.shape, bool)
    edge[:, 1:] |= tid[:, 1:] != tid[:, :-1]
    edge[:, :-1] |= tid[:, 1:] != tid[:, :-1]
    edge[1:] |= tid[1:] != tid[:-1]
    edge[:-1] |= tid[1:] != tid[:-1]
    return edge


def image_gl(r) -> np.ndarray:
    """The shaded image as (H*W, 3) in GL row order (row 0 = bottom), like the overlays."""
    return r.read_image()[::-1].reshape(-1, 3).astype(np.int32)


def draw_views(r, cam, views) -> tuple[object, dict[str, int], object]:
    """Draw the window's panel and overlay annotations headless, one frame per view: a real imgui +
    implot frame whose draw data is built but not rasterised. Renders each view with Renderer `r` from
    `cam`, the panel 340 px wide in a 900x600 window; returns (FrameHistory, draw-data vertices per
    view, last FrameReport) and leaves `r.view` at "final"."""
    from imgui_bundle import imgui, implot

    from viewer.ui.camera_controller import FlyCamera
    from viewer.ui.panel import FrameHistory, chart_phases, draw_overlay_annotations, draw_panel

    hist = FrameHistory()
    host = SimpleNamespace(renderer=r, fly=FlyCamera.from_camera(cam, r.diagonal), history=hist, render_scale=1.0,
                           status="", backend_error="", last_report=None,
                           current_camera=lambda: cam, switch_backend=lambda n: None, take_screenshot=lambda: None,
                           toggle_recording=lambda: None, toggle_playback=lambda: None,
                           copy_to_clipboard=lambda t: None, mode_line=lambda: "")
    imgui.create_context()
    implot.create_context()
    vtx: dict[str, int] = {}
    try:
        io = imgui.get_io()
        io.display_size = (900, 600)
        io.set_ini_filename("")
        io.fonts.build()  # what a renderer backend does
        for view in views:
            r.view = view
            rep = r.render(cam)
            host.last_report = rep
            hist.add(rep.wall_ms, sum(rep.gpu_ms.values()), chart_phases(rep.gpu_ms, r.backend.info.phases),
                     rep.backend_stats)
            io.delta_time = 1 / 30
            imgui.new_frame()
            draw_overlay_annotations(host, 900, 600, 340)
            draw_panel(host, 340, 600)
            imgui.render()
            vtx[view] = imgui.get_draw_data().total_vtx_count
    finally:
        r.view = "final"
        implot.destroy_context()
        imgui.destroy_context()
    return hist, vtx, host.last_report

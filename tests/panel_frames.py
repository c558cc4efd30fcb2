"""Draw the window's panel and overlay annotations headless, one frame per view: a real imgui + implot
frame whose draw data is built but not rasterised. Shared by the panel tests of every backend."""

from __future__ import annotations

from types import SimpleNamespace


def draw_views(r, cam, views) -> tuple[object, dict[str, int], object]:
    """Render each view with Renderer `r` from `cam` and draw the panel (340 px wide, in a 900x600
    window) with its history; returns (FrameHistory, draw-data vertices per view, last FrameReport).
    Leaves `r.view` at "final"."""
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

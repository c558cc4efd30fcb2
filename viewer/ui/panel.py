"""The side panel (imgui): scene stats, effect settings, backend/view, timings, camera, keys.

`FrameHistory` and `camera_argument` are plain Python (unit-testable); `draw_panel` needs a live
imgui frame and reads/writes the viewer through the small `PanelHost` interface below.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

import numpy as np

from viewer.camera import Camera

PANEL_WIDTH = 340
HISTORY = 120


class FrameHistory:
    """Last `n` frame times (ms) and the latest per-phase GPU timings."""

    def __init__(self, n: int = HISTORY):
        self.frame_ms: deque[float] = deque(maxlen=n)
        self.gpu_ms: deque[float] = deque(maxlen=n)

    def add(self, frame_ms: float, gpu_total_ms: float) -> None:
        self.frame_ms.append(float(frame_ms))
        self.gpu_ms.append(float(gpu_total_ms))

    def array(self, which: str = "frame") -> np.ndarray:
        src = self.frame_ms if which == "frame" else self.gpu_ms
        return np.asarray(src, np.float32) if src else np.zeros(1, np.float32)

    @property
    def mean_ms(self) -> float:
        return float(np.mean(self.frame_ms)) if self.frame_ms else 0.0

    @property
    def fps(self) -> float:
        m = self.mean_ms
        return 1000.0 / m if m > 0 else 0.0


def camera_argument(camera: Camera, target_distance: float = 1.0) -> str:
    """The value of `rtwalk render --camera` that reproduces this view (roll is not kept)."""
    eye = np.asarray(camera.position, np.float64)
    target = eye + camera.forward * max(float(target_distance), 1e-3)
    vals = [*eye, *target, camera.fov_y]
    return ",".join(_fmt(v) for v in vals)


def _fmt(v: float) -> str:
    s = f"{float(v):.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


class PanelHost(Protocol):
    """What the panel needs from the viewer (implemented by viewer.ui.app.ViewerApp)."""

    renderer: object
    fly: object
    history: FrameHistory
    render_scale: float
    status: str
    backend_error: str
    last_report: object | None

    def current_camera(self) -> Camera: ...
    def switch_backend(self, name: str) -> None: ...
    def take_screenshot(self) -> None: ...
    def toggle_recording(self) -> None: ...
    def toggle_playback(self) -> None: ...
    def copy_to_clipboard(self, text: str) -> None: ...
    def mode_line(self) -> str: ...


def _mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB"


def draw_panel(host, width: float, height: float) -> None:  # noqa: C901 (a flat list of widgets)
    from imgui_bundle import imgui

    from viewer.backends import BACKENDS
    from viewer.passes.shade import VIEW_MODES

    r = host.renderer
    s = r.settings
    scene = r.scene
    imgui.set_next_window_pos((0, 0), imgui.Cond_.always)
    imgui.set_next_window_size((width, height), imgui.Cond_.always)
    imgui.set_next_window_bg_alpha(0.82)
    flags = (imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_saved_settings)
    imgui.begin("rtwalk", None, flags)
    imgui.push_item_width(-110)

    # -- status line --------------------------------------------------------------------------
    hist = host.history
    imgui.text(f"{hist.fps:5.1f} fps  {hist.mean_ms:6.1f} ms/frame  render {r.size[0]}x{r.size[1]}")
    imgui.text(f"{scene.name}: {scene.triangle_count:,} tris, backend {r.backend_name}, view {r.view}")
    mode = host.mode_line()
    if mode:
        imgui.text_colored((1.0, 0.45, 0.35, 1.0), mode)
    if host.status:
        imgui.text_wrapped(host.status)

    # -- timings ------------------------------------------------------------------------------
    if imgui.collapsing_header("Timings", imgui.TreeNodeFlags_.default_open):
        rep = host.last_report
        frame = hist.array("frame")
        imgui.plot_lines("##frame", frame, overlay_text=f"frame ms (last {len(hist.frame_ms)})",
                         scale_min=0.0, scale_max=float(max(frame.max() * 1.1, 1.0)), graph_size=(-1, 56))
        if rep is not None:
            total = max(sum(rep.gpu_ms.values()), 1e-6)
            imgui.text(f"GPU {total:.1f} ms, wall {rep.wall_ms:.1f} ms")
            for name, ms in rep.gpu_ms.items():
                imgui.progress_bar(min(ms / total, 1.0), (-1, 0), f"{name}  {ms:.2f} ms")
            rays = sum(rep.rays.values())
            if rep.rays:
                if imgui.begin_table("rays", 2):
                    for name, n in rep.rays.items():
                        imgui.table_next_column()
                        imgui.text(f"{name} {n:,}")
                    imgui.end_table()
                trace = rep.trace_ms
                mrays_trace = rays / (trace * 1e3) if trace > 0 else 0.0
                mrays_frame = rays / (rep.wall_ms * 1e3) if rep.wall_ms > 0 else 0.0
                imgui.text(f"{rays:,} rays: {mrays_trace:.1f} Mrays/s traced")
                imgui.text(f"({mrays_frame:.1f} Mrays/s over the whole frame)")
            else:
                imgui.text("no rays traced (all effects off)")

    # -- effects ------------------------------------------------------------------------------
    if imgui.collapsing_header("Effects", imgui.TreeNodeFlags_.default_open):
        col = 150

        def toggle_with_samples(label: str, on: str, samples: str | None) -> None:
            _, val = imgui.checkbox(label, getattr(s, on))
            setattr(s, on, val)
            if samples is not None and val:
                imgui.same_line(col)
                imgui.push_item_width(-1)
                _, n = imgui.slider_int(f"##{samples}", getattr(s, samples), 1, 64, "%d samples")
                imgui.pop_item_width()
                setattr(s, samples, n)

        _, s.shadows = imgui.checkbox("shadows", s.shadows)
        imgui.same_line(col)
        _, s.reflections = imgui.checkbox("reflections", s.reflections)
        toggle_with_samples("soft shadows", "soft", "soft_samples")
        toggle_with_samples("ambient occl.", "ao", "ao_samples")
        if s.ao:
            _, s.ao_length = imgui.slider_float("ao length", s.ao_length, 0.001, 1.0, "%.3f",
                                                imgui.SliderFlags_.logarithmic)
        toggle_with_samples("diffuse bounce", "diffuse", "diffuse_samples")
        _, s.primary = imgui.checkbox("trace primary rays", s.primary)
        _, s.perturb_deg = imgui.slider_float("perturb (deg)", s.perturb_deg, 0.0, 180.0, "%.1f")
        _, s.exposure = imgui.slider_float("exposure", s.exposure, 0.05, 8.0, "%.2f",
                                           imgui.SliderFlags_.logarithmic)
        _, s.ambient = imgui.slider_float("ambient", s.ambient, 0.0, 1.0, "%.2f")

    # -- renderer -----------------------------------------------------------------------------
    if imgui.collapsing_header("Renderer", imgui.TreeNodeFlags_.default_open):
        names = list(BACKENDS)
        cur = names.index(r.backend_name) if r.backend_name in names else 0
        changed, idx = imgui.combo("backend", cur, names)
        if changed and names[idx] != r.backend_name:
            host.switch_backend(names[idx])
        if host.backend_error:
            imgui.text_colored((1.0, 0.4, 0.3, 1.0), "backend error:")
            imgui.text_wrapped(host.backend_error)
        cur = VIEW_MODES.index(r.view) if r.view in VIEW_MODES else 0
        changed, idx = imgui.combo("view", cur, VIEW_MODES)
        if changed:
            r.view = VIEW_MODES[idx]
        _, host.render_scale = imgui.slider_float("render scale", host.render_scale, 0.25, 1.0, "%.2f")

    # -- scene --------------------------------------------------------------------------------
    if imgui.collapsing_header("Scene", imgui.TreeNodeFlags_.default_open):
        st = r.stats()
        imgui.text(f"{scene.name}: {scene.triangle_count:,} triangles")
        imgui.text(f"{len(scene.materials)} materials, {len(scene.point_lights)} point / "
                   f"{len(scene.rect_lights)} area lights")
        imgui.text(f"BVH {st.get('nodes', 0):,} nodes, depth {st.get('depth', 0)}")
        imgui.text(f"SAH cost {st.get('sah_cost', 0.0):.1f}, built in {st.get('build_time_s', 0.0):.2f} s")
        imgui.text(f"GPU memory {_mib(st.get('gpu_memory_bytes', 0))}")

    # -- camera -------------------------------------------------------------------------------
    if imgui.collapsing_header("Camera", imgui.TreeNodeFlags_.default_open):
        cam = host.current_camera()
        fly = host.fly
        p = cam.position
        imgui.text(f"pos   {p[0]:9.3f} {p[1]:9.3f} {p[2]:9.3f}")
        imgui.text(f"yaw {np.degrees(fly.yaw):7.1f}  pitch {np.degrees(fly.pitch):6.1f}  fov {cam.fov_y:.0f}")
        q = cam.orientation
        imgui.text(f"quat  {q[0]:.3f} {q[1]:.3f} {q[2]:.3f} {q[3]:.3f}")
        imgui.text(f"speed {fly.speed:.2f}/s (wheel x1.25, shift x5)")
        arg = "--camera " + camera_argument(cam, max(1.0, r.diagonal * 0.05))
        imgui.push_item_width(-60)
        imgui.input_text("##camarg", arg, imgui.InputTextFlags_.read_only | imgui.InputTextFlags_.auto_select_all)
        imgui.pop_item_width()
        imgui.same_line()
        if imgui.button("Copy"):
            host.copy_to_clipboard(arg)

    # -- actions / keys -----------------------------------------------------------------------
    if imgui.collapsing_header("Keys", imgui.TreeNodeFlags_.default_open):
        if imgui.button("Screenshot (F12)"):
            host.take_screenshot()
        imgui.same_line()
        if imgui.button("Record (R)"):
            host.toggle_recording()
        imgui.same_line()
        if imgui.button("Play (P)"):
            host.toggle_playback()
        imgui.text_wrapped("WASD move, Q/E down/up, drag to look, wheel = speed, shift = x5, Esc quits")

    imgui.pop_item_width()
    imgui.end()

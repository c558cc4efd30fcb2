"""The side panel (imgui): scene stats, effect settings, backend/view, timings, camera, keys;
backend phases as a stacked bar per frame (CHC+RT paper, Figure 8) and per-frame counters; the
overlay views' controls, and their legend / tile labels drawn over the image.

Everything backend-specific comes from the active backend's `info` (viewer.backends.interface):
the counters it declares (others go under "more counters"), the phases it stacks (else the
per-ray-type trace:* phases), its overlay views and their kinds and labels. No backend is named
here.

`FrameHistory`, `chart_phases`, `phase_label`, `counter_rows` and `camera_argument` are plain
Python (unit-testable); `draw_panel` and `draw_overlay_annotations` need a live imgui (+ implot)
frame and read/write the viewer through the small `PanelHost` interface below.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from viewer.camera import Camera
from viewer.gl.limits import host_time_label

PANEL_WIDTH = 340
HISTORY = 120
CHART_FRAMES = 60  # frames in the stacked phase chart


def chart_phases(gpu_ms: dict[str, float], phases: Sequence[str] = ()) -> dict[str, float]:
    """The phases stacked per frame: the backend's declared `phases` (BackendInfo.phases, in that
    order) that this frame timed, else the per-ray-type trace times (trace:*)."""
    own = {k: gpu_ms[k] for k in phases if k in gpu_ms}
    return own if own else {k: v for k, v in gpu_ms.items() if k.startswith("trace:")}


def phase_label(name: str) -> str:
    """Chart legend label: the part after a 'prefix:', without a leading step number:
    'x:2-queries' -> 'queries', 'trace:ao' -> 'ao', 'gbuffer' -> 'gbuffer'."""
    tail = name.split(":", 1)[-1]
    tail = re.sub(r"^\d+[-_. ]*", "", tail) or tail
    return tail.replace("-", " ").replace("_", " ")


def counter_rows(stats: dict[str, float], declared: Sequence[str]) -> tuple[list[str], list[str]]:
    """(the backend's declared counters present in `stats`, in its order; the other counters)."""
    rows = [k for k in declared if k in stats]
    return rows, [k for k in stats if k not in rows]


TOP_PHASES = 4  # the timings section lists the costliest phases; the rest share one bar


def top_phases(gpu_ms: dict[str, float], n: int = TOP_PHASES) -> list[tuple[str, float]]:
    """The `n` costliest phases in frame order, then one "other (k phases)" row for the rest, so the
    section keeps its height whatever the backend times (a backend with a dozen phases)."""
    items = list(gpu_ms.items())
    if len(items) <= n + 1:
        return items
    keep = {k for k, _ in sorted(items, key=lambda kv: -kv[1])[:n]}
    rest = [v for k, v in items if k not in keep]
    return [(k, v) for k, v in items if k in keep] + [(f"other ({len(rest)} phases)", float(sum(rest)))]


def fps_line(host) -> str:
    """The panel's first line: the rate of the last frame actually rendered, or that the window is
    idle (a converged image is not rendered again; a mean over older frames would go stale)."""
    last = float(getattr(host, "last_frame_ms", 0.0) or 0.0)
    if getattr(host, "idle", False):
        return f"idle (converged; last frame {last:,.0f} ms)" if last > 0 else "idle (converged)"
    if last <= 0:  # not measured yet (first frame), or a host that does not track it
        hist = host.history
        return f"{hist.fps:5.1f} fps  {hist.mean_ms:6.1f} ms/frame" if hist.frame_ms else "- fps"
    return f"{1000.0 / last:5.1f} fps  {last:6.1f} ms/frame"


class FrameHistory:
    """Last `n` frame times (ms), GPU totals, chart phases and backend counters."""

    def __init__(self, n: int = HISTORY):
        self.frame_ms: deque[float] = deque(maxlen=n)
        self.gpu_ms: deque[float] = deque(maxlen=n)
        self.phases: deque[dict[str, float]] = deque(maxlen=n)
        self.counters: deque[dict[str, float]] = deque(maxlen=n)

    def add(self, frame_ms: float, gpu_total_ms: float, phases: dict[str, float] | None = None,
            counters: dict[str, float] | None = None) -> None:
        self.frame_ms.append(float(frame_ms))
        self.gpu_ms.append(float(gpu_total_ms))
        self.phases.append(dict(phases or {}))
        self.counters.append(dict(counters or {}))

    def phase_table(self, last: int = CHART_FRAMES) -> tuple[list[str], np.ndarray]:
        """(phase names, float64 (phases, frames) ms) over the last frames; 0 where a frame lacks
        a phase (backend switched). Names in first-seen order."""
        frames = list(self.phases)[-last:]
        names: list[str] = []
        for f in frames:
            names += [k for k in f if k not in names]
        table = np.array([[f.get(n, 0.0) for f in frames] for n in names], np.float64)
        return names, table.reshape(len(names), len(frames))

    def counter_mean(self, name: str) -> float:
        vals = [c[name] for c in self.counters if name in c]
        return float(np.mean(vals)) if vals else 0.0

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

    from viewer.backends import backend_names
    from viewer.passes.overlay import view_names

    r = host.renderer
    s = r.settings
    scene = r.scene
    imgui.set_next_window_pos((0, 0), imgui.Cond_.always)
    imgui.set_next_window_size((width, height), imgui.Cond_.always)
    imgui.set_next_window_bg_alpha(1.0)  # beside the image, not over it
    flags = (imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_saved_settings)
    imgui.begin("rtwalk", None, flags)
    imgui.push_item_width(-110)

    # -- status line --------------------------------------------------------------------------
    hist = host.history
    imgui.text_wrapped(fps_line(host) + f"  render {r.size[0]}x{r.size[1]}")
    imgui.text_wrapped(f"{scene.name}: {scene.triangle_count:,} tris, backend {r.backend_name}, view {r.view}")
    step = getattr(host, "step", None)
    if step is not None:
        imgui.text_wrapped(step.line())
    elif getattr(host, "progressive", None) is None:
        imgui.text_wrapped("full quality every frame (--no-progressive)")
    mode = host.mode_line()
    if mode:
        imgui.text_colored((1.0, 0.45, 0.35, 1.0), mode)
    if r.overlay_missing:  # an overlay view the backend cannot feed: the final image is shown
        imgui.text_colored((1.0, 0.45, 0.35, 1.0), overlay_missing_line(r))
        imgui.text_wrapped(r.overlay_missing)
    if host.status:
        imgui.text_wrapped(host.status)

    # -- timings ------------------------------------------------------------------------------
    # Sections fold (collapsing headers); only the timings are open at first, so the panel fits a
    # 504-px window, and the window scrolls (wheel) whatever is opened
    if imgui.collapsing_header("Timings", imgui.TreeNodeFlags_.default_open):
        rep = host.last_report
        frame = hist.array("frame")
        imgui.plot_lines("##frame", frame, overlay_text=f"frame ms (last {len(hist.frame_ms)})",
                         scale_min=0.0, scale_max=float(max(frame.max() * 1.1, 1.0)), graph_size=(-1, 36))
        if rep is not None:
            total = max(sum(rep.gpu_ms.values()), 1e-6)
            imgui.text(f"GPU {total:.1f} ms, wall {rep.wall_ms:.1f} ms")
            for name, ms in top_phases(rep.gpu_ms):
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

    # -- backend phases and counters (CHC+RT paper, Figure 8) ------------------------------------
    if imgui.collapsing_header("Backend phases, counters & I/O"):
        if host.last_report is not None:  # what crosses between host and device (viewer.iostats)
            _draw_io(host.last_report, r.size, r.ctx.info.get("GL_RENDERER"))
        _draw_phase_chart(hist)
        _draw_counters(host.last_report, hist, r.backend.info.counters)

    # -- effects ------------------------------------------------------------------------------
    if imgui.collapsing_header("Effects"):
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
    if imgui.collapsing_header("Renderer"):
        names = backend_names()
        cur = names.index(r.backend_name) if r.backend_name in names else 0
        changed, idx = imgui.combo("backend", cur, names)
        if changed and names[idx] != r.backend_name:
            host.switch_backend(names[idx])
        if host.backend_error:
            imgui.text_colored((1.0, 0.4, 0.3, 1.0), "backend error:")
            imgui.text_wrapped(host.backend_error)
        views = view_names(r.backend.info)  # the shade pass's views + this backend's overlays
        if r.view not in views:  # kept from another backend: listed, and the panel says why it is not shown
            views.append(r.view)
        changed, idx = imgui.combo("view", views.index(r.view), views)
        if changed:
            r.view = views[idx]
        _draw_overlay_controls(r, host.last_report)
        _, host.render_scale = imgui.slider_float("render scale", host.render_scale, 0.25, 1.0, "%.2f")
        _draw_params(r.backend)

    # -- scene --------------------------------------------------------------------------------
    if imgui.collapsing_header("Scene"):
        st = r.stats()
        imgui.text(f"{scene.name}: {scene.triangle_count:,} triangles")
        imgui.text(f"{len(scene.materials)} materials, {len(scene.point_lights)} point / "
                   f"{len(scene.rect_lights)} area lights")
        imgui.text(f"BVH {st.get('nodes', 0):,} nodes, depth {st.get('depth', 0)}")
        imgui.text(f"SAH cost {st.get('sah_cost', 0.0):.1f}, built in {st.get('build_time_s', 0.0):.2f} s")
        imgui.text(f"GPU memory {_mib(st.get('gpu_memory_bytes', 0))}")

    # -- camera -------------------------------------------------------------------------------
    if imgui.collapsing_header("Camera"):
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
    if imgui.collapsing_header("Keys"):
        if imgui.button("Screenshot (F12)"):
            host.take_screenshot()
        imgui.same_line()
        if imgui.button("Record (R)"):
            host.toggle_recording()
        imgui.same_line()
        if imgui.button("Play (P)"):
            host.toggle_playback()
        imgui.text_wrapped("WASD move, Q/E down/up, drag to look, wheel = speed, shift = x5, V view "
                           "(final / the backend's overlay views), O overlay pass, F1 panel, Esc quits")

    imgui.pop_item_width()
    imgui.end()


def param_rows(backend) -> list[tuple[str, str]]:
    """("name = value", help) of the active backend's parameters, from its documented fields."""
    from viewer.backends.interface import param_docs

    params = getattr(backend, "params", None)
    return [(f"{d.name} = {getattr(params, d.name, d.default)}", d.help) for d in param_docs(backend.info.params)]


def _draw_params(backend) -> None:
    """The backend's parameters as set (--backend-params / RTWALK_<NAME>), each with its help as a
    tooltip, folded under one tree node."""
    from imgui_bundle import imgui

    rows = param_rows(backend)
    if rows and imgui.tree_node(f"{backend.info.name} parameters ({len(rows)})"):
        for text, help_text in rows:
            imgui.text(text)
            if help_text and imgui.is_item_hovered():
                imgui.set_tooltip(help_text)
        imgui.tree_pop()


# --------------------------------------------------------------------------- backend phases, counters


def io_lines(io, size: tuple[int, int], renderer: str | None = None) -> list[str]:
    """The "I/O per frame" lines: what crossed between host and devices and what the host
    submitted (viewer.iostats), bytes also per pixel; `renderer` (GL_RENDERER) names the host time."""
    px = max(size[0] * size[1], 1)
    return [f"to device {_mib(io.bytes_to_device)} ({io.bytes_to_device / px:.1f} B/px)",
            f"to host   {_mib(io.bytes_to_host)} ({io.bytes_to_host / px:.1f} B/px)",
            f"host syncs {io.host_syncs}, CL launches {io.cl_launches}",
            f"GL draws {io.gl_draws}, GL queries {io.gl_queries}",
            f"{host_time_label(renderer)} {io.python_ms:.1f} ms"]


def _draw_io(rep, size: tuple[int, int], renderer: str | None) -> None:
    from imgui_bundle import imgui

    io = getattr(rep, "io", None)
    if io is None:
        return
    imgui.separator()
    imgui.text("I/O per frame")
    for line in io_lines(io, size, renderer):
        imgui.text(line)


def _draw_phase_chart(hist: FrameHistory) -> None:
    """GPU ms per phase, one stacked bar per frame over the recent frames (implot)."""
    from imgui_bundle import imgui, implot

    names, table = hist.phase_table()
    if not names:
        imgui.text("no backend phases timed yet")
        return
    n = table.shape[1]
    totals = table.sum(axis=0)
    # the y range follows the typical frame: a warm-up frame (shader compilation) or a backend
    # switch would flatten every other bar; such a bar runs off the top
    ymax = float(max(np.percentile(totals, 90) * 1.25, 1e-3))
    last = ", ".join(f"{phase_label(k)} {v:.1f}" for k, v in zip(names, table[:, -1], strict=True))
    imgui.text_wrapped(f"last frame (ms): {last}")
    flags = implot.Flags_.no_menus | implot.Flags_.no_box_select | implot.Flags_.no_mouse_text
    sv = implot.StyleVar_
    implot.push_style_var(sv.legend_inner_padding, imgui.ImVec2(3, 3))  # a narrow legend beside the bars
    implot.push_style_var(sv.legend_spacing, imgui.ImVec2(2, 1))
    implot.push_style_var(sv.legend_padding, imgui.ImVec2(4, 4))
    if implot.begin_plot("##phases", (-1, 140), flags):
        implot.setup_axes("frames (newest right)", "GPU ms", implot.AxisFlags_.no_tick_labels)
        implot.setup_axis_limits(implot.ImAxis_.x1, -0.6, max(n, 8) - 0.4, implot.Cond_.always)
        implot.setup_axis_limits(implot.ImAxis_.y1, 0.0, ymax, implot.Cond_.always)
        implot.setup_legend(implot.Location_.north_east, implot.LegendFlags_.outside)
        implot.plot_bar_groups([phase_label(k) for k in names], np.ascontiguousarray(table.reshape(-1)),
                               0.8, 0.0, implot.BarGroupsFlags_.stacked)
        implot.end_plot()
    implot.pop_style_var(3)


def fmt_counter(v: float) -> str:
    """A counter cell: whole numbers with separators; small fractional values (MB) with 2 decimals."""
    return f"{v:,.2f}" if abs(v) < 100 and v % 1 != 0 else f"{v:,.0f}"


def _draw_counters(rep, hist: FrameHistory, declared: Sequence[str]) -> None:
    """This frame's backend counters (summed over its passes) and their mean over the history:
    the backend's declared counters in a table, the others folded away."""
    from imgui_bundle import imgui

    stats = rep.backend_stats if rep is not None else {}
    if not stats:
        imgui.text("the backend reports no counters")
        return
    rows, others = counter_rows(stats, declared)
    flags = imgui.TableFlags_.row_bg | imgui.TableFlags_.borders_inner_v
    if imgui.begin_table("counters", 3, flags):
        stretch = imgui.TableColumnFlags_.width_stretch
        imgui.table_setup_column("counter", stretch, 1.7)
        imgui.table_setup_column("frame", stretch, 1.0)
        imgui.table_setup_column(f"mean ({len(hist.counters)})", stretch, 1.0)
        imgui.table_headers_row()
        for k in rows:
            imgui.table_next_row()
            imgui.table_next_column()
            imgui.text(k.replace("_", " "))
            imgui.table_next_column()
            imgui.text(fmt_counter(stats[k]))
            imgui.table_next_column()
            imgui.text(fmt_counter(hist.counter_mean(k)))
        imgui.end_table()
    if others and imgui.tree_node("more counters"):
        for k in others:
            imgui.text(f"{k.replace('_', ' ')}: {fmt_counter(stats[k])}")
        imgui.tree_pop()


# --------------------------------------------------------------------------- overlays


def overlay_pass_choices(renderer) -> list[tuple[str, tuple | None]]:
    """(label, Renderer.overlay_pass value) for the overlay source selector: the frame's first
    pass (automatic), then each (ray type, sample) of the frame."""
    seen: list[tuple] = []
    for rt, k, _, _ in renderer.passes():
        if (rt, k) not in seen:
            seen.append((rt, k))
    return [("first pass of the frame", None)] + [(f"{rt.label} sample {k}", (rt, k)) for rt, k in seen]


def overlay_missing_line(r) -> str:
    """One short line for Renderer.overlay_missing (the full reason is in that attribute); it
    never names a backend: the view, and what is shown instead."""
    if not r.overlay_missing:
        return ""
    if r.is_overlay_view and r.view_spec is None:
        return f"view '{r.view}': not produced by this backend; final image shown"
    if not r.passes():  # no pass traced rays this frame
        return "no traced pass: turn an effect on"
    return f"view '{r.view}': no overlay this frame; final image shown"


def _draw_overlay_controls(r, rep) -> None:
    """Overlay source pass, heat-map scale, and one line saying what the overlay shows (or why
    there is none)."""
    from imgui_bundle import imgui

    if not r.backend.info.overlays:
        imgui.text_colored((1.0, 0.7, 0.3, 1.0), "this backend has no overlay views")
    spec = r.view_spec
    if spec is None:
        return
    choices = overlay_pass_choices(r)
    values = [v for _, v in choices]
    cur = values.index(r.overlay_pass) if r.overlay_pass in values else 0
    changed, idx = imgui.combo("overlay pass", cur, [label for label, _ in choices])
    if changed:
        r.overlay_pass = values[idx]
    if spec.kind == "heat":
        _, auto = imgui.checkbox("auto scale", r.overlay_scale <= 0)
        imgui.same_line(150)
        _, r.overlay_log = imgui.checkbox("log scale", r.overlay_log)
        if auto:
            r.overlay_scale = 0
        else:
            _, v = imgui.slider_int("scale max", max(int(r.overlay_scale), 1), 1, 2000, "%d",
                                    imgui.SliderFlags_.logarithmic)
            r.overlay_scale = max(int(v), 1)
    if r.overlay_source is not None:
        rt, k = r.overlay_source
        imgui.text(f"overlays of the {rt.label} pass, sample {k}")
    if spec.label:
        imgui.text_wrapped(spec.label)


def _u32(rgb, alpha: int = 255) -> int:
    from imgui_bundle import imgui

    return imgui.IM_COL32(int(rgb[0]), int(rgb[1]), int(rgb[2]), int(alpha))


def _text_box(dl, x: float, y: float, text: str, fg=(255, 255, 255), bg_alpha: int = 170) -> None:
    """Text at (x, y) (top left) on a dark box, readable over any image."""
    from imgui_bundle import imgui

    sz = imgui.calc_text_size(text)
    dl.add_rect_filled((x - 2, y - 1), (x + sz.x + 2, y + sz.y + 1), _u32((0, 0, 0), bg_alpha))
    dl.add_text((x, y), _u32(fg), text)


def draw_overlay_annotations(host, width: float, height: float, left: float = 0.0) -> None:
    """Over the image (behind the panel): why an overlay view shows the final image instead, or
    the view's annotations by kind: the heat map's legend, or an id view's per-tile numbers.
    `width` x `height`: the window in imgui units; the image fills it; `left`: panel width (the
    annotations stay right of it). Reads back only while an overlay view is shown."""
    from imgui_bundle import imgui

    r = host.renderer
    if r.overlay_missing and r.is_overlay_view:  # on the image too: the panel may be hidden (F1)
        line = imgui.get_text_line_height()
        _text_box(imgui.get_background_draw_list(), left + 10, height - line - 10, overlay_missing_line(r),
                  fg=(255, 150, 120), bg_alpha=220)
        return
    spec = r.view_spec
    if r.overlay_source is None or r.overlay_missing or spec is None:
        return
    dl = imgui.get_background_draw_list()
    if spec.kind == "heat":
        _draw_heat_legend(dl, r, spec, width, height, left)
    elif spec.kind == "ids":
        _draw_tile_labels(dl, r, spec, width, height, left)


def _draw_heat_legend(dl, r, spec, width: float, height: float, left: float) -> None:
    """Colour bar with ticks (the shader's scale, same colormap), the scale's maximum and how it
    was chosen, the frame's maximum, and the source pass; bottom right of the image."""
    from imgui_bundle import imgui

    from viewer.passes.overlay import heat_colors, heat_position, heat_ticks

    vmax = r.overlay_scale_max(spec.name)
    frame_max = r.overlay.read_max(spec.name)[0]
    rt, k = r.overlay_source
    how = "fixed" if r.overlay_scale > 0 else "auto"
    lines = [spec.label or spec.name.replace("_", " "), f"max {vmax} ({how}), frame max {frame_max}",
             f"{rt.label} #{k}, {'log' if r.overlay_log else 'linear'} scale, grey: no ray"]
    line = imgui.get_text_line_height()
    bar_w = float(min(300.0, max(120.0, width - left - 60.0)))
    box_w = max(bar_w + 12.0, *(imgui.calc_text_size(t).x for t in lines)) + 16.0
    bar_h = 14.0
    box_h = 3 * line + bar_h + line + 30.0
    bx, by = width - box_w - 8.0, height - box_h - 8.0
    dl.add_rect_filled((bx, by), (bx + box_w, by + box_h), _u32((20, 20, 20), 215), 4.0)
    white, grey = _u32((255, 255, 255)), _u32((210, 210, 210))
    x0 = bx + (box_w - bar_w) / 2
    dl.add_text((bx + 8, by + 6), white, lines[0])
    y0 = by + line + 12.0
    segs = 64
    pos = np.linspace(0.0, 1.0, segs + 1)
    # colours at evenly spaced positions of the bar: invert the scale to get the values there
    m = float(max(vmax, 1))
    at = np.expm1(pos * np.log1p(m)) if r.overlay_log else pos * m
    cols = heat_colors(at.astype(np.float32), vmax, r.overlay_log)
    for i in range(segs):
        a, b = x0 + bar_w * pos[i], x0 + bar_w * pos[i + 1]
        ca, cb = _u32(cols[i]), _u32(cols[i + 1])
        dl.add_rect_filled_multi_color((a, y0), (b + 0.5, y0 + bar_h), ca, cb, cb, ca)
    dl.add_rect((x0, y0), (x0 + bar_w, y0 + bar_h), grey)
    for t in heat_ticks(vmax, r.overlay_log):
        x = x0 + bar_w * float(heat_position(t, vmax, r.overlay_log))
        dl.add_line((x, y0 + bar_h), (x, y0 + bar_h + 4), grey)
        label = str(t)
        tw = imgui.calc_text_size(label).x
        dl.add_text((min(max(x - tw / 2, x0 - 6), x0 + bar_w - tw + 6), y0 + bar_h + 5), grey, label)
    dl.add_text((bx + 8, y0 + bar_h + line + 8), grey, lines[1])
    dl.add_text((bx + 8, y0 + bar_h + 2 * line + 10), grey, lines[2])


def _draw_tile_labels(dl, r, spec, width: float, height: float, left: float) -> None:
    """The id view's number per screen tile (where it fits) and a note saying what colours and
    numbers are (ids_labels of the view's OverlaySpec)."""
    from imgui_bundle import imgui

    from viewer.passes.overlay import ids_labels

    tiles = r.overlay_tiles(spec.name)
    colour, what = ids_labels(spec)
    rt, k = r.overlay_source
    line = imgui.get_text_line_height()
    if tiles is None:  # a backend without screen tiles: the colours only
        note = f"{rt.label} #{k}: colour = {colour}"
        _text_box(dl, max(left + 6, width - imgui.calc_text_size(note).x - 10), height - line - 8, note,
                  bg_alpha=210)
        return
    rects, counts, from_counts = tiles
    if not from_counts:
        what = "distinct ids in the tile"
    rw, rh = r.size
    sx, sy = width / rw, height / rh
    for (x, y, w, h), c in zip(rects.tolist(), counts.tolist(), strict=True):
        cx, cy = (x + w / 2) * sx, height - (y + h / 2) * sy
        label = str(c)
        sz = imgui.calc_text_size(label)
        if w * sx < sz.x + 6 or h * sy < line + 4 or cx - sz.x / 2 < left:
            continue  # too small to label, or under the panel
        _text_box(dl, cx - sz.x / 2, cy - sz.y / 2, label)
    note = f"{rt.label} #{k}: colour = {colour}; numbers = {what}"
    tw = imgui.calc_text_size(note).x
    _text_box(dl, max(left + 6, width - tw - 10), height - line - 8, note, bg_alpha=210)

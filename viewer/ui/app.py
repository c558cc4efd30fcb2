"""`rtwalk view`: the interactive window (moderngl-window, pyglet backend, imgui side panel).

The scene is loaded and its BVH built before the window opens. The window is the panel (left,
PANEL_WIDTH wide; F1 hides it) beside the image viewport (`--size`). Each frame: move the camera
(keys/mouse, or a recording being played back), render with progressive refinement
(viewer.progressive: one pass per effect at a reduced scale while the camera moves, sample passes
added when it stops, idle once converged; `--no-progressive` renders every frame at full quality),
draw the final texture into the viewport (at `render_scale` of its size), draw the panel.
Keys: WASD/QE move, drag (left or right button) to look, wheel = speed, shift = x5, F12
screenshot, R record, P play back, V next view of 'final' and the active backend's overlay views
(its info.overlays; legend and tile labels drawn over the image), O next overlay source pass, F1
panel on/off, Esc quits. An overlay view the active backend does not produce shows the
final image with a message on it, and F12 then saves nothing (the message says why).

For tests and the README screenshot: `--max-frames N` or RTWALK_VIEW_FRAMES=N quits after N
frames; RTWALK_VIEW_SCREENSHOT=path.png then saves the whole window, panel included (an existing
file is refused, as render -o refuses one, unless --force; F12 never replaces a file).
RTWALK_VIEW_SCALE=0.25..1 sets the initial render scale (default 1); RTWALK_VIEW_MODE=VIEW the
initial view (a `--view` argument, where the parser has one, takes precedence).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import moderngl
import numpy as np

from viewer.camera import Camera
from viewer.errors import RtwalkError
from viewer.gl.programs import ProgramCache
from viewer.progressive import DEFAULT_TARGET_MS
from viewer.ui.camera_controller import FlyCamera
from viewer.ui.panel import (
    PANEL_WIDTH,
    FrameHistory,
    chart_phases,
    draw_overlay_annotations,
    draw_panel,
    overlay_missing_line,
    overlay_pass_choices,
)

DEFAULT_RENDER_SCALE = 1.0  # progressive refinement lowers it while the camera moves
SCREENSHOT_DIR = Path("screenshots")
RECORDING_DIR = Path("recordings")
IDLE_SLEEP_S = 0.01  # a converged image: wait a little instead of spinning
MAX_DT = 0.25  # a stall (scene switch, screenshot) must not throw the camera across the scene
NO_DISPLAY_HINT = "use `rtwalk render`/`rtwalk bench` or run under xvfb-run (e.g. xvfb-run -a rtwalk view)"



def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- entry point


def frame_limit(args) -> int | None:
    """--max-frames N, else RTWALK_VIEW_FRAMES=N, else None (run until closed)."""
    n = getattr(args, "max_frames", None)
    source = "--max-frames"
    if n is None:
        env = os.environ.get("RTWALK_VIEW_FRAMES", "").strip()
        if not env:
            return None
        source = "RTWALK_VIEW_FRAMES"
        try:
            n = int(env)
        except ValueError:
            raise RtwalkError(f"{source}='{env}' is not an integer") from None
    if n < 1:
        raise RtwalkError(f"{source} must be >= 1, got {n}")
    return int(n)


def render_scale_from_env() -> float:
    """RTWALK_VIEW_SCALE (0.25..1), else DEFAULT_RENDER_SCALE; the panel slider changes it live."""
    env = os.environ.get("RTWALK_VIEW_SCALE", "").strip()
    if not env:
        return DEFAULT_RENDER_SCALE
    try:
        v = float(env)
    except ValueError:
        v = float("nan")
    if not 0.25 <= v <= 1.0:
        raise RtwalkError(f"RTWALK_VIEW_SCALE='{env}' must be a number in 0.25..1")
    return v


def initial_view(args) -> str:
    """`--view` if the parser has it, else RTWALK_VIEW_MODE, else final; checked before the window
    against every registered backend's views (the window says so when the active one lacks it)."""
    from viewer.backends import registered_infos
    from viewer.passes.overlay import all_view_names

    views = all_view_names(registered_infos())
    view = getattr(args, "view", None)
    source = "--view"
    if view is None:
        view = os.environ.get("RTWALK_VIEW_MODE", "").strip() or "final"
        source = "RTWALK_VIEW_MODE"
    if view not in views:
        raise RtwalkError(f"{source}: unknown view '{view}' (choose from {', '.join(views)})")
    return view


def require_display() -> None:
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise RtwalkError(f"no display (DISPLAY is not set) for the `view` window; {NO_DISPLAY_HINT}")


def window_class():
    """moderngl-window's pyglet window class; importing it connects to the display (checked early)."""
    require_display()
    try:
        import moderngl_window as mglw

        return mglw.get_local_window_cls("pyglet")
    except Exception as exc:  # pyglet connects to the X server on import (NoSuchDisplayException)
        where = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY", "")
        raise RtwalkError(f"no display: cannot connect to '{where}' ({type(exc).__name__}); "
                          f"{NO_DISPLAY_HINT}") from None


def display_size() -> tuple[int, int] | None:
    """The size of the display's default screen in pixels (pyglet), None where it cannot tell."""
    try:
        import pyglet

        display = pyglet.display.get_display() if hasattr(pyglet, "display") else pyglet.canvas.get_display()
        screen = display.get_default_screen()
        w, h = int(screen.width), int(screen.height)
    except Exception:  # no screen list on this platform: the driver's limits still apply (Renderer)
        return None
    return (w, h) if w > 0 and h > 0 else None


def fit_to_screen(size: tuple[int, int], screen: tuple[int, int] | None,
                  panel: int = PANEL_WIDTH) -> tuple[int, int]:
    """The image size whose window (image + panel beside it) fits `screen`: `size` itself when it
    fits, else scaled down keeping its aspect ratio (as image viewers fit a window to the screen).
    A window larger than the screen cannot be seen whole, and under a virtual X server a 10000x10000
    one was accepted and took minutes per frame."""
    if screen is None:
        return size
    w, h = size
    room_w, room_h = screen[0] - panel, screen[1]
    if w <= room_w and h <= room_h:
        return size
    scale = min(room_w / w, room_h / h)
    return max(1, int(w * scale)), max(1, int(h * scale))


def open_window(size: tuple[int, int], title: str):
    """A pyglet window with an OpenGL 4.5 core context (RtwalkError when there is none)."""
    import moderngl_window as mglw

    window_cls = window_class()
    try:
        window = window_cls(title=title, gl_version=(4, 5), size=size, resizable=True, vsync=False,
                            aspect_ratio=None)
    except Exception as exc:
        raise RtwalkError(f"cannot open a window with an OpenGL 4.5 core context ({_first_line(exc)}); "
                          f"{NO_DISPLAY_HINT}") from None
    mglw.activate_context(window=window)
    window.exit_key = None  # Esc is handled here so that it does not quit while typing in the panel
    return window


def _new_file(folder: Path, stem: str, suffix: str) -> Path:
    """A file created here under a name no other file had (stem, stem-1, ...): created exclusively,
    so a screenshot never replaces one, even one another window saved in the same second."""
    n = 0
    while True:
        path = folder / (f"{stem}-{n}{suffix}" if n else f"{stem}{suffix}")
        try:
            with open(path, "xb"):
                return path
        except FileExistsError:
            n += 1


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def run_viewer(args) -> int:
    from viewer.cli_args import check_image_output, check_positive, request_from, scene_from_args, warn_no_mirrors
    from viewer.recording import load_recording
    from viewer.ui.frame_log import check_frame_log

    max_frames = frame_limit(args)
    check_positive(getattr(args, "frame_target_ms", None), "--frame-target-ms")  # 0 and nan were taken
    render_scale_from_env()  # bad values fail before the window opens
    view = initial_view(args)
    shot = os.environ.get("RTWALK_VIEW_SCREENSHOT", "").strip() or None
    force = bool(getattr(args, "force", False))  # view --force; demo has none: never replace
    if shot:
        check_image_output(shot, "RTWALK_VIEW_SCREENSHOT")
        if Path(shot).expanduser().exists() and not force:  # as render -o: an earlier picture is kept
            how = "pass --force" if hasattr(args, "force") else "run `rtwalk view --force`"  # demo has no --force
            raise RtwalkError(f"RTWALK_VIEW_SCREENSHOT={shot}: exists; {how} to replace it, or choose another file")
    frame_log = getattr(args, "frame_log", None)
    if frame_log:
        check_frame_log(frame_log, force)
    window_class()  # fail on a missing display before spending time on the scene
    req = request_from(args)
    settings, backend_options, size = req.settings, req.backend_options, req.size
    screen = display_size()
    fitted = fit_to_screen(size, screen)
    if screen is not None and fitted[0] < 64:  # the panel alone fills the screen
        raise RtwalkError(f"the {screen[0]}x{screen[1]} display has no room for the image beside the "
                          f"{PANEL_WIDTH}-pixel panel; use a larger screen or `rtwalk render`")
    if fitted != size:
        log(f"rtwalk view: warning: --size {size[0]}x{size[1]} with the {PANEL_WIDTH}-pixel panel does not fit the "
            f"{screen[0]}x{screen[1]} display; the window shows {fitted[0]}x{fitted[1]} (larger images: rtwalk render)")
        size = fitted
    rec_path = getattr(args, "recording", None)
    recording = load_recording(rec_path) if rec_path else None
    quiet = bool(getattr(args, "quiet", False))
    if not quiet:
        log("rtwalk view: loading the scene before opening the window ...")
    prepared = scene_from_args(args, recording)
    mirrors_note = warn_no_mirrors(settings, prepared.scene)
    window = open_window((size[0] + PANEL_WIDTH, size[1]), f"rtwalk - {prepared.scene.name}")
    app = None
    try:
        app = ViewerApp(window, prepared, settings, args.backend, backend_options=backend_options,
                        recording=recording,
                        scene_arg=getattr(args, "scene", None), max_frames=max_frames, window_shot=shot,
                        quiet=quiet, progressive=getattr(args, "progressive", True),
                        frame_target_ms=getattr(args, "frame_target_ms", DEFAULT_TARGET_MS),
                        denoise=getattr(args, "denoise", "on") == "on",
                        frame_log=getattr(args, "frame_log", None))
        app.renderer.view = view
        if mirrors_note:
            app.status = mirrors_note.removeprefix("rtwalk: warning: ")
        return app.run()
    finally:
        if app is not None:
            app.release()
        _ = window.ctx.error  # a pending GL error would make pyglet's close raise
        try:
            window.close()
        except Exception as exc:  # closing must not turn a clean exit into a traceback
            if not quiet:
                log(f"rtwalk view: warning: closing the window: {_first_line(exc)}")


# --------------------------------------------------------------------------- the window


class ViewerApp:
    def __init__(self, window, prepared, settings, backend: str, recording=None, scene_arg: str | None = None,
                 backend_options: dict[str, str] | None = None, max_frames: int | None = None,
                 window_shot: str | None = None, quiet: bool = False, progressive: bool = True,
                 frame_target_ms: float = DEFAULT_TARGET_MS, denoise: bool = True, frame_log: str | None = None):
        from imgui_bundle import imgui, implot
        from moderngl_window.integrations.imgui_bundle import ModernglWindowRenderer

        from viewer.progressive import Progressive
        from viewer.recording import Recorder
        from viewer.renderer import Renderer

        self.wnd = window
        self.ctx: moderngl.Context = window.ctx
        self.scene = prepared.scene
        self.scene_arg = scene_arg
        self.quiet = quiet
        self.max_frames = max_frames
        self.window_shot = window_shot
        from viewer.ui.frame_log import FrameLog

        self.frame_log = FrameLog(frame_log) if frame_log else None  # --frame-log: written on close
        self.render_scale = render_scale_from_env()
        self.show_panel = True
        self.status = ""
        self.backend_error = ""
        self.last_report = None
        self.history = FrameHistory()
        self.frames = 0
        self.last_frame_ms = 0.0  # the last loop iteration that rendered (the panel's fps line)
        self.idle = False  # the last frame rendered nothing (progressive image converged)
        self._rendered_last = False
        self._render_ms = 0.0
        self._pending: list[Callable[[], None]] = []

        self.renderer = Renderer(self.ctx, prepared.scene, prepared.bvh, self._render_size(), backend, settings,
                                 backend_options)
        self.renderer.strict_overlays = False  # an overlay view the backend cannot feed: a panel line
        self.progressive = (Progressive(self.renderer, self._render_size(), frame_target_ms,
                                        resize=self._resize_renderer) if progressive else None)
        self.step = None  # the progressive step of the last frame (the panel shows it)
        from viewer.ui.denoise_view import DisplayDenoiser

        self.denoiser = DisplayDenoiser(self.ctx) if denoise else None  # --denoise on: the picture shown
        self.renderer.denoise = denoise  # the device filter runs inside each frame (its cost is timed)
        start = self.scene.default_camera or _overview_camera(self.scene)
        self.fly = FlyCamera.from_camera(start, self.renderer.diagonal)
        self.camera: Camera = self.fly.camera()

        self.recorder = Recorder()
        self.cli_recording = recording
        self.session_recording = None
        self.playing = None  # the Recording being played back
        self._play_t0 = 0.0
        self._anim_t0 = time.perf_counter()  # scene time 0 of an animated scene (outside playback)
        self._looking = False
        # --recording: the user asked to see it: played from the start once the first frame (shader
        # compilation, a full-size image) is up, so the path's clock does not run during that frame
        self._autoplay = recording is not None

        # imgui: context, renderer, extra keys (ctrl+A/C for the read-only camera field)
        imgui.create_context()
        implot.create_context()  # the panel's phase chart
        io = imgui.get_io()
        io.set_ini_filename("")  # no imgui.ini in the working directory
        self.imgui = ModernglWindowRenderer(window)
        keys = window.keys
        self.imgui.REVERSE_KEYMAP.update({keys.A: imgui.Key.a, keys.C: imgui.Key.c, keys.V: imgui.Key.v,
                                          keys.X: imgui.Key.x, keys.Y: imgui.Key.y, keys.Z: imgui.Key.z,
                                          keys.LEFT_CTRL: imgui.Key.left_ctrl,
                                          keys.LEFT_SHIFT: imgui.Key.left_shift,
                                          keys.RIGHT_SHIFT: imgui.Key.right_shift})

        self.programs = ProgramCache(self.ctx)  # the window's own programs (the blit)
        self.blit = self.programs.get("fullscreen.vert", "blit.frag")
        self.blit["image"] = 0
        self.blit_vao = self.ctx.vertex_array(self.blit, [])
        self.sampler = self.ctx.sampler(filter=(moderngl.LINEAR, moderngl.LINEAR), repeat_x=False,
                                        repeat_y=False)

        window.key_event_func = self.on_key
        window.mouse_position_event_func = self.on_mouse_position
        window.mouse_drag_event_func = self.on_mouse_drag
        window.mouse_press_event_func = self.on_mouse_press
        window.mouse_release_event_func = self.on_mouse_release
        window.mouse_scroll_event_func = self.on_mouse_scroll
        window.unicode_char_entered_func = self.imgui.unicode_char_entered
        window.resize_func = self.on_resize

    # -- helpers -------------------------------------------------------------------------------
    def panel_width(self) -> float:
        """The panel's width in window coordinates (0 when hidden)."""
        # a window opened at --size plus the panel leaves exactly --size to the image (down to --size
        # 227 wide); a narrower window (resized by hand) keeps 40% for the image
        return float(min(PANEL_WIDTH, self.wnd.size[0] * 0.6)) if self.show_panel else 0.0

    def viewport(self) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the image in framebuffer pixels: the window right of the panel."""
        bw, bh = self.wnd.buffer_size
        x = int(round(self.panel_width() * bw / max(self.wnd.size[0], 1)))
        return x, 0, max(1, bw - x), max(1, bh)

    def _render_size(self) -> tuple[int, int]:
        _, _, w, h = self.viewport()
        s = float(np.clip(self.render_scale, 0.1, 1.0))
        return max(1, int(round(w * s))), max(1, int(round(h * s)))

    def _resize_renderer(self, size: tuple[int, int]) -> None:
        if tuple(self.renderer.size) == tuple(size):
            return
        # With one of the renderer's framebuffers bound, moderngl re-binds the released (deleted)
        # framebuffer after creating the new ones: GL_INVALID_OPERATION, which pyglet later reports.
        self.ctx.screen.use()
        self.renderer.resize(size)
        _ = self.ctx.error  # consume anything left over so it is not blamed on pyglet's next call

    def say(self, msg: str) -> None:
        """Show in the panel and print (the paths of saved files are wanted on the terminal too)."""
        self.status = msg
        if not self.quiet:
            log(msg)

    def current_camera(self) -> Camera:
        return self.camera

    def mode_line(self) -> str:
        if self.playing is not None:
            t = min(time.perf_counter() - self._play_t0, self.playing.duration)
            return f"PLAYING {t:5.1f} / {self.playing.duration:.1f} s (P stops)"
        if self.recorder.recording:
            return f"RECORDING {self.recorder.keyframe_count} keyframes (R stops and saves)"
        return ""

    def copy_to_clipboard(self, text: str) -> None:
        from imgui_bundle import imgui

        imgui.set_clipboard_text(text)
        try:
            self.wnd._window.set_clipboard_text(text)  # system clipboard through pyglet
            self.status = "copied to the clipboard"
        except Exception as exc:  # no clipboard owner support on this display
            self.status = f"clipboard unavailable ({_first_line(exc)}); select the field and copy"

    # -- actions (deferred to the start of the next frame: they render or touch GL state) --------
    def switch_backend(self, name: str) -> None:
        self._pending.append(lambda: self._switch_backend(name))

    def _switch_backend(self, name: str) -> None:
        try:  # on failure Renderer.set_backend keeps the current backend
            self.renderer.set_backend(name)
            self.backend_error = ""
            self.say(f"backend: {name}")
        except RtwalkError as exc:
            self.backend_error = f"{name}: {exc}"
        except Exception as exc:  # a backend that fails in an unexpected way must not end the session
            self.backend_error = f"{name}: {type(exc).__name__}: {_first_line(exc)}"

    def take_screenshot(self) -> None:
        self._pending.append(self._screenshot)

    def _screenshot(self) -> None:
        from PIL import Image

        # the saved image is always at the full viewport size and quality, of the current view (V may
        # have changed it since the last frame), so it is rendered again here
        self._resize_renderer(tuple(self.viewport()[2:]))
        self.renderer.render(self.camera)
        if self.progressive is not None:
            self.progressive.invalidate()
        if self.renderer.overlay_missing:  # the image is not the view asked for: say so, save nothing
            self.say(f"screenshot not saved: {overlay_missing_line(self.renderer)}")
            return
        img = (self.renderer.read_denoised("library", self.camera) if self.denoiser is not None
               else self.renderer.read_image())
        stamp = time.strftime("%Y%m%d-%H%M%S")
        path = SCREENSHOT_DIR
        try:
            SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
            path = _new_file(SCREENSHOT_DIR, f"rtwalk-{stamp}", ".png")
            Image.fromarray(img).save(path)
        except OSError as exc:
            if path != SCREENSHOT_DIR:  # the name was taken for this picture: no empty file left
                path.unlink(missing_ok=True)
            self.say(f"screenshot failed: {path}: {exc.strerror or exc}")
            return
        self.say(f"screenshot: {path} ({img.shape[1]}x{img.shape[0]})")

    def toggle_recording(self) -> None:
        self._pending.append(self._toggle_recording)

    def _toggle_recording(self) -> None:
        if self.recorder.recording:
            self._stop_recording()
            return
        if self.playing is not None:
            self._stop_playback("playback stopped")
        identity = self.scene.identity or self.scene_arg or self.scene.name
        try:
            self.recorder.start(identity, tuple(self.wnd.buffer_size), fps=30)
        except RtwalkError as exc:
            self.say(f"cannot record: {exc}")
            return
        self.recorder.add(time.perf_counter(), self.camera)
        self.say("recording the camera path (R stops and saves)")

    def _stop_recording(self) -> None:
        try:
            path = self.recorder.save(RECORDING_DIR)
        except RtwalkError as exc:
            self.say(f"recording not saved: {exc}")
            return
        rec = self.recorder.last
        self.session_recording = rec
        self.say(f"recording: {path} ({len(rec.keyframes)} keyframes, {rec.duration:.1f} s; P plays it)")

    def toggle_playback(self) -> None:
        self._pending.append(self._toggle_playback)

    def _toggle_playback(self) -> None:
        if self.playing is not None:
            self._stop_playback("playback stopped")
            return
        if self.recorder.recording:
            self._stop_recording()
        rec = self.session_recording or self.cli_recording
        if rec is None:
            self.say("nothing to play: press R to record a camera path, or start with --recording FILE")
            return
        self.playing = rec
        self._play_t0 = time.perf_counter()
        name = rec.source if rec.source is not None else "recording"
        self.say(f"playing {name} ({rec.duration:.1f} s; P stops)")

    def _stop_playback(self, msg: str) -> None:
        self.playing = None
        self.fly.set_camera(self.camera)  # take over from where the path was
        self.say(msg)

    # -- events ----------------------------------------------------------------------------------
    def on_resize(self, width: int, height: int) -> None:
        self.imgui.resize(width, height)

    def on_key(self, key, action, modifiers) -> None:
        from imgui_bundle import imgui

        io = imgui.get_io()
        io.add_key_event(imgui.Key.mod_ctrl, bool(modifiers.ctrl))
        io.add_key_event(imgui.Key.mod_shift, bool(modifiers.shift))
        self.imgui.key_event(key, action, modifiers)
        keys = self.wnd.keys
        if action != keys.ACTION_PRESS or io.want_capture_keyboard:
            return
        if key == keys.ESCAPE:
            self.wnd.is_closing = True
        elif key == keys.F12:
            self.take_screenshot()
        elif key == keys.R:
            self.toggle_recording()
        elif key == keys.P:
            self.toggle_playback()
        elif key == keys.F1:
            self.show_panel = not self.show_panel
        elif key == keys.V:
            self.cycle_view()
        elif key == keys.O:
            self.cycle_overlay_pass()

    def cycle_view(self) -> None:
        """V: final -> each overlay view of the active backend -> final (any other view goes to final)."""
        from viewer.passes.overlay import cycled_views

        r = self.renderer
        views = cycled_views(r.backend.info)
        i = views.index(r.view) if r.view in views else -1
        r.view = views[(i + 1) % len(views)]
        self.say(f"view: {r.view}" if len(views) > 1 else f"view: {r.view} (this backend has no overlay views)")

    def cycle_overlay_pass(self) -> None:
        """O: the overlay views' source pass: first pass of the frame, then each pass in turn."""
        r = self.renderer
        choices = overlay_pass_choices(r)
        values = [v for _, v in choices]
        i = values.index(r.overlay_pass) if r.overlay_pass in values else 0
        label, r.overlay_pass = choices[(i + 1) % len(choices)]
        self.say(f"overlay pass: {label}")

    def on_mouse_position(self, x, y, dx, dy) -> None:
        self.imgui.mouse_position_event(x, y, dx, dy)

    def on_mouse_press(self, x, y, button) -> None:
        from imgui_bundle import imgui

        self.imgui.mouse_press_event(x, y, button)
        if button in (self.wnd.mouse.left, self.wnd.mouse.right) and not imgui.get_io().want_capture_mouse:
            self._looking = True

    def on_mouse_release(self, x, y, button) -> None:
        self.imgui.mouse_release_event(x, y, button)
        states = self.wnd.mouse_states
        if not (states.left or states.right):
            self._looking = False

    def on_mouse_drag(self, x, y, dx, dy) -> None:
        self.imgui.mouse_drag_event(x, y, dx, dy)
        if self._looking and self.playing is None:
            self.fly.look(dx, dy)

    def on_mouse_scroll(self, x_offset, y_offset) -> None:
        from imgui_bundle import imgui

        self.imgui.mouse_scroll_event(x_offset, y_offset)
        if not imgui.get_io().want_capture_mouse:
            self.fly.scroll(y_offset)

    # -- frame -----------------------------------------------------------------------------------
    def _movement(self) -> tuple[list[str], bool]:
        from imgui_bundle import imgui

        if imgui.get_io().want_capture_keyboard:
            return [], False
        k = self.wnd.keys
        held = self.wnd.is_key_pressed
        actions = [a for key, a in ((k.W, "forward"), (k.S, "back"), (k.A, "left"), (k.D, "right"),
                                    (k.Q, "down"), (k.E, "up")) if held(key)]
        return actions, held(k.LEFT_SHIFT) or held(k.RIGHT_SHIFT)

    def update_camera(self, now: float, dt: float) -> None:
        if self.playing is not None:
            rec = self.playing
            t = now - self._play_t0
            self.camera = rec.camera_at(rec.start_time + min(t, rec.duration))
            self.renderer.set_scene_time(rec.scene_time_at(rec.start_time + min(t, rec.duration)))
            self.fly.set_camera(self.camera)
            if t >= rec.duration:
                self._stop_playback("playback finished")
            return
        if self.renderer.scene.animated:  # an animated scene runs on the wall clock outside playback
            self.renderer.set_scene_time(now - self._anim_t0)
        actions, fast = self._movement()
        self.fly.update(dt, actions, fast)
        self.camera = self.fly.camera()
        if self.recorder.recording:
            self.recorder.add(now, self.camera)

    def _render_once(self):
        """One frame: a progressive step (None when converged and idle), or a full-quality frame
        (--no-progressive, and overlay views, which show one traced pass's diagnostics)."""
        r, prog = self.renderer, self.progressive
        size = self._render_size()
        if prog is None or r.is_overlay_view:
            self.step = None
            self._resize_renderer(size)
            if prog is not None:
                prog.invalidate()
            return r.render(self.camera)
        prog.full_size = size
        self.step = prog.frame(self.camera)
        if self.step.report is None:
            time.sleep(IDLE_SLEEP_S)  # converged: nothing to draw but the panel
        return self.step.report

    def _render(self):
        from viewer.backends import backend_names

        r = self.renderer
        fallback = backend_names()[0]  # the registry's first backend
        try:
            return self._render_once()
        except RtwalkError as exc:
            if r.backend_name == fallback:
                raise
            self.backend_error = f"{r.backend_name}: {exc} (back to {fallback})"
            r.set_backend(fallback)
            if self.progressive is not None:
                self.progressive.invalidate()
            return self._render_once()

    def frame(self, now: float, dt: float, frame_ms: float) -> None:
        from imgui_bundle import imgui

        pending, self._pending = self._pending, []
        for action in pending:
            action()
        imgui.get_io().delta_time = max(dt, 1e-4)
        if self._rendered_last and frame_ms > 0:  # frame_ms: the previous iteration, which rendered
            self.last_frame_ms = frame_ms
            if self.progressive is not None:  # the panel, blit and swap count against the budget too
                extra = max(frame_ms - self._render_ms, 0.0)
                self.progressive.extra_ms += 0.3 * (extra - self.progressive.extra_ms)
        self.update_camera(now, dt)
        t_render = time.perf_counter()
        report = self._render()
        self._render_ms = (time.perf_counter() - t_render) * 1e3
        self._rendered_last, self.idle = report is not None, report is None
        if report is not None:
            self.last_report = report
            self.history.add(frame_ms if frame_ms > 0 else report.wall_ms, sum(report.gpu_ms.values()),
                             chart_phases(report.gpu_ms, self.renderer.backend.info.phases), report.backend_stats)

        # --denoise on: the device filter or the library's still (viewer.ui.denoise_view), drawn
        # into their own targets before the window's framebuffer is set up
        shown = (self.renderer.final_texture if self.denoiser is None
                 else self.denoiser.texture(self.renderer, self.camera, self.step, report is not None))
        ctx = self.ctx
        w, h = self.wnd.buffer_size
        vx, vy, vw, vh = self.viewport()
        ctx.screen.use()
        ctx.viewport = (0, 0, w, h)
        ctx.scissor = None
        ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.clear(0.0, 0.0, 0.0, 1.0)
        ctx.viewport = (vx, vy, vw, vh)
        self.sampler.use(0)
        shown.use(0)
        self.blit["viewport"] = (float(vw), float(vh))
        self.blit["origin"] = (float(vx), float(vy))
        self.blit_vao.render(moderngl.TRIANGLES, vertices=3)
        self.sampler.clear(0)  # the renderer's passes sample integer textures on unit 0 unfiltered
        ctx.viewport = (0, 0, w, h)

        imgui.new_frame()
        ww, wh = self.wnd.size
        panel_w = self.panel_width()
        draw_overlay_annotations(self, ww, wh, panel_w)
        if self.show_panel:
            draw_panel(self, panel_w, wh)
        imgui.render()
        self.imgui.render(imgui.get_draw_data())
        if self._autoplay:
            self._autoplay = False
            self.toggle_playback()

    def save_window(self, path: str) -> Path:
        """The default framebuffer as it is now (scene + panel), as PNG."""
        from PIL import Image

        w, h = self.wnd.buffer_size
        data = np.frombuffer(self.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1), np.uint8)
        img = data.reshape(h, w, 3)[::-1]
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.ascontiguousarray(img)).save(p)
        except OSError as exc:
            raise RtwalkError(f"cannot write the window screenshot {p}: {exc.strerror or exc}") from None
        return p

    def run(self) -> int:
        if not self.quiet:
            log("rtwalk view: WASD/QE move, drag to look, wheel = speed, shift = x5; F12 screenshot, "
                "R record, P play, V view (final/overlays), O overlay pass, F1 panel, Esc quits")
        last = time.perf_counter()
        frame_ms = 0.0
        try:
            while not self.wnd.is_closing:
                now = time.perf_counter()
                dt = min(now - last, MAX_DT) if self.frames else 0.0
                if self.frames:
                    frame_ms = (now - last) * 1e3
                    self._log_frame(frame_ms)
                last = now
                self.frame(now, dt, frame_ms)
                self._logged = (self.step, self.last_report if self._rendered_last else None,
                                self._render_ms, tuple(self.renderer.size))
                self.frames += 1
                if self.max_frames is not None and self.frames >= self.max_frames:
                    if self.window_shot:
                        p = self.save_window(self.window_shot)
                        if not self.quiet:
                            log(f"window screenshot: {p}")
                    self.wnd.swap_buffers()
                    self._log_frame((time.perf_counter() - last) * 1e3)
                    break
                self.wnd.swap_buffers()
        finally:
            if self.frame_log is not None:
                path = self.frame_log.write()
                if not self.quiet:
                    log(f"{self.frame_log.line()} ({path})")
        if self.recorder.recording:  # do not lose a path when the window is closed while recording
            self._stop_recording()
        return 0

    def _log_frame(self, iteration_ms: float) -> None:
        """--frame-log: the iteration that just ended (its frame's step, report and sizes)."""
        if self.frame_log is not None and getattr(self, "_logged", None) is not None:
            step, report, render_ms, size = self._logged
            self.frame_log.add(self.frames - 1, iteration_ms, render_ms, step, report, size)

    def release(self) -> None:
        from imgui_bundle import imgui, implot

        try:
            self.imgui.shutdown()
            implot.destroy_context()
            imgui.destroy_context()
        finally:
            for obj in (self.blit_vao, self.sampler):
                obj.release()
            self.programs.release()
            if self.denoiser is not None:
                self.denoiser.release()
            self.renderer.release()


def _overview_camera(scene) -> Camera:
    """A view of the whole scene for scenes without a default camera."""
    lo, hi = (np.asarray(v, np.float64) for v in scene.bounds)
    centre, diag = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 1e-6)
    eye = centre + np.array([0.35, 0.3, 0.9]) * diag * 0.7
    return Camera.look_at(eye, centre, fov_y=60.0)

"""Camera-path recordings: a versioned JSON list of keyframes, interpolated smoothly.

File format (version 2; version 1 files, which have no scene time, still load)::

    {"format": "rtwalk-recording", "version": 1,
     "scene": {"builtin": "city", "size": 150000, "seed": 1},   # or {"file": "sponza-dabrovic/sponza.obj"}
     "resolution": [1280, 720], "fps": 30,
     "keyframes": [{"time": 0.0, "position": [x, y, z], "orientation": [w, x, y, z], "fov_y": 60.0}, ...]}

Rules enforced by `load_recording` (each violation is one `RtwalkError` line naming the file):

* ``scene`` has exactly one of ``builtin`` (a name, with optional integer ``size`` > 0 and ``seed``)
  or ``file`` (a path; see `resolve_scene_spec`).
* ``resolution`` is two positive integers (at most 16384 each); ``fps`` is a finite number in (0, 1000].
* at least ONE keyframe: a single keyframe is a still (duration 0, one frame);
  keyframe times are finite and strictly increasing (the first need not be 0);
  positions are 3 finite numbers; orientations 4 finite numbers, not all zero (they are
  normalised on load); ``fov_y`` is a finite number of degrees strictly inside (1, 179).
* unknown keys are ignored (room for additions that keep version 1 readable).
* version 2 adds an optional ``"scene_time"`` (seconds, finite) per keyframe: the time of an
  animated scene (``viewer.scene.Scene.animation``) shown at that keyframe. Either every keyframe
  has one or none: without it the scene time is the keyframe clock itself (``time``). Scene times
  are interpolated linearly between keyframes (they may stand still or run at another rate than
  the camera clock). A file is written as version 1 when no keyframe has a scene time, so paths
  of static scenes stay readable by older builds.

Keyframe indices in messages are 0-based positions in the ``keyframes`` array.

Interpolation (`Recording.camera_at`): positions follow a uniform Catmull-Rom spline through the
keyframes (each segment parametrised by u = (t - t_i) / (t_{i+1} - t_i); the first and last
keyframes are duplicated for the boundary tangents), orientations are slerped along the
shortest arc, fov_y is linear; t is clamped to [first time, last time]. Keyframe times are hit
exactly. Frames are sampled at a fixed rate (`Recording.frame_times`), never from the wall clock.
"""

from __future__ import annotations

import json
import math
import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from viewer.camera import Camera
from viewer.errors import RtwalkError
from viewer.paths import SHARED_SCENES

FORMAT_TAG = "rtwalk-recording"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
MIN_FOV, MAX_FOV = 1.0, 179.0
MAX_RESOLUTION = 16384
MAX_FPS = 1000.0
#: `Recorder.add` drops a keyframe closer than this (seconds) to the previously kept one.
RECORDER_MIN_STEP = 0.1



# --------------------------------------------------------------------------- data


@dataclass(eq=False)
class Keyframe:
    time: float  # seconds
    position: np.ndarray  # float64 (3,)
    orientation: np.ndarray  # float64 (4,), unit quaternion (w, x, y, z), camera-to-world
    fov_y: float = 60.0  # degrees
    scene_time: float | None = None  # animated scenes: the scene's time at this keyframe (None: `time`)

    def __post_init__(self) -> None:
        self.time = float(self.time)
        self.scene_time = None if self.scene_time is None else float(self.scene_time)
        self.position = np.asarray(self.position, np.float64).reshape(3).copy()
        self.orientation = np.asarray(self.orientation, np.float64).reshape(4).copy()
        self.fov_y = float(self.fov_y)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Keyframe):
            return NotImplemented
        return (self.time == other.time and self.fov_y == other.fov_y and self.scene_time == other.scene_time
                and np.array_equal(self.position, other.position)
                and np.array_equal(self.orientation, other.orientation))

    @staticmethod
    def from_camera(time_s: float, camera: Camera) -> Keyframe:
        return Keyframe(time_s, camera.position, _unit(camera.orientation), camera.fov_y)

    def camera(self) -> Camera:
        return Camera(self.position.copy(), self.orientation.copy(), self.fov_y)

    def to_dict(self) -> dict:
        d = {"time": self.time, "position": [float(v) for v in self.position],
             "orientation": [float(v) for v in self.orientation], "fov_y": self.fov_y}
        if self.scene_time is not None:
            d["scene_time"] = self.scene_time
        return d


@dataclass
class Recording:
    scene: dict  # {"builtin": name, "size"?: int, "seed"?: int} or {"file": path}
    resolution: tuple[int, int]  # (width, height)
    fps: float
    keyframes: list[Keyframe]
    source: Path | None = field(default=None, compare=False)  # file it was loaded from / saved to

    # ---- timing

    @property
    def start_time(self) -> float:
        return self.keyframes[0].time

    @property
    def end_time(self) -> float:
        return self.keyframes[-1].time

    @property
    def duration(self) -> float:
        """Seconds from the first to the last keyframe (0 for a single-keyframe still)."""
        return self.end_time - self.start_time

    def _fps(self, fps: float | None) -> float:
        f = self.fps if fps is None else fps
        try:
            f = float(f)
        except (TypeError, ValueError):
            raise RtwalkError(f"{self._name()}: fps must be a number, got {_short(fps)}") from None
        if not math.isfinite(f) or f <= 0:
            raise RtwalkError(f"{self._name()}: fps must be a finite number > 0, got {_short(fps)}")
        return f

    def frame_count(self, fps: float | None = None) -> int:
        """Number of frames: floor(duration * fps) + 1 (a tiny tolerance absorbs float rounding)."""
        f = self._fps(fps)
        return int(math.floor(self.duration * f + 1e-9)) + 1

    def frame_times(self, fps: float | None = None) -> np.ndarray:
        """t_i = t0 + i / fps for i in range(frame_count(fps)); float64, deterministic."""
        f = self._fps(fps)
        return self.start_time + np.arange(self.frame_count(f), dtype=np.float64) / f

    def camera_for_frame(self, n: int, fps: float | None = None) -> Camera:
        count = self.frame_count(fps)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n < count:
            raise RtwalkError(f"{self._name()}: frame {n!r} out of range (the path has {count} frames)")
        f = self._fps(fps)
        return self.camera_at(self.start_time + int(n) / f)

    def scene_time_for_frame(self, n: int, fps: float | None = None) -> float:
        """The animated scene's time at frame n (see scene_time_at)."""
        self.camera_for_frame(n, fps)  # range check
        return self.scene_time_at(self.start_time + int(n) / self._fps(fps))

    def scene_time_at(self, t: float) -> float:
        """Scene time at camera time t: linear between the keyframes' scene_time values (clamped to
        the path), or t itself when the keyframes carry none."""
        t = float(t)
        kfs = self.keyframes
        if not kfs or kfs[0].scene_time is None:
            return t
        times = np.array([k.time for k in kfs])
        values = np.array([k.scene_time for k in kfs], np.float64)
        return float(np.interp(t, times, values))

    @property
    def has_scene_time(self) -> bool:
        return bool(self.keyframes) and self.keyframes[0].scene_time is not None

    # ---- interpolation

    def camera_at(self, t: float) -> Camera:
        """Camera at time t (seconds, same clock as the keyframe times; clamped to the path)."""
        t = float(t)
        if not math.isfinite(t):
            raise RtwalkError(f"{self._name()}: camera time must be finite, got {t}")
        kfs = self.keyframes
        if not kfs:
            raise RtwalkError(f"{self._name()}: recording has no keyframes")
        if t <= kfs[0].time or len(kfs) == 1:
            return kfs[0].camera()
        if t >= kfs[-1].time:
            return kfs[-1].camera()
        times = np.array([k.time for k in kfs])
        i = int(np.searchsorted(times, t, side="right")) - 1
        i = min(max(i, 0), len(kfs) - 2)
        k1, k2 = kfs[i], kfs[i + 1]
        u = (t - k1.time) / (k2.time - k1.time)
        if u <= 0.0:
            return k1.camera()
        p0 = kfs[i - 1].position if i > 0 else k1.position
        p3 = kfs[i + 2].position if i + 2 < len(kfs) else k2.position
        pos = catmull_rom(p0, k1.position, k2.position, p3, u)
        rot = slerp(k1.orientation, k2.orientation, u)
        fov = k1.fov_y + (k2.fov_y - k1.fov_y) * u
        return Camera(pos, rot, float(fov))

    # ---- (de)serialisation

    def to_dict(self) -> dict:
        return {"format": FORMAT_TAG, "version": FORMAT_VERSION if self.has_scene_time else 1,
                "scene": dict(self.scene),
                "resolution": [int(self.resolution[0]), int(self.resolution[1])],
                "fps": _num_out(self.fps), "keyframes": [k.to_dict() for k in self.keyframes]}

    @property
    def scene_name(self) -> str:
        """Short name for file names and titles: the builtin name or the scene file's stem."""
        if "builtin" in self.scene:
            return str(self.scene["builtin"])
        return Path(str(self.scene.get("file", "scene"))).stem or "scene"

    def _name(self) -> str:
        return str(self.source) if self.source is not None else "recording"


# --------------------------------------------------------------------------- maths


def catmull_rom(p0, p1, p2, p3, u: float) -> np.ndarray:
    """Uniform Catmull-Rom point between p1 (u=0, exact) and p2 (u=1)."""
    p0, p1, p2, p3 = (np.asarray(p, np.float64) for p in (p0, p1, p2, p3))
    a = 0.5 * (p2 - p0)
    b = 0.5 * (2 * p0 - 5 * p1 + 4 * p2 - p3)
    c = 0.5 * (-p0 + 3 * p1 - 3 * p2 + p3)
    return p1 + u * (a + u * (b + u * c))


def slerp(q0, q1, u: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions along the shortest arc; returns a unit quaternion."""
    q0 = _unit(q0)
    q1 = _unit(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:  # q and -q are the same rotation: take the short way round
        q1, d = -q1, -d
    if u <= 0.0:
        return q0
    if u >= 1.0:
        return q1
    if d > 0.9995:  # nearly identical: normalised lerp avoids dividing by sin(~0)
        return _unit(q0 + u * (q1 - q0))
    theta = math.acos(min(d, 1.0))
    s = math.sin(theta)
    return _unit((math.sin((1 - u) * theta) / s) * q0 + (math.sin(u * theta) / s) * q1)


def _unit(q) -> np.ndarray:
    q = np.asarray(q, np.float64).reshape(4)
    n = float(np.linalg.norm(q))
    if not math.isfinite(n) or n == 0.0:
        raise ValueError("quaternion has zero or non-finite length")
    return q / n


# --------------------------------------------------------------------------- validation


def _short(v: Any, limit: int = 40) -> str:
    s = repr(v).replace("\n", " ").replace("\r", " ")
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _num_out(v: float) -> int | float:
    v = float(v)
    return int(v) if v.is_integer() and abs(v) < 2**53 else v


class _Invalid(Exception):
    """Internal: the message (without the file name) of the first problem found."""


def _number(v: Any, what: str) -> float:
    if not _is_num(v):
        raise _Invalid(f"{what} must be a number, got {_short(v)}")
    try:
        f = float(v)
    except OverflowError:
        raise _Invalid(f"{what} is too large") from None
    if not math.isfinite(f):
        raise _Invalid(f"{what} must be finite, got {f}")
    return f


def _vector(v: Any, n: int, what: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        raise _Invalid(f"{what} must be a list of {n} numbers, got {_short(v)}")
    return np.array([_number(x, f"{what}[{j}]") for j, x in enumerate(v)], np.float64)


def _int(v: Any, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Invalid(f"{what} must be an integer, got {_short(v)}")
    return v


def _parse_scene(s: Any) -> dict:
    if not isinstance(s, dict):
        raise _Invalid(f"'scene' must be an object like {{\"builtin\": \"city\"}} or {{\"file\": ...}}, "
                       f"got {_short(s)}")
    has_b, has_f = "builtin" in s, "file" in s
    if has_b == has_f:
        raise _Invalid("'scene' must have exactly one of 'builtin' or 'file'")
    if has_f:
        f = s["file"]
        if not isinstance(f, str) or not f.strip():
            raise _Invalid(f"scene 'file' must be a non-empty path string, got {_short(f)}")
        return {"file": f}
    name = s["builtin"]
    if not isinstance(name, str) or not name.strip():
        raise _Invalid(f"scene 'builtin' must be a non-empty name, got {_short(name)}")
    out: dict = {"builtin": name}
    if s.get("size") is not None:
        size = _int(s["size"], "scene 'size'")
        if size <= 0:
            raise _Invalid(f"scene 'size' must be > 0, got {size}")
        out["size"] = size
    if s.get("seed") is not None:
        out["seed"] = _int(s["seed"], "scene 'seed'")
    return out


def _parse_keyframe(k: Any, i: int, version: int = FORMAT_VERSION) -> Keyframe:
    where = f"keyframe {i}"
    if not isinstance(k, dict):
        raise _Invalid(f"{where}: must be an object, got {_short(k)}")
    for key in ("time", "position", "orientation", "fov_y"):
        if key not in k:
            raise _Invalid(f"{where}: missing '{key}'")
    try:
        t = _number(k["time"], "time")
        pos = _vector(k["position"], 3, "position")
        q = _vector(k["orientation"], 4, "orientation")
        n = float(np.linalg.norm(q))
        if not math.isfinite(n) or n < 1e-12:
            raise _Invalid("orientation must be a non-zero quaternion [w, x, y, z], "
                           f"got {_short(k['orientation'])}")
        fov = _number(k["fov_y"], "fov_y")
        if not MIN_FOV < fov < MAX_FOV:
            raise _Invalid(f"fov_y must be between {MIN_FOV:g} and {MAX_FOV:g} degrees, got {fov:g}")
        st = _number(k["scene_time"], "scene_time") if "scene_time" in k and version >= 2 else None
    except _Invalid as e:
        raise _Invalid(f"{where}: {e}") from None
    return Keyframe(t, pos, q / n, fov, st)


def _parse(data: Any) -> tuple[dict, tuple[int, int], float, list[Keyframe]]:
    if not isinstance(data, dict):
        raise _Invalid(f"top level must be a JSON object, got {type(data).__name__}")
    fmt = data.get("format")
    if fmt != FORMAT_TAG:
        raise _Invalid(f"not an rtwalk recording (format is {_short(fmt)}, expected {FORMAT_TAG!r})")
    if "version" not in data:
        raise _Invalid("missing 'version'")
    ver = data["version"]
    if isinstance(ver, bool) or not isinstance(ver, int):
        raise _Invalid(f"'version' must be an integer, got {_short(ver)}")
    if ver not in READ_VERSIONS:
        raise _Invalid(f"unsupported version {ver} (this rtwalk reads versions "
                       f"{', '.join(map(str, READ_VERSIONS))})")
    for key in ("scene", "resolution", "fps", "keyframes"):
        if key not in data:
            raise _Invalid(f"missing '{key}'")
    scene = _parse_scene(data["scene"])
    res = data["resolution"]
    if (not isinstance(res, list) or len(res) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= MAX_RESOLUTION
                   for v in res)):
        raise _Invalid(f"'resolution' must be [width, height] with integers in 1..{MAX_RESOLUTION}, "
                       f"got {_short(res)}")
    try:
        fps = _number(data["fps"], "'fps'")
    except _Invalid as e:
        raise _Invalid(str(e)) from None
    if not 0 < fps <= MAX_FPS:
        raise _Invalid(f"'fps' must be > 0 and <= {MAX_FPS:g}, got {fps:g}")
    kf = data["keyframes"]
    if not isinstance(kf, list):
        raise _Invalid(f"'keyframes' must be a list, got {_short(kf)}")
    if not kf:
        raise _Invalid("'keyframes' is empty (need at least 1; 2 or more for a moving path)")
    keyframes = [_parse_keyframe(k, i, ver) for i, k in enumerate(kf)]
    with_st = [k.scene_time is not None for k in keyframes]
    if any(with_st) and not all(with_st):
        i = with_st.index(not with_st[0])
        raise _Invalid(f"keyframe {i}: 'scene_time' must be given on every keyframe or on none")
    for i in range(1, len(keyframes)):
        if not keyframes[i].time > keyframes[i - 1].time:
            raise _Invalid(f"keyframe {i}: time must increase ({keyframes[i].time:g} after "
                           f"{keyframes[i - 1].time:g})")
    return scene, (int(res[0]), int(res[1])), fps, keyframes


def recording_from_dict(data: Any, name: str = "recording", source: Path | None = None) -> Recording:
    """Validate an already-parsed JSON object; errors are `RtwalkError("<name>: <problem>")`."""
    try:
        scene, res, fps, keyframes = _parse(data)
    except _Invalid as e:
        raise RtwalkError(_one_line(f"{name}: {e}")) from None
    return Recording(scene, res, fps, keyframes, source)


def _one_line(msg: str) -> str:
    return " ".join(msg.split())


def load_recording(path: str | os.PathLike) -> Recording:
    """Read and validate a recording; any problem raises a one-line `RtwalkError` naming the file."""
    p = Path(path)
    if not p.exists():
        raise RtwalkError(_one_line(f"{p}: recording not found"))
    if p.is_dir():
        raise RtwalkError(_one_line(f"{p}: is a directory, expected a recording .json file"))
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise RtwalkError(_one_line(f"{p}: cannot read: {e.strerror or e}")) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise RtwalkError(_one_line(f"{p}: not a text file (invalid UTF-8)")) from None
    if not text.strip():
        raise RtwalkError(_one_line(f"{p}: file is empty"))
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        msg = f"{p}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}"
        raise RtwalkError(_one_line(msg)) from None
    except (ValueError, RecursionError) as e:
        raise RtwalkError(_one_line(f"{p}: invalid JSON: {_short(str(e), 80)}")) from None
    return recording_from_dict(data, str(p), p)


def _format_json(rec_dict: dict) -> str:
    """Readable JSON: header fields on their own lines, one keyframe per line."""
    lines = ["{"]
    for key in ("format", "version", "scene", "resolution", "fps"):
        lines.append(f"  {json.dumps(key)}: {json.dumps(rec_dict[key])},")
    lines.append('  "keyframes": [')
    kfs = [json.dumps(k) for k in rec_dict["keyframes"]]
    for j, k in enumerate(kfs):
        lines.append(f"    {k}{',' if j < len(kfs) - 1 else ''}")
    lines.append("  ]")
    lines.append("}")
    return "\n".join(lines) + "\n"


def save_recording(rec: Recording, path: str | os.PathLike) -> Path:
    """Validate and write `rec` as JSON (parent folders are created; the write is atomic)."""
    p = Path(path)
    data = rec.to_dict()
    recording_from_dict(data, str(p))  # refuse to write a file that would not load back
    text = _format_json(data)
    tmp = p.with_name(p.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as e:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise RtwalkError(_one_line(f"{p}: cannot write recording: {e.strerror or e}")) from None
    rec.source = p
    return p


# --------------------------------------------------------------------------- recorder


def _scene_dict(scene_identity: Any) -> dict:
    """Scene identity for the file: a dict as in the format, or a builtin name / scene path string."""
    if isinstance(scene_identity, dict):
        try:
            return _parse_scene(scene_identity)
        except _Invalid as e:
            raise RtwalkError(_one_line(f"recorder: {e}")) from None
    if isinstance(scene_identity, os.PathLike):
        return {"file": os.fspath(scene_identity)}
    if isinstance(scene_identity, str) and scene_identity.strip():
        s = scene_identity
        if Path(s).suffix or "/" in s or os.sep in s:
            return {"file": s}
        return {"builtin": s}
    raise RtwalkError(f"recorder: bad scene identity {_short(scene_identity)}")


class Recorder:
    """Collects camera keyframes from the interactive window.

    `add` takes any monotonic clock in seconds; times are stored relative to the first added
    keyframe. Keyframes closer than `min_step` seconds to the previously kept one are thinned
    out, but the latest pose is kept aside and appended by `stop` so the path ends where the
    user stopped.
    """

    def __init__(self, min_step: float = RECORDER_MIN_STEP):
        self.min_step = float(min_step)
        self._scene: dict | None = None
        self._resolution: tuple[int, int] = (1280, 720)
        self._fps = 30.0
        self._t0: float | None = None
        self._keyframes: list[Keyframe] = []
        self._pending: Keyframe | None = None
        self._recording = False
        self.last: Recording | None = None

    @property
    def recording(self) -> bool:
        return self._recording

    @property
    def keyframe_count(self) -> int:
        return len(self._keyframes) + (self._pending is not None)

    def start(self, scene_identity: Any, resolution: tuple[int, int], fps: float = 30) -> None:
        self._scene = _scene_dict(scene_identity)
        w, h = (int(v) for v in resolution)
        self._resolution = (w, h)
        self._fps = float(fps)
        self._t0 = None
        self._keyframes = []
        self._pending = None
        self._recording = True

    def add(self, time_s: float, camera: Camera) -> bool:
        """Offer a pose; returns True when it was kept as a keyframe (False: thinned/ignored)."""
        if not self._recording:
            return False
        t = float(time_s)
        try:
            kf = Keyframe.from_camera(0.0, camera)
        except ValueError:
            return False
        if not (math.isfinite(t) and np.all(np.isfinite(kf.position)) and math.isfinite(kf.fov_y)):
            return False
        kf.fov_y = min(max(kf.fov_y, MIN_FOV + 1e-6), MAX_FOV - 1e-6)
        if self._t0 is None:
            self._t0 = t
        kf.time = t - self._t0
        if self._keyframes:
            last = self._keyframes[-1].time
            if kf.time <= last:
                return False
            if kf.time - last < self.min_step:
                self._pending = kf
                return False
        self._keyframes.append(kf)
        self._pending = None
        return True

    def stop(self) -> Recording:
        """End recording; RtwalkError if nothing was added. One keyframe gives a still."""
        self._recording = False
        kfs = list(self._keyframes)
        if self._pending is not None and (not kfs or self._pending.time > kfs[-1].time):
            kfs.append(self._pending)
        self._pending = None
        if not kfs or self._scene is None:
            raise RtwalkError("recorder: nothing was recorded (no camera poses)")
        self._keyframes = kfs
        self.last = Recording(dict(self._scene), self._resolution, self._fps, kfs)
        return self.last

    def save(self, directory: str | os.PathLike = "recordings") -> Path:
        """Write the recording (stopping first if needed) as <dir>/<scene-name>-YYYYmmdd-HHMMSS.json."""
        rec = self.stop() if self._recording or self.last is None else self.last
        d = Path(directory)
        stamp = _time.strftime("%Y%m%d-%H%M%S")
        name = "".join(c if c.isalnum() or c in "-_." else "_" for c in rec.scene_name) or "scene"
        p = d / f"{name}-{stamp}.json"
        n = 1
        while p.exists():
            p = d / f"{name}-{stamp}-{n}.json"
            n += 1
        return save_recording(rec, p)


# --------------------------------------------------------------------------- scenes


class SceneSpec(NamedTuple):
    """What to pass to `viewer.scene_io.load_scene`: a builtin name or a file path (+ size, seed)."""

    spec: str
    size: int | None = None
    seed: int | None = None


def resolve_scene_spec(recording: Recording, recording_path: str | os.PathLike | None = None) -> SceneSpec:
    """Scene spec of a recording. Builtins: the name with size/seed (None when not given).

    Files: the first that exists of the path relative to the recording's folder, relative to
    ``../shared/scenes`` next to the repository, or as given (absolute, or relative to the
    current directory); when none exists the path is returned as given so the loader reports it.
    """
    scene = recording.scene
    if "builtin" in scene:
        return SceneSpec(str(scene["builtin"]), scene.get("size"), scene.get("seed"))
    given = Path(os.path.expanduser(str(scene["file"])))
    if recording_path is None:
        recording_path = recording.source
    candidates: list[Path] = []
    if given.is_absolute():
        candidates.append(given)
    else:
        if recording_path is not None:
            candidates.append(Path(recording_path).resolve().parent / given)
        candidates.append(SHARED_SCENES / given)
        candidates.append(given)
    for c in candidates:
        if c.is_file():
            return SceneSpec(str(c.resolve()))
    return SceneSpec(str(given))

"""Loading scenes: built-in procedural scenes by name, or files through trimesh.

Every failure is an RtwalkError with one line naming the file; NaN/Inf vertices and zero-area
triangles are dropped with a one-line count in `scene.notes`.
"""

from __future__ import annotations

import fnmatch
import json
import re
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from viewer.camera import Camera
from viewer.errors import RtwalkError
from viewer.paths import RECORDINGS, SHARED_SCENES
from viewer.scene import Material, PointLight, RectLight, Scene

GREY = np.array([0.7, 0.7, 0.7], np.float32)


def resolve_scene_path(spec: str) -> Path:
    p = Path(spec).expanduser()
    for cand in ([p] if p.is_absolute() else [p, SHARED_SCENES / p, RECORDINGS / p]):
        if cand.exists():
            return cand
    raise RtwalkError(f"{spec}: no such scene file (and not a built-in: city, room, room-anim)")


def load_scene(spec: str | None, scene_size: int | None = None, seed: int = 1,
               mirror_patterns: list[str] | None = None, progress: bool = True) -> Scene:
    from viewer.procedural import BUILTIN_SCENES

    name = "city" if spec is None else str(spec)
    base, sep, spec_size = name.partition(":")
    if sep and base in BUILTIN_SCENES and re.fullmatch(r"[0-9_]+[kKmM]?", spec_size):
        # "city:400000", "city:2M": a size in the spec takes precedence over scene_size
        mult = {"k": 1_000, "m": 1_000_000}.get(spec_size[-1].lower(), 1)
        name, scene_size = base, int(spec_size.rstrip("kKmM").replace("_", "")) * mult
    if name in BUILTIN_SCENES:
        b = BUILTIN_SCENES[name]
        size = check_builtin_size(name, b.default_size if scene_size is None else int(scene_size))
        check_seed(seed, "seed")  # a recording's scene seed too
        scene = b.make(size, seed)
        if mirror_patterns:
            _apply_mirrors(scene.materials, mirror_patterns)
        return scene
    if "/" not in name and "." not in name:
        raise RtwalkError(f"unknown built-in scene '{name}' (built-ins: {', '.join(BUILTIN_SCENES)})")
    path = resolve_scene_path(name)
    return _load_file(path, name, mirror_patterns or [], progress)


MAX_SEED = 2**32 - 1  # NumPy's seed range; -1 was a ValueError traceback from inside NumPy


def check_seed(seed: int | None, flag: str = "--seed") -> None:
    """A procedural scene's seed within NumPy's range, else one line (None: not given)."""
    if seed is not None and not 0 <= seed <= MAX_SEED:
        raise RtwalkError(f"{flag} must be in 0..{MAX_SEED} (got {seed})")


def check_builtin_size(name: str, size: int, flag: str = "--scene-size") -> int:
    """`size` if within the built-in's range and its estimated memory fits what this process may
    still allocate (viewer.sysmem), else one line with the figures. Nothing is built here."""
    from viewer.procedural import BUILTIN_SCENES
    from viewer.sysmem import available_bytes, gib

    b = BUILTIN_SCENES[name]
    if not (b.min_size <= size <= b.max_size):
        raise RtwalkError(f"{flag} {size} out of range for {name} ({b.min_size}..{b.max_size}, {b.size_meaning})")
    need = b.memory_estimate(size)
    have = available_bytes()
    if have is not None and need > have:
        raise RtwalkError(f"{flag} {size:,}: {name} needs about {gib(need)} to build (scene + BVH), "
                          f"only {gib(have)} is available; choose a smaller size")
    return size


def _apply_mirrors(materials: list[Material], patterns: list[str]) -> None:
    pats = [p.lower() for p in patterns]
    for m in materials:
        if any(fnmatch.fnmatch(m.name.lower(), p) for p in pats):
            m.mirror = True


def _material_of(geom, index: int) -> tuple[str, np.ndarray, np.ndarray | None]:
    """(name, albedo, per-face colours or None) of a trimesh geometry."""
    vis = getattr(geom, "visual", None)
    kind = getattr(vis, "kind", None)
    if kind == "texture" or hasattr(vis, "material"):
        mat = getattr(vis, "material", None)
        if mat is not None:
            name = getattr(mat, "name", None) or f"material_{index}"
            alb = _material_albedo(mat)
            return str(name), (GREY if alb is None else alb), None
    if kind == "face":
        fc = np.asarray(vis.face_colors, np.float32)[:, :3] / 255.0
        return f"face_colors_{index}", GREY, fc
    if kind == "vertex":
        vc = np.asarray(vis.vertex_colors, np.float32)[:, :3] / 255.0
        fc = vc[np.asarray(geom.faces)].mean(axis=1)
        return f"vertex_colors_{index}", GREY, fc
    return f"default_{index}", GREY, None


def _material_albedo(mat) -> np.ndarray | None:
    """Diffuse albedo (float32 (3,), 0..1) of a trimesh material, or None if it has none.

    MTL: the exact Kd floats (trimesh keeps them in `kwargs`; its `diffuse` is rounded to 8 bits).
    glTF: baseColorFactor (uint8 in trimesh, or floats). No sRGB conversion: both are linear.
    """
    kd = (getattr(mat, "kwargs", None) or {}).get("kd")
    if kd is not None:
        try:
            a = np.asarray(kd, np.float64).ravel()[:3]
            if a.size == 3 and np.isfinite(a).all():
                return np.clip(a, 0, 1).astype(np.float32)
        except (TypeError, ValueError):
            pass
    for attr in ("diffuse", "baseColorFactor"):
        value = getattr(mat, attr, None)
        if value is None:
            continue
        raw = np.asarray(value)
        a = raw.astype(np.float64).ravel()[:3]
        if a.size != 3 or not np.isfinite(a).all():
            continue
        if raw.dtype.kind in "ui" or a.max() > 1.0:
            a = a / 255.0
        return np.clip(a, 0, 1).astype(np.float32)
    return None


MAX_COLOUR_MATERIALS = 256


def _colour_materials(face_colors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct per-face colours (0..1) -> (unique colours (K, 3) float32, per-face index).

    More than MAX_COLOUR_MATERIALS distinct 8-bit colours (a vertex-coloured scan averaged per face
    can have one per face) are quantised to 4 bits per channel, so K <= 4096.
    """
    q = np.clip(np.round(face_colors * 255), 0, 255).astype(np.int32)
    uniq, inv = np.unique(q, axis=0, return_inverse=True)
    if len(uniq) > MAX_COLOUR_MATERIALS:
        q = np.round(q / 17.0).astype(np.int32) * 17
        uniq, inv = np.unique(q, axis=0, return_inverse=True)
    return (uniq / 255.0).astype(np.float32), inv.reshape(-1).astype(np.int32)


@contextmanager
def _elapsed_ticker(desc: str, enabled: bool, every_s: float = 0.5):
    """A line that counts the seconds of one long call that reports no progress itself (the
    parser); shown only on a terminal, after the first second."""
    if not enabled or not sys.stderr.isatty():
        yield
        return
    from tqdm import tqdm

    stop = threading.Event()
    bar = tqdm(desc=desc, bar_format="{desc}: {elapsed}", file=sys.stderr, leave=False, delay=1.0)

    def tick() -> None:
        while not stop.wait(every_s):
            bar.refresh()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        bar.close()


def _load_file(path: Path, given: str, mirror_patterns: list[str], progress: bool) -> Scene:
    import trimesh

    if progress:
        print(f"loading {path} ({path.stat().st_size / 2**20:.1f} MiB) ...", file=sys.stderr, flush=True)
    try:
        with _elapsed_ticker(f"reading {path.name}", progress):
            loaded = trimesh.load(str(path), force="scene", process=False)  # we clean, and say what we drop
    except ImportError as exc:  # a corrupt file sent trimesh to an optional reader (truncated STL: ASCII)
        raise RtwalkError(f"{path}: cannot read scene file (corrupt or truncated {path.suffix.lstrip('.').upper()} "
                          f"file; trimesh's fallback reader needs module '{exc.name}', not installed)") from None
    except Exception as exc:  # trimesh raises many types for corrupt files
        msg = _short(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        if path.suffix.lower() in _SIZED_FORMATS:  # sizes in the file: a cut one fails to parse
            declared = declared_counts(path)  # the parser's own words (NumPy's for OFF) say less
            if declared is not None:
                msg = f"its header declares {declared[0]:,} vertices and {declared[1]:,} faces"
            raise RtwalkError(f"{path}: cannot read scene file (truncated or corrupt "
                              f"{path.suffix.lstrip('.').upper()} file: {msg})") from None
        raise RtwalkError(f"{path}: cannot read scene file ({msg})") from None
    tris_list, mat_list, materials = [], [], []
    mat_index: dict[tuple, int] = {}
    try:
        items = list(loaded.graph.nodes_geometry)
    except Exception:
        items = []
    try:
        for i, node in enumerate(items):
            transform, geom_name = loaded.graph[node]
            geom = loaded.geometry[geom_name]
            faces = getattr(geom, "faces", None)
            verts = getattr(geom, "vertices", None)
            if faces is None or verts is None or len(faces) == 0:
                continue
            faces = np.asarray(faces, np.int64)
            v = np.asarray(verts, np.float64)
            if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(v):
                raise ValueError(f"bad face indices in '{geom_name}'")
            t = np.asarray(transform, np.float64)
            if not np.array_equal(t, np.eye(4)):
                with np.errstate(all="ignore"):
                    v = v @ t[:3, :3].T + t[:3, 3]
            tri = v.astype(np.float32)[faces]  # cast first: no float64 (N, 3, 3) temporary
            name, albedo, face_colors = _material_of(geom, i)
            if face_colors is not None:
                uniq, inv = _colour_materials(face_colors)
                base = len(materials)
                for k, c in enumerate(uniq):
                    materials.append(Material(f"{name}_{k}", c))
                ids = base + inv
            else:
                key = (name, tuple(np.round(albedo, 6)))
                if key not in mat_index:
                    mat_index[key] = len(materials)
                    materials.append(Material(name, albedo))
                ids = np.full(len(tri), mat_index[key], np.int32)
            tris_list.append(tri)
            mat_list.append(ids)
    except Exception as exc:  # corrupt content that trimesh let through
        msg = _short(str(exc)) or type(exc).__name__
        raise RtwalkError(f"{path}: cannot read scene file ({msg})") from None
    _check_declared_counts(path, items and loaded)
    if not tris_list:
        raise RtwalkError(f"{path}: no triangles in file")
    tris = np.concatenate(tris_list)
    mats = np.concatenate(mat_list)
    tris, mats, notes = clean_triangles(tris, mats)
    if len(tris) == 0:
        raise RtwalkError(f"{path}: has no valid triangles ({'; '.join(notes)})")
    for n in notes:
        print(f"{path.name}: {n}", file=sys.stderr)
    scene = Scene(name=path.stem, triangles=tris, material_ids=mats, materials=materials,
                  identity={"file": given, "name": path.name}, notes=notes)
    from viewer.presets import apply_preset, find_preset

    preset = find_preset(path.name, len(tris))
    patterns = apply_preset(scene, preset) if preset is not None else []  # shipped presets (viewer/presets)
    sidecar = path.with_name(path.name + ".rtwalk.json")
    if sidecar.exists():
        patterns += _apply_sidecar(scene, sidecar)
    patterns += list(mirror_patterns)
    _apply_mirrors(scene.materials, patterns)
    if not scene.point_lights and not scene.rect_lights:
        default_lights(scene)
    if scene.default_camera is None:
        scene.default_camera = default_camera(scene)
    return scene


_SIZED_FORMATS = (".ply", ".off", ".glb", ".stl")  # formats whose files state their own sizes


def _short(msg: str, limit: int = 120) -> str:
    """One line of at most `limit` characters, cut at a word boundary (not mid-word)."""
    msg = " ".join(msg.split())
    if len(msg) <= limit:
        return msg
    return msg[:limit].rsplit(" ", 1)[0] + " ..."


def declared_counts(path: Path) -> tuple[int, int] | None:
    """(vertices, faces) a PLY header or an OFF counts line declares, None for other formats or
    a header that cannot be read (the parser reports that). Reads only the head of the file."""
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".off"):
        return None
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return None
    if suffix == ".ply":
        end = head.find(b"end_header")
        counts = dict(re.findall(rb"^element[ \t]+(vertex|face)[ \t]+([0-9]+)", head[:max(end, 0)], re.M))
        if end < 0 or b"vertex" not in counts:
            return None
        return int(counts[b"vertex"]), int(counts.get(b"face", 0))
    tokens = []
    for line in head.decode("latin-1").splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            tokens += line.split()
        if len(tokens) >= 3:
            break
    if tokens and tokens[0].endswith("OFF"):
        tokens = tokens[1:]
    try:
        return int(tokens[0]), int(tokens[1])
    except (IndexError, ValueError):
        return None


def ascii_stl_cut(path: Path) -> bool:
    """An ASCII STL (starts with 'solid', and its size is not that of the binary STL its first 84
    bytes would describe) that does not end with 'endsolid': cut short. trimesh returned no
    triangles for one, reported as 'no triangles in file'."""
    if path.suffix.lower() != ".stl":
        return False
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(84)
            f.seek(max(0, size - 1024))
            tail = f.read()
    except OSError:
        return False
    if not head.lstrip().startswith(b"solid"):
        return False
    if len(head) == 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return False  # a binary STL whose 80-byte header happens to start with 'solid'
    last = tail.rstrip().rsplit(b"\n", 1)[-1].strip()
    return not last.startswith(b"endsolid")


def _check_declared_counts(path: Path, loaded) -> None:
    """A PLY or OFF file whose body ends before the vertices and faces its header declares is
    truncated: trimesh reads an ASCII body line by line and returns what it found (a bunny cut in
    half loaded with no faces, reported as 'no triangles in file', or with part of them silently)."""
    if ascii_stl_cut(path):
        raise RtwalkError(f"{path}: truncated or corrupt STL file (an ASCII STL, and it does not end with 'endsolid')")
    declared = declared_counts(path)
    if declared is None:
        return
    nv = nf = 0
    if loaded:
        for geom in loaded.geometry.values():
            nv += len(getattr(geom, "vertices", ()))
            nf += len(getattr(geom, "faces", ()))  # polygons triangulated: never fewer than declared
    if nv < declared[0] or nf < declared[1]:
        fmt = path.suffix.lstrip(".").upper()
        raise RtwalkError(f"{path}: truncated or corrupt {fmt} file (its header declares {declared[0]:,} vertices "
                          f"and {declared[1]:,} faces, the file holds {nv:,} and {nf:,})")


def clean_triangles(tris: np.ndarray, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    notes = []
    finite = np.isfinite(tris).all(axis=(1, 2))
    if (~finite).any():
        notes.append(f"dropped {int((~finite).sum())} triangles with NaN/Inf vertices")
    t64 = tris.astype(np.float64)
    with np.errstate(all="ignore"):  # NaN/Inf rows are dropped and counted above: no numpy warning
        cross = np.cross(t64[:, 1] - t64[:, 0], t64[:, 2] - t64[:, 0])
        area2 = np.einsum("ij,ij->i", cross, cross)
        nondeg = finite & (area2 > 0) & np.isfinite(area2)
        # a float32 normal must also be finite and non-zero for the shaders
        c32 = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        nondeg &= np.isfinite(c32).all(1) & (np.abs(c32).max(1) > 0)
    zero = finite & ~nondeg
    if zero.any():
        notes.append(f"dropped {int(zero.sum())} zero-area triangles")
    keep = finite & nondeg
    return np.ascontiguousarray(tris[keep]), np.ascontiguousarray(mats[keep]), notes


def vertical_hits(tris: np.ndarray, x: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Heights where the vertical line (x, *, z) crosses the triangles, sorted, with the sign of
    each crossed triangle's normal y (+1 faces up by its winding, -1 down). Vectorised."""
    t = tris.astype(np.float64)
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    d = (b[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2]) - (c[:, 0] - a[:, 0]) * (b[:, 2] - a[:, 2])
    ok = np.abs(d) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((x - a[:, 0]) * (c[:, 2] - a[:, 2]) - (c[:, 0] - a[:, 0]) * (z - a[:, 2])) / d
        v = ((b[:, 0] - a[:, 0]) * (z - a[:, 2]) - (x - a[:, 0]) * (b[:, 2] - a[:, 2])) / d
        inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    y = a[inside, 1] + u[inside] * (b[inside, 1] - a[inside, 1]) + v[inside] * (c[inside, 1] - a[inside, 1])
    # normal y of cross(b - a, c - a) has the sign of -d (x/z ordering of the 2D determinant)
    up = -np.sign(d[inside])
    order = np.argsort(y)
    return y[order], up[order]


def default_lights(scene: Scene) -> None:
    """A point light and a small rect light in the largest free vertical gap above the centre.

    Indoor scenes (sibenik's vaulted nave, the conference room) need the light under the
    ceiling, not at a fixed fraction of the bounds, which may be above the roof.
    """
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    c = (lo + hi) / 2
    ext = hi - lo
    diag = float(np.linalg.norm(ext))
    light_y = lo[1] + 0.85 * ext[1]
    reach = 0.5 * diag  # distance at which the point light gives irradiance ~1
    ys, up = vertical_hits(scene.triangles, c[0], c[2])
    if len(ys) >= 2:
        gaps = np.diff(ys)
        # a room: floor facing up below, ceiling facing down above (not the inside of a solid)
        gaps[~((up[:-1] > 0) & (up[1:] < 0))] = 0.0
        k = int(np.argmax(gaps))
        if gaps[k] >= 0.25 * ext[1] and gaps[k] > hi[1] - ys[-1]:
            light_y = ys[k] + 0.8 * gaps[k]
            reach = 1.6 * (light_y - ys[k])
    pos = np.array([c[0], light_y, c[2]])
    scene.point_lights = [PointLight(pos.astype(np.float32), np.full(3, reach ** 2, np.float32))]
    side = 0.1 * max(ext[0], ext[2], 1e-6)
    corner = pos + np.array([-side / 2, -0.02 * ext[1], -side / 2])
    # cross(edge_u, edge_v) must point down (-Y): cross(+X, +Z) = -Y
    eu = np.array([side, 0, 0])
    ev = np.array([0, 0, side])
    power_scale = reach ** 2 / (side * side)
    scene.rect_lights = [RectLight(corner.astype(np.float32), eu.astype(np.float32), ev.astype(np.float32),
                                   np.full(3, power_scale, np.float32))]
    scene.auto_lights = True  # a guess: viewer.session moves it by ray casts once the BVH exists


def axis_ray_hits(tris: np.ndarray, origin, axis: int, sign: float,
                  tri_min: np.ndarray | None = None, tri_max: np.ndarray | None = None,
                  facing: bool = False):
    """Sorted distances of all hits of the ray origin + t * sign * e_axis (t > 0). Vectorised;
    triangles whose bounding box misses the ray are skipped first (pass tri_min/tri_max, the
    per-triangle vertex min/max, to reuse them over several rays). With `facing`, also the sign of
    dot(winding normal, ray direction) of each hit (-1: the surface faces the origin)."""
    origin = np.asarray(origin, np.float64)
    tri_min = tris.min(axis=1) if tri_min is None else tri_min
    tri_max = tris.max(axis=1) if tri_max is None else tri_max
    b, c = (axis + 1) % 3, (axis + 2) % 3
    cand = ((tri_min[:, b] <= origin[b]) & (tri_max[:, b] >= origin[b])
            & (tri_min[:, c] <= origin[c]) & (tri_max[:, c] >= origin[c]))
    cand &= (tri_max[:, axis] >= origin[axis]) if sign > 0 else (tri_min[:, axis] <= origin[axis])
    t = tris[np.nonzero(cand)[0]].astype(np.float64)
    d = np.zeros(3)
    d[axis] = 1.0 if sign > 0 else -1.0
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    with np.errstate(all="ignore"):  # Moller-Trumbore
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        inv = 1.0 / det
        s = origin - t[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        dist = np.einsum("ij,ij->i", e2, q) * inv
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 0)
    order = np.argsort(dist[ok])
    if facing:  # dot(cross(e1, e2), d) = -det (Moller-Trumbore: det = dot(e1, cross(d, e2)))
        return dist[ok][order], -np.sign(det[ok][order])
    return dist[ok][order]


def is_enclosed(scene: Scene, point) -> bool:
    """Whether `point` is inside a shell that spans the scene bounds (an interior such as sponza,
    sibenik, the conference room), not inside a closed object (a scanned bunny, a box): along at
    least 4 of the 6 axis directions, the farthest surface is within 3% of the bounding-box face,
    and the nearest surfaces do not all turn their backs to the point (inside a solid whose
    winding points outwards, such as trimesh.creation.box(), every nearest hit is a back face)."""
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    ext = np.maximum(hi - lo, 1e-12)
    point = np.asarray(point, np.float64)
    tmin, tmax = scene.triangles.min(axis=1), scene.triangles.max(axis=1)
    near_face = back = hit = 0
    for axis in range(3):
        for sign, face in ((1.0, hi[axis]), (-1.0, lo[axis])):
            hits, facing = axis_ray_hits(scene.triangles, point, axis, sign, tmin, tmax, facing=True)
            if len(hits):
                hit += 1
                back += int(facing[0] > 0)
                if abs(face - point[axis]) - hits[-1] <= 0.03 * ext[axis]:
                    near_face += 1
    return near_face >= 4 and not (hit == 6 and back == 6)


def default_camera(scene: Scene) -> Camera:
    """Interiors: from the centre moved 35% of the x extent towards -X, at 30% of the height,
    looking along +X. Objects (bunny, dragon: that point would be inside them): from outside, in
    front (+Z) and a little above, looking at the centre from 1.7 bounding-sphere radii."""
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    c = (lo + hi) / 2
    ext = hi - lo
    eye = np.array([c[0] - 0.35 * ext[0], lo[1] + 0.3 * ext[1], c[2]])
    if is_enclosed(scene, eye):
        return Camera.look_at(eye, eye + np.array([1.0, 0.0, 0.0]), fov_y=60.0)
    direction = np.array([0.0, 0.3, 1.0]) / np.hypot(0.3, 1.0)
    radius = 0.5 * max(float(np.linalg.norm(ext)), 1e-9)
    return Camera.look_at(c + direction * 1.7 * radius, c, fov_y=60.0)


def _vec(v, n: int, what: str, path: Path) -> np.ndarray:
    try:
        a = np.asarray(v, np.float64).reshape(n)
    except (TypeError, ValueError):
        raise RtwalkError(f"{path}: {what} must be {n} numbers") from None
    if not np.isfinite(a).all():
        raise RtwalkError(f"{path}: {what} must be finite")
    return a


def _apply_sidecar(scene: Scene, path: Path) -> list[str]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RtwalkError(f"{path}: bad sidecar JSON ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise RtwalkError(f"{path}: sidecar must be a JSON object")
    try:
        scene.point_lights = [PointLight(_vec(p["position"], 3, "position", path).astype(np.float32),
                                         _vec(p["intensity"], 3, "intensity", path).astype(np.float32))
                              for p in data.get("point_lights", [])]
        scene.rect_lights = [RectLight(*(_vec(r[k], 3, k, path).astype(np.float32)
                                         for k in ("corner", "edge_u", "edge_v", "radiance")))
                             for r in data.get("rect_lights", [])]
        cam = data.get("camera")
        if cam is not None:
            fov = float(cam.get("fov_y", 60.0))
            if "target" in cam:
                scene.default_camera = Camera.look_at(_vec(cam["position"], 3, "camera position", path),
                                                      _vec(cam["target"], 3, "camera target", path), fov_y=fov)
            else:
                q = _vec(cam["orientation"], 4, "camera orientation", path)
                pos = _vec(cam["position"], 3, "camera position", path)
                scene.default_camera = Camera(pos, q / np.linalg.norm(q), fov)
        if "sky_color" in data:
            scene.sky_color = _vec(data["sky_color"], 3, "sky_color", path).astype(np.float32)
        mirrors = data.get("mirrors", [])
        if not isinstance(mirrors, list) or not all(isinstance(m, str) for m in mirrors):
            raise RtwalkError(f"{path}: 'mirrors' must be a list of name patterns")
    except (KeyError, TypeError, AttributeError) as exc:
        raise RtwalkError(f"{path}: malformed sidecar ({type(exc).__name__}: {exc})") from None
    return mirrors

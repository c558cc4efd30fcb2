"""Material presets shipped with rtwalk for known scene files (the files themselves are not changed).

A preset is `<scene file name>.json` in this folder (e.g. conference.ply.json) and applies to a
loaded file of that name whose triangle count after cleaning equals its "triangles" (another
file that merely shares the name is left alone). Keys:
  "mirrors": material name patterns made mirrors (fnmatch, case-insensitive, as --mirror);
  "albedo": {pattern: [r, g, b]} albedo of the matching materials;
  "mirror_parts": for files without usable materials (conference.ply has none): each entry gives
      a new mirror material ("material", "albedo") to the connected parts (triangles sharing
      vertex positions) whose triangle count is one of "triangles" and whose bounds lie inside
      "box" [[x0, y0, z0], [x1, y1, z1]].
Order at load (viewer.scene_io): preset, then the sidecar beside the file, then --mirror, so a
user's own settings come last. RTWALK_NO_PRESETS=1 turns presets off (the scene as in the file).
"""

from __future__ import annotations

import fnmatch
import json
import os
from pathlib import Path

import numpy as np

from viewer.errors import RtwalkError
from viewer.scene import Material, Scene

HERE = Path(__file__).resolve().parent
ENV_OFF = "RTWALK_NO_PRESETS"


def preset_path(file_name: str) -> Path:
    return HERE / f"{file_name}.json"


def find_preset(file_name: str, triangle_count: int) -> dict | None:
    """The preset for a loaded file (its name and its triangle count after cleaning), else None."""
    if os.environ.get(ENV_OFF, "").strip() not in ("", "0"):
        return None
    path = preset_path(file_name)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except ValueError as exc:
        raise RtwalkError(f"{path}: bad preset JSON ({exc})") from None
    return data if int(data.get("triangles", -1)) == int(triangle_count) else None


def part_labels(triangles: np.ndarray) -> np.ndarray:
    """Connected part of every triangle (int64 labels): triangles sharing a vertex position."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    t = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
    n = len(t)
    bits = (t.reshape(-1, 3) + np.float32(0)).view(np.uint32)  # + 0: -0.0 and 0.0 are one position
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    sb = bits[order]
    new = np.ones(len(sb), bool)
    new[1:] = (sb[1:] != sb[:-1]).any(1)
    vid = np.empty(len(sb), np.int64)
    vid[order] = np.cumsum(new) - 1
    tri = np.repeat(np.arange(n), 3)
    m = n + int(vid.max()) + 1 if n else 0
    g = coo_matrix((np.ones(3 * n), (tri, n + vid)), shape=(m, m))
    _, lab = connected_components(g, directed=False)
    return lab[:n].astype(np.int64)


def _select_parts(tris: np.ndarray, labels: np.ndarray, counts: list[int], box: np.ndarray) -> np.ndarray:
    """Mask of the triangles in parts with one of `counts` triangles lying inside `box`."""
    size = np.bincount(labels)
    inside = ((tris >= box[0]) & (tris <= box[1])).all(axis=(1, 2))
    outside_parts = np.bincount(labels[~inside], minlength=len(size)) > 0
    ok_part = np.isin(size, counts) & ~outside_parts
    return ok_part[labels]


def apply_preset(scene: Scene, preset: dict) -> list[str]:
    """Apply a preset to a freshly loaded scene (materials, material ids); returns its mirror patterns."""
    for pat, albedo in preset.get("albedo", {}).items():
        for m in scene.materials:
            if fnmatch.fnmatch(m.name.lower(), pat.lower()):
                m.albedo = np.asarray(albedo, np.float32)
    parts = preset.get("mirror_parts", [])
    if parts:
        tris = np.asarray(scene.triangles, np.float32).reshape(-1, 3, 3)
        labels = part_labels(tris)
        ids = np.asarray(scene.material_ids).copy()
        for p in parts:
            mask = _select_parts(tris, labels, [int(c) for c in p["triangles"]], np.asarray(p["box"], np.float32))
            if mask.any():
                ids[mask] = len(scene.materials)
                scene.materials.append(Material(str(p["material"]), np.asarray(p["albedo"], np.float32), mirror=True))
        scene.material_ids = ids.astype(scene.material_ids.dtype)
    return [str(m) for m in preset.get("mirrors", [])]

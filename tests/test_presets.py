"""Shipped material presets (viewer/presets): the mirrors of the thesis's Figure 5.6 scenes appear
with no flags, only on the files they were made for, and can be turned off."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from tests.conftest import shared_scene
from viewer.paths import RECORDINGS
from viewer.presets import part_labels
from viewer.scene_io import load_scene


def test_part_labels_match_trimesh_components():
    a = trimesh.creation.icosphere(2)
    b = trimesh.creation.box().apply_translation([5, 0, 0])
    c = trimesh.creation.cylinder(0.3, 1.0).apply_translation([0, 5, 0])
    m = trimesh.util.concatenate([a, b, c])
    tris = m.vertices[m.faces].astype(np.float32)
    perm = np.random.default_rng(0).permutation(len(tris))
    tris = tris[perm]
    lab = part_labels(tris)
    ref = np.zeros(len(m.faces), np.int64)
    for i, comp in enumerate(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(m.faces)))):
        ref[comp] = i
    ref = ref[perm]
    assert len(np.unique(lab)) == len(np.unique(ref)) == 3
    # the same partition: each label maps to exactly one reference label
    pairs = np.unique(np.stack([lab, ref], 1), axis=0)
    assert len(pairs) == 3


def test_sibenik_floor_is_a_mirror_with_no_flags():
    s = load_scene(shared_scene("sibenik/sibenik.obj"), progress=False)
    mirrors = {m.name for m in s.materials if m.mirror}
    assert mirrors == {"pod", "pod_rub"}
    floor = np.isin(s.material_ids, [i for i, m in enumerate(s.materials) if m.mirror])
    ys = s.triangles.reshape(-1, 3, 3)[floor][:, :, 1]
    lo = s.triangles[..., 1].min()
    assert np.median(ys) < lo + 0.2 * (s.triangles[..., 1].max() - lo)  # the floor, low in the nave


def test_conference_table_and_chair_frames(monkeypatch):
    s = load_scene(shared_scene("conference/conference.ply"), progress=False)
    names = [m.name for m in s.materials if m.mirror]
    assert names == ["polished_table", "polished_chair_frames"]
    tris = s.triangles.reshape(-1, 3, 3)
    ids = {m.name: i for i, m in enumerate(s.materials)}
    table = tris[s.material_ids == ids["polished_table"]]
    chairs = tris[s.material_ids == ids["polished_chair_frames"]]
    assert len(table) == 2 * 88 + 4 * 680 and len(chairs) == 12 * 520
    assert table[..., 1].max() < 200 and chairs[..., 1].max() < 200  # furniture, not the walls
    # every selected triangle's whole connected part was selected
    lab = part_labels(tris)
    sel = np.isin(s.material_ids, [ids["polished_table"], ids["polished_chair_frames"]])
    assert not np.isin(lab[~sel], lab[sel]).any()
    monkeypatch.setenv("RTWALK_NO_PRESETS", "1")
    plain = load_scene(shared_scene("conference/conference.ply"), progress=False)
    assert not any(m.mirror for m in plain.materials) and len(plain.materials) == 1


def test_preset_needs_the_same_file(tmp_path):
    """A file that only shares the name (another triangle count) gets no preset."""
    m = trimesh.creation.icosphere(1)
    path = tmp_path / "sibenik.obj"
    m.export(path)
    s = load_scene(str(path), progress=False)
    assert not any(mat.mirror for mat in s.materials)


def test_buddha_white_and_reflective():
    s = load_scene(shared_scene("buddha/buddha_100k.obj"), progress=False)
    assert all(m.mirror for m in s.materials)
    assert all(np.allclose(m.albedo, 0.95) for m in s.materials)


@pytest.mark.parametrize("walk, scene, frame", [("conference-walk", "conference/conference.ply", 150),
                                                ("sibenik-walk", "sibenik/sibenik.obj", 10)])
def test_shipped_walks_trace_reflection_rays(tmp_path, walk, scene, frame):
    shared_scene(scene)
    r = subprocess.run([sys.executable, "-m", "viewer.cli", "render", "--recording", str(RECORDINGS / f"{walk}.json"),
                        "--frame", str(frame), "--size", "160x90", "--effects", "reflections", "--backend", "glsl",
                        "-o", str(tmp_path / "f.png")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    m = re.search(r"reflections ([0-9,]+)", r.stdout + r.stderr)
    assert m and int(m.group(1).replace(",", "")) > 0.05 * 160 * 90, r.stdout + r.stderr

"""Every backend's frames fence what their shaders write (tests/gl_hazards.py).

A GL command sees what an earlier shader wrote through a storage block or an image only after a
glMemoryBarrier with the bit of the path it reads through; llvmpipe forgives a missing bit, an
NVIDIA driver need not. The recorder follows a short walk of every registered backend (the
renderer's own passes included: G-buffer culling, ray generation, accumulation, shading,
overlays), with every effect, overlays on and off, and with the loop limit off as on a GPU (no
counter read, whose barrier would hide a missing one) and on as on llvmpipe (the resumed
traversals' draws), and fails on any access to shader-written memory without its barrier.

The recorder itself is checked on hand-made sequences against the rules it encodes.
"""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np
import pytest

from tests.conftest import opencl_missing, prepared_scene
from tests.gl_hazards import HazardRecorder
from viewer.backends import backend_info, backend_names
from viewer.effects import parse_effects
from viewer.gl.programs import compute_shader
from viewer.recording import load_recording
from viewer.renderer import Renderer

REPO = Path(__file__).resolve().parents[1]

SIZE = (96, 54)
EFFECTS = "primary,shadows,soft:2,ao:3,diffuse:1,reflections"


def _backends() -> list:
    params = []
    for name in backend_names():
        marks = []
        if backend_info(name).device == "cl" and opencl_missing() is not None:
            marks.append(pytest.mark.skip(reason=f"backend '{name}' runs on OpenCL: {opencl_missing()}"))
        params.append(pytest.param(name, marks=marks, id=name))
    return params


def _walk(ctx, backend: str, overlays: bool) -> tuple[np.ndarray, list[dict[str, int]]]:
    """Four frames of the city-near recording (the first builds, the later ones are steady): the
    image read back, and each frame's ray counts."""
    ps = prepared_scene("city")
    rec = load_recording(REPO / "recordings" / "city-near.json")
    r = Renderer(ctx, ps.scene, ps.bvh, SIZE, backend, parse_effects(EFFECTS))
    try:
        r.capture_overlays = overlays
        rays = [r.render(rec.camera_for_frame(n)).rays for n in range(60, 64)]
        return r.read_image(), rays
    finally:
        r.release()


POISON = b"\x77"  # 0x77777777: 5.1e33 as a float, a large positive int


def _poison_new_memory(monkeypatch) -> dict[str, int]:
    """Every GL buffer and 2D texture made without data starts filled with POISON bytes instead of
    what the driver leaves there (llvmpipe: often zeros or the last freed block; an NVIDIA GPU:
    whatever was there, text once). Returns the counts of poisoned buffers and textures made."""
    buffer, texture = moderngl.Context.buffer, moderngl.Context.texture
    itemsize = {"f1": 1, "u1": 1, "i1": 1, "f2": 2, "u2": 2, "i2": 2, "f4": 4, "u4": 4, "i4": 4}
    made = {"buffers": 0, "textures": 0}

    def poisoned_buffer(self, data=None, reserve=0, dynamic=False):
        if data is None and isinstance(reserve, int) and reserve > 0:
            data, reserve = POISON * reserve, 0
            made["buffers"] += 1
        return buffer(self, data, reserve=reserve, dynamic=dynamic)

    def poisoned_texture(self, size, components, data=None, samples=0, alignment=1, dtype="f1", **kw):
        if data is None and samples == 0 and dtype in itemsize:
            data = POISON * (size[0] * size[1] * components * itemsize[dtype])
            made["textures"] += 1
        return texture(self, size, components, data, samples=samples, alignment=alignment, dtype=dtype, **kw)

    monkeypatch.setattr(moderngl.Context, "buffer", poisoned_buffer)
    monkeypatch.setattr(moderngl.Context, "texture", poisoned_texture)
    return made


@pytest.mark.parametrize("loop_limit", ["none", "llvmpipe"])
@pytest.mark.parametrize("overlays", [False, True], ids=["plain", "overlays"])
@pytest.mark.parametrize("backend", _backends())
def test_shader_writes_are_fenced(backend, overlays, loop_limit, gl_ctx, monkeypatch):
    _assert_fenced_walk(gl_ctx, backend, overlays, loop_limit, monkeypatch)


def _assert_fenced_walk(ctx, backend: str, overlays: bool, loop_limit: str, monkeypatch) -> None:
    """The walk under the recorder, with llvmpipe's loop limit or none (as on a GPU): no hazard."""
    if loop_limit == "none":
        monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    else:
        monkeypatch.delenv("RTWALK_LOOP_LIMIT", raising=False)
    rec = HazardRecorder()
    with rec.installed(monkeypatch):
        _walk(ctx, backend, overlays)
    assert not rec.unknown_programs, rec.unknown_programs
    assert sum(rec.commands.values()) > 20, rec.commands  # the walk was recorded
    assert not rec.hazards, "\n".join(sorted({str(h) for h in rec.hazards}))


# the compute stages of the GL traversals (viewer/gl/stages.py), which `auto` takes on devices other
# than a software rasterizer: their parameters, by backend
COMPUTE_STAGES = {"glsl": "stage=compute", "chcrt": "visible_stage=compute,full_bvh_stage=compute"}


@pytest.mark.parametrize("loop_limit", ["none", "llvmpipe"])
@pytest.mark.parametrize("backend", sorted(COMPUTE_STAGES))
def test_compute_stages_are_fenced(backend, loop_limit, gl_ctx, monkeypatch):
    """The compute stages, which llvmpipe never takes by default, under the same recorder: their
    dispatches, hit buffers and resolve draws need the barriers a GPU needs too."""
    monkeypatch.setenv(backend_info(backend).env_var, COMPUTE_STAGES[backend])
    _assert_fenced_walk(gl_ctx, backend, False, loop_limit, monkeypatch)


@pytest.mark.parametrize("backend", sorted(COMPUTE_STAGES))
def test_compute_stages_read_no_memory_nothing_wrote(backend, gl_ctx, monkeypatch):
    """test_no_frame_reads_memory_nothing_wrote for the compute stages (their hit buffers are new
    memory every renderer)."""
    monkeypatch.setenv(backend_info(backend).env_var, COMPUTE_STAGES[backend])
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    clean, clean_rays = _walk(gl_ctx, backend, overlays=False)
    _poison_new_memory(monkeypatch)
    poisoned, poisoned_rays = _walk(gl_ctx, backend, overlays=False)
    assert np.array_equal(clean, poisoned) and poisoned_rays == clean_rays


@pytest.mark.parametrize("backend", _backends())
def test_no_frame_reads_memory_nothing_wrote(backend, gl_ctx, monkeypatch):
    """A walk with every new buffer and texture full of POISON draws the same image, bit for bit,
    and counts the same rays as one with the driver's fresh memory: no pass reads what nothing
    wrote (a GPU's fresh memory holds garbage where llvmpipe's mostly held zeros; on an H200 a test
    read a plan buffer no pass had written). The loop limit is off, as on a GPU."""
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "none")
    clean, clean_rays = _walk(gl_ctx, backend, overlays=False)
    made = _poison_new_memory(monkeypatch)
    poisoned, poisoned_rays = _walk(gl_ctx, backend, overlays=False)
    assert made["buffers"] > 0 and made["textures"] > 0, made  # the poison reached the frame's memory
    assert clean.mean() > 1.0  # something was drawn
    differ = np.flatnonzero((clean != poisoned).any(axis=-1))
    assert differ.size == 0, f"{differ.size} of {clean.shape[0] * clean.shape[1]} pixels differ"
    assert poisoned_rays == clean_rays


# ------------------------------------------------------------------------------ the recorder itself

WRITE_SSBO = """
layout(local_size_x = 1) in;
layout(std430, binding = 3) buffer Data { uint data[]; };
void main() { data[0] = 7u; }
"""
ADD_SSBO = """
layout(local_size_x = 1) in;
layout(std430, binding = 3) buffer Data { uint data[]; };
void main() { atomicAdd(data[0], 1u); }
"""
READ_SSBO = """
layout(local_size_x = 1) in;
layout(std430, binding = 3) readonly buffer Data { uint data[]; };
layout(std430, binding = 4) writeonly buffer Out { uint result[]; };
void main() { result[0] = data[0]; }
"""


def _program(ctx, tmp_path, name: str, body: str):
    (tmp_path / name).write_text(body)
    return compute_shader(ctx, name, search=(tmp_path,))


@pytest.mark.parametrize("case", ["fenced", "unfenced", "wrong bit", "atomics", "atomic then read", "host read",
                                  "indirect"])
def test_the_recorder_knows_the_rules(case, gl_ctx, tmp_path, monkeypatch):
    """A write then a read through SSBOs: a hazard without a SHADER_STORAGE barrier, none with it;
    a barrier of another path does not count; atomics after atomics need none, a plain read after
    them does; a host read needs BUFFER_UPDATE, an indirect dispatch COMMAND."""
    ctx = gl_ctx
    write = _program(ctx, tmp_path, "hz_write.comp", WRITE_SSBO)
    add = _program(ctx, tmp_path, "hz_add.comp", ADD_SSBO)
    read = _program(ctx, tmp_path, "hz_read.comp", READ_SSBO)
    rec = HazardRecorder()
    with rec.installed(monkeypatch):
        data = ctx.buffer(np.array([1, 1, 1, 0], np.uint32).tobytes())
        out = ctx.buffer(reserve=16)
        data.bind_to_storage_buffer(3)
        out.bind_to_storage_buffer(4)
        if case == "atomics":
            add.run(1)
            add.run(1)
        elif case == "atomic then read":
            add.run(1)
            read.run(1)
        elif case == "host read":
            write.run(1)
            data.read()
        elif case == "indirect":
            write.run(1)
            read.run_indirect(data)
        else:
            write.run(1)
            if case == "fenced":
                ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
            elif case == "wrong bit":
                ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT)
            read.run(1)
        ctx.finish()
        data.release()
        out.release()
    paths = sorted({h.path for h in rec.hazards})
    expected = {"fenced": [], "unfenced": ["ssbo"], "wrong bit": ["ssbo"], "atomics": [],
                "atomic then read": ["ssbo"], "host read": ["buffer_update"], "indirect": ["command", "ssbo"]}[case]
    assert paths == expected, [str(h) for h in rec.hazards]

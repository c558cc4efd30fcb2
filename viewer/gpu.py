"""All OpenGL resource handling lives here: context creation, shader loading, scene buffers.

Other modules ask this one for programs, textures and framebuffers so that formats, bindings
and lifetimes are decided in one place.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from viewer.accel.bvh import BVH, gpu_triangles
from viewer.errors import RtwalkError
from viewer.scene import Scene

SHADER_DIR = Path(__file__).resolve().parent / "shaders"

# SSBO binding points shared by every shader (see shaders/common.glsl).
BIND_NODES = 0
BIND_TRIS = 1
BIND_MATERIALS = 2
BIND_COUNTERS = 3

_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.MULTILINE)


def create_headless_context() -> moderngl.Context:
    """An OpenGL 4.5 core context through EGL (no display needed)."""
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
    except Exception as exc:  # moderngl raises plain Exception subclasses for EGL failures
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RtwalkError(f"cannot create a headless OpenGL 4.5 context through EGL ({msg}); "
                          "install Mesa EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)") from exc
    return ctx


def load_shader_source(name: str, defines: dict[str, object] | None = None) -> str:
    """Shader text with `#include "file"` expanded and `#define`s inserted after #version."""
    seen: set[str] = set()

    def expand(fname: str) -> str:
        if fname in seen:
            return ""
        seen.add(fname)
        text = (SHADER_DIR / fname).read_text()
        return _INCLUDE.sub(lambda m: expand(m.group(1)), text)

    body = expand(name)
    header = "#version 450 core\n"
    for key, value in (defines or {}).items():
        header += f"#define {key} {value}\n"
    return header + body


class ProgramCache:
    """Compiles each (vertex, fragment, defines) combination once per context."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._programs: dict[tuple, moderngl.Program] = {}

    def get(self, vertex: str, fragment: str, defines: dict[str, object] | None = None,
            geometry: str | None = None) -> moderngl.Program:
        key = (vertex, fragment, geometry, tuple(sorted((defines or {}).items())))
        prog = self._programs.get(key)
        if prog is None:
            try:
                prog = self.ctx.program(vertex_shader=load_shader_source(vertex, defines),
                                        fragment_shader=load_shader_source(fragment, defines),
                                        geometry_shader=load_shader_source(geometry, defines) if geometry else None)
            except moderngl.Error as exc:
                raise RuntimeError(f"shader {vertex}/{fragment} failed to compile:\n{exc}") from exc
            self._programs[key] = prog
        return prog


@dataclass
class GpuScene:
    """The scene on the GPU: BVH nodes, leaf-ordered triangles, materials, raster vertices.

    Triangle ids everywhere are leaf-order slots (the scene passed in must already be
    reordered with `Scene.reordered(bvh.tri_order)`).
    """

    nodes: moderngl.Buffer
    tris: moderngl.Buffer
    materials: moderngl.Buffer
    vertices: moderngl.Buffer  # float32 (3N, 3) positions, for rasterization
    triangle_count: int
    stack_size: int
    memory_bytes: int

    @staticmethod
    def upload(ctx: moderngl.Context, scene: Scene, bvh: BVH) -> GpuScene:
        nodes = bvh.gpu_nodes()
        tris = gpu_triangles(scene.triangles, scene.material_ids)
        mats = scene.albedo_table()
        verts = np.ascontiguousarray(scene.triangles.reshape(-1, 3), dtype=np.float32)
        bufs = [ctx.buffer(nodes.tobytes()), ctx.buffer(tris.tobytes()), ctx.buffer(mats.tobytes()),
                ctx.buffer(verts.tobytes())]
        return GpuScene(*bufs, triangle_count=scene.triangle_count,
                        stack_size=int(max(16, bvh.stats.depth + 4)),
                        memory_bytes=sum(b.size for b in bufs))

    def bind(self) -> None:
        self.nodes.bind_to_storage_buffer(BIND_NODES)
        self.tris.bind_to_storage_buffer(BIND_TRIS)
        self.materials.bind_to_storage_buffer(BIND_MATERIALS)

    def release(self) -> None:
        for b in (self.nodes, self.tris, self.materials, self.vertices):
            b.release()


def float_texture(ctx: moderngl.Context, size: tuple[int, int], components: int) -> moderngl.Texture:
    tex = ctx.texture(size, components, dtype="f4")
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return tex


def int_texture(ctx: moderngl.Context, size: tuple[int, int]) -> moderngl.Texture:
    tex = ctx.texture(size, 1, dtype="i4")
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return tex


def read_texture(tex: moderngl.Texture) -> np.ndarray:
    """Texture contents as (H, W, C) in GL order (row 0 = bottom)."""
    dtype = {"f4": np.float32, "i4": np.int32, "u4": np.uint32, "f1": np.uint8, "u1": np.uint8}[tex.dtype]
    data = np.frombuffer(tex.read(), dtype=dtype)
    return data.reshape(tex.height, tex.width, tex.components)


class FullscreenQuad:
    """One triangle covering the viewport; fragment shaders do the work."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._vaos: dict[int, moderngl.VertexArray] = {}

    def render(self, program: moderngl.Program) -> None:
        vao = self._vaos.get(id(program))
        if vao is None:
            vao = self.ctx.vertex_array(program, [])
            self._vaos[id(program)] = vao
        vao.render(moderngl.TRIANGLES, vertices=3)

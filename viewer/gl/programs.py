"""Shader loading and the program cache.

Shaders are files: `#include "file"` is expanded (each file once), `#version 450 core`, the
binding-point header (viewer.gl.bindings) and the caller's `#define`s are put in front. Files are
looked up along a search path: a backend folder (viewer/backends/NAME/) can keep its own shaders
beside its code and still include the shared ones from viewer/shaders/, which always come last.

Numeric contract (docs/numerics.md): NUMERIC_PRAGMAS follow `#version` in every shader, asking
NVIDIA's compiler for IEEE arithmetic (no fast math, full precision); other compilers ignore
pragmas they do not know. The intersection math itself is `precise` (intersect.glsl), which is
the part GLSL guarantees.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import moderngl

from viewer.gl import inactive
from viewer.gl import io as glio
from viewer.gl.bindings import shader_header

inactive.install()  # a uniform NVIDIA's compiler removed and Mesa's kept is no KeyError

SHADER_DIR = Path(__file__).resolve().parents[1] / "shaders"

NUMERIC_PRAGMAS = "#pragma optionNV(fastmath off)\n#pragma optionNV(fastprecision off)\n"

_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.MULTILINE)


def _search_dirs(search: Sequence[Path | str] = ()) -> tuple[Path, ...]:
    dirs = [Path(d).resolve() for d in search]
    return tuple(dict.fromkeys([*dirs, SHADER_DIR]))


def find_shader(name: str, search: Sequence[Path | str] = (), near: Path | None = None) -> Path:
    """The file `name` names: beside the including file (`near`) first, then along `search`, then
    viewer/shaders/. FileNotFoundError lists where it looked."""
    dirs = ((near,) if near is not None else ()) + _search_dirs(search)
    for d in dirs:
        cand = d / name
        if cand.is_file():
            return cand
    raise FileNotFoundError(f"shader '{name}' not found in {', '.join(str(d) for d in dirs)}")


def load_shader_source(name: str, defines: dict[str, object] | None = None,
                       search: Sequence[Path | str] = ()) -> str:
    """Shader text with `#include "file"` expanded and NUMERIC_PRAGMAS, the binding header and the
    `#define`s inserted after #version."""
    seen: set[Path] = set()

    def expand(path: Path) -> str:
        if path in seen:
            return ""
        seen.add(path)
        text = path.read_text()
        return _INCLUDE.sub(lambda m: expand(find_shader(m.group(1), search, path.parent)), text)

    body = expand(find_shader(name, search))
    header = "#version 450 core\n" + NUMERIC_PRAGMAS + shader_header()
    for key, value in (defines or {}).items():
        header += f"#define {key} {value}\n"
    return header + body


class ProgramCache:
    """Compiles each (vertex, fragment, geometry, defines, search path) combination once per context.

    `search`: folders looked in before viewer/shaders/ (e.g. a backend's own folder); `with_path`
    gives a view of the same cache with more folders, for a backend that ships shaders."""

    def __init__(self, ctx: moderngl.Context, search: Sequence[Path | str] = (),
                 _programs: dict | None = None):
        self.ctx = ctx
        self.search = tuple(Path(d).resolve() for d in search)
        self._programs: dict[tuple, moderngl.Program] = {} if _programs is None else _programs

    def with_path(self, *folders: Path | str) -> ProgramCache:
        """The same cache (same compiled programs), looking in `folders` first."""
        return ProgramCache(self.ctx, (*folders, *self.search), self._programs)

    def get(self, vertex: str, fragment: str, defines: dict[str, object] | None = None,
            geometry: str | None = None) -> moderngl.Program:
        key = (vertex, fragment, geometry, tuple(sorted((defines or {}).items())), self.search)
        prog = self._programs.get(key)
        if prog is None:
            s = self.search
            srcs = (load_shader_source(vertex, defines, s), load_shader_source(fragment, defines, s),
                    load_shader_source(geometry, defines, s) if geometry else None)
            try:
                prog = self.ctx.program(vertex_shader=srcs[0], fragment_shader=srcs[1], geometry_shader=srcs[2])
            except moderngl.Error as exc:
                raise RuntimeError(f"shader {vertex}/{fragment} failed to compile:\n{exc}") from exc
            inactive.mark(prog, *srcs, name="/".join(filter(None, (vertex, fragment, geometry))))
            self._programs[key] = prog
        return prog

    def release(self) -> None:
        """Release every program compiled through this cache (and its views)."""
        for prog in self._programs.values():
            prog.release()
        self._programs.clear()


def compute_shader(ctx: moderngl.Context, name: str, defines: dict[str, object] | None = None,
                   search: Sequence[Path | str] = ()) -> moderngl.ComputeShader:
    """A compute shader from a file (load_shader_source), with its declared uniform names."""
    src = load_shader_source(name, defines, search)
    return inactive.mark(ctx.compute_shader(src), src, name=name)


class FullscreenQuad:
    """One triangle covering the viewport (fullscreen.vert); fragment shaders do the work."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._vaos: dict[int, moderngl.VertexArray] = {}

    def render(self, program: moderngl.Program) -> None:
        vao = self._vaos.get(id(program))
        if vao is None:
            vao = self.ctx.vertex_array(program, [])
            self._vaos[id(program)] = vao
        glio.draw(vao, moderngl.TRIANGLES, vertices=3)

    def release(self) -> None:
        for vao in self._vaos.values():
            vao.release()
        self._vaos.clear()

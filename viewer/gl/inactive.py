"""Uniforms a driver's compiler removed: setting one is a no-op, not a KeyError.

A GL program lists only its *active* uniforms, and which are active is the compiler's call: a
uniform whose value cannot change the output (a define switched its use off, or the optimiser
proved it dead) is gone. Mesa and NVIDIA optimise differently, so `prog["x"] = v` that works on
llvmpipe can raise KeyError on an NVIDIA GPU and stop every frame. Programs made through
viewer.gl.programs carry the names their source declares (`extra["declared_uniforms"]`); for
those, a declared but inactive name is written to a stand-in that drops the value, while a name
the source never declares still raises KeyError (a typo stays an error on every driver).
"""

from __future__ import annotations

import re
from typing import Any

import moderngl

_DECL = re.compile(r"\buniform\s+(?:(?:lowp|mediump|highp|coherent|volatile|restrict|readonly|writeonly)\s+)*"
                   r"\w+\s+([^;{]+);")


def declared_uniforms(*sources: str | None) -> frozenset[str]:
    """Names declared `uniform TYPE a, b[2];` outside blocks in the given shader sources."""
    names: set[str] = set()
    for src in sources:
        for decl in _DECL.findall(src or ""):
            for part in decl.split(","):
                m = re.match(r"\s*(\w+)", part)
                if m:
                    names.add(m.group(1))
    return frozenset(names)


class InactiveUniform:
    """Stands in for a declared uniform the compiler removed: writes are dropped."""

    name = ""
    value: Any = None

    def write(self, data: Any) -> None:
        """Dropped, as `value` is."""


def _declared(obj: Any, key: str) -> bool:
    extra = getattr(obj, "extra", None)
    return isinstance(extra, dict) and key in extra.get("declared_uniforms", ())


_ORIGINAL: dict[type, Any] = {}  # each class's own __getitem__, called first (no moderngl internals)


def _getitem(self: Any, key: str) -> Any:
    try:
        return _ORIGINAL[type(self)](self, key)
    except KeyError:
        if _declared(self, key):
            return InactiveUniform()
        raise


def _setitem(self: Any, key: str, value: Any) -> None:
    _getitem(self, key).value = value


def install() -> None:
    """Route moderngl's Program and ComputeShader item access through the checks above (once;
    objects without declared names behave exactly as before)."""
    for cls in (moderngl.Program, moderngl.ComputeShader):
        if cls not in _ORIGINAL:
            _ORIGINAL[cls] = cls.__getitem__
            cls.__getitem__ = _getitem
            cls.__setitem__ = _setitem


def mark(obj: Any, *sources: str | None, name: str = "") -> Any:
    """`obj` (a Program or ComputeShader) with the uniform names its sources declare, its sources
    (what tests/gl_hazards.py reads the storage blocks' and images' access qualifiers from) and
    the name of its shader files."""
    obj.extra = {"declared_uniforms": declared_uniforms(*sources), "sources": sources, "name": name}
    return obj

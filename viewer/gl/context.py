"""The headless OpenGL context: created through EGL (no display needed), one per process for tools."""

from __future__ import annotations

import moderngl

from viewer.errors import RtwalkError

_CTX: moderngl.Context | None = None


def create_headless_context() -> moderngl.Context:
    """An OpenGL 4.5 core context through EGL (no display needed)."""
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
    except Exception as exc:  # moderngl raises plain Exception subclasses for EGL failures
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RtwalkError(f"cannot create a headless OpenGL 4.5 context through EGL ({msg}); "
                          "install Mesa EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)") from exc
    return ctx


def shared_context() -> moderngl.Context:
    """The process's shared headless context (tests, tracing tools, benchmarks): created once."""
    global _CTX
    if _CTX is None:
        _CTX = create_headless_context()
    return _CTX

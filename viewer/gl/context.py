"""The headless OpenGL context: created through EGL (no display needed), one per process for tools.

EGL lists one device per driver (EGL_EXT_platform_device; glcontext opens `device_index`, default
0, or GLCONTEXT_DEVICE_INDEX). On a machine with NVIDIA's driver and Mesa both installed the order
is the vendor loader's: when device 0 is a software rasterizer (llvmpipe) and no index was asked
for, the next devices are tried and the first hardware one is taken, so a GPU run does not end up
timing llvmpipe.
"""

from __future__ import annotations

import os

import moderngl

from viewer.errors import RtwalkError

_CTX: moderngl.Context | None = None
DEVICE_INDEX_ENV = "GLCONTEXT_DEVICE_INDEX"  # read by glcontext itself
MAX_EGL_DEVICES = 8


def _is_software(ctx: moderngl.Context) -> bool:
    from viewer.gl.limits import shares_system_memory

    return shares_system_memory(ctx)


def _hardware_device(first: moderngl.Context) -> moderngl.Context:
    """`first` (device 0) unless it is a software rasterizer and another EGL device is hardware."""
    if os.environ.get(DEVICE_INDEX_ENV) or not _is_software(first):
        return first
    for index in range(1, MAX_EGL_DEVICES):
        try:
            ctx = moderngl.create_context(standalone=True, backend="egl", require=450, device_index=index)
        except Exception as exc:  # no such device ("requested device index N, but found N devices"), no GL 4.5
            if "but found" in str(exc):
                break
            continue
        if not _is_software(ctx):
            first.release()
            return ctx
        ctx.release()
    # a probe that got as far as a context made it current, a failed one too (moderngl's GL 4.5
    # check raises after glcontext made the context current): the first is made current again
    first.__enter__()
    return first


def create_headless_context() -> moderngl.Context:
    """An OpenGL 4.5 core context through EGL (no display needed), on a hardware device if any."""
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
    except Exception as exc:  # moderngl raises plain Exception subclasses for EGL failures
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        index = os.environ.get(DEVICE_INDEX_ENV, "").strip()
        hint = (f"{DEVICE_INDEX_ENV}={index} chose the EGL device; unset it to take the first" if index
                else "install Mesa EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)")
        raise RtwalkError(f"cannot create a headless OpenGL 4.5 context through EGL ({msg}); {hint}") from exc
    return _hardware_device(ctx)


def shared_context() -> moderngl.Context:
    """The process's shared headless context (tests, tracing tools, benchmarks): created once."""
    global _CTX
    if _CTX is None:
        _CTX = create_headless_context()
    return _CTX

"""A DEPTH_COMPONENT32F depth texture (moderngl's depth_texture is 24-bit fixed point).

Depth buffers that order exact ray distances (the G-buffer's t / (t + scale), the CHC+RT hit key) need
float precision: 24-bit fixed point resolves only 6e-8 of the scale, so surfaces a millimetre apart
in front of a camera in a city-sized scene would tie. moderngl cannot ask for that storage, so the
texture it creates is re-specified through the core GL entry points.
"""

from __future__ import annotations

import moderngl

from viewer.errors import RtwalkError

_GL_TEXTURE_2D = 0x0DE1
_GL_TEXTURE_BINDING_2D = 0x8069
_GL_DEPTH_COMPONENT = 0x1902
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_FLOAT = 0x1406
_GL_TEXTURE_DEPTH_SIZE = 0x884A
_GL_TEXTURE_DEPTH_TYPE = 0x8C16
_gl_funcs: dict | None = None


def _gl() -> dict:
    """A few core GL entry points through GLVND's libOpenGL (dispatches to the current context,
    EGL or GLX alike): moderngl has no way to ask for a DEPTH_COMPONENT32F texture."""
    global _gl_funcs
    if _gl_funcs is None:
        import ctypes

        lib = None
        for name in ("libOpenGL.so.0", "libGL.so.1", "libGL.so"):
            try:
                lib = ctypes.CDLL(name)
                break
            except OSError:
                continue
        if lib is None:
            raise RtwalkError("cannot load libOpenGL/libGL for the float depth buffer")
        u, i, vp = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        pi = ctypes.POINTER(ctypes.c_int)
        spec = {"glBindTexture": [u, u], "glTexImage2D": [u, i, i, i, i, i, u, u, vp],
                "glGetIntegerv": [u, pi], "glGetTexLevelParameteriv": [u, i, u, pi]}
        _gl_funcs = {}
        for name, args in spec.items():
            f = getattr(lib, name)
            f.argtypes = args
            f.restype = None
            _gl_funcs[name] = f
        _gl_funcs["ctypes"] = ctypes
    return _gl_funcs


def float_depth_texture(ctx: moderngl.Context, size: tuple[int, int]) -> moderngl.Texture:
    """A depth texture with DEPTH_COMPONENT32F storage (moderngl's depth_texture is 24-bit fixed
    point, which would quantise ray distances): moderngl's texture, storage re-specified."""
    tex = ctx.depth_texture(size)
    for _ in range(16):  # clear errors left by others: the check below must see only ours
        if ctx.error == "GL_NO_ERROR":
            break
    gl = _gl()
    ct = gl["ctypes"]
    prev = ct.c_int(0)
    gl["glGetIntegerv"](_GL_TEXTURE_BINDING_2D, ct.byref(prev))
    gl["glBindTexture"](_GL_TEXTURE_2D, tex.glo)
    gl["glTexImage2D"](_GL_TEXTURE_2D, 0, _GL_DEPTH_COMPONENT32F, size[0], size[1], 0, _GL_DEPTH_COMPONENT,
                       _GL_FLOAT, None)
    bits, kind = ct.c_int(0), ct.c_int(0)
    gl["glGetTexLevelParameteriv"](_GL_TEXTURE_2D, 0, _GL_TEXTURE_DEPTH_SIZE, ct.byref(bits))
    gl["glGetTexLevelParameteriv"](_GL_TEXTURE_2D, 0, _GL_TEXTURE_DEPTH_TYPE, ct.byref(kind))
    gl["glBindTexture"](_GL_TEXTURE_2D, prev.value)
    err = ctx.error
    if bits.value != 32 or kind.value != _GL_FLOAT or err != "GL_NO_ERROR":
        tex.release()
        raise RtwalkError(f"could not create a 32-bit float depth buffer ({bits.value} bits, {err})")
    return tex

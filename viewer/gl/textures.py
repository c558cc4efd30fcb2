"""Textures: float and integer render targets, read-back, the 32-bit float depth texture, and
buffer textures over storage buffers (TexelView)."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer.errors import RtwalkError
from viewer.gl import io as glio


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
    data = np.frombuffer(glio.read(tex), dtype=dtype)
    return data.reshape(tex.height, tex.width, tex.components)


_GL_TEXTURE_2D = 0x0DE1
_GL_TEXTURE_BINDING_2D = 0x8069
_GL_DEPTH_COMPONENT = 0x1902
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_FLOAT = 0x1406
_GL_TEXTURE_DEPTH_SIZE = 0x884A
_GL_TEXTURE_DEPTH_TYPE = 0x8C16
_GL_RED_INTEGER = 0x8D94
_GL_R32UI = 0x8236
_GL_UNSIGNED_INT = 0x1405
_GL_RED = 0x1903
_GL_INT = 0x1404
_GL_TEXTURE_BUFFER = 0x8C2A
_GL_RGBA32UI = 0x8D70
_GL_MAX_TEXTURE_BUFFER_SIZE = 0x8C2B
_GL_TEXTURE_BUFFER_OFFSET_ALIGNMENT = 0x919F
TEXEL_BYTES = 16  # one RGBA32UI texel of a TexelView
_gl_funcs: dict | None = None


def _gl() -> dict:
    """A few core GL entry points through GLVND's libOpenGL (dispatches to the current context,
    EGL or GLX alike): moderngl has no way to ask for a DEPTH_COMPONENT32F texture, nor to copy an
    integer texture (its copy_framebuffer leaves an R32I target unwritten), nor to make a buffer
    texture."""
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
            raise RtwalkError("cannot load libOpenGL/libGL for the 32-bit float depth buffer")
        u, i, vp = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        pi = ctypes.POINTER(ctypes.c_int)
        spec = {"glBindTexture": [u, u], "glTexImage2D": [u, i, i, i, i, i, u, u, vp],
                "glGetIntegerv": [u, pi], "glGetTexLevelParameteriv": [u, i, u, pi],
                "glCopyImageSubData": [u, u, i, i, i, i, u, u, i, i, i, i, i, i, i],
                "glClearTexImage": [u, i, u, u, vp], "glCreateTextures": [u, i, pi],
                "glDeleteTextures": [i, pi], "glBindTextureUnit": [u, u],
                "glTextureBufferRange": [u, u, u, ctypes.c_ssize_t, ctypes.c_ssize_t],
                "glClearNamedBufferSubData": [u, u, ctypes.c_ssize_t, ctypes.c_ssize_t, u, u, vp]}
        funcs: dict = {}
        for name, args in spec.items():
            f = getattr(lib, name)
            f.argtypes = args
            f.restype = None
            funcs[name] = f
        funcs["ctypes"] = ctypes
        _gl_funcs = funcs
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


def copy_texture(dst: moderngl.Texture, src: moderngl.Texture) -> None:
    """Copy level 0 of a 2D texture into one of the same size and format on the device
    (glCopyImageSubData: works for integer formats, no framebuffer, nothing read back)."""
    if dst.size != src.size or dst.dtype != src.dtype or dst.components != src.components:
        raise RtwalkError("copy_texture: textures differ in size or format")
    w, h = src.size
    _gl()["glCopyImageSubData"](src.glo, _GL_TEXTURE_2D, 0, 0, 0, 0, dst.glo, _GL_TEXTURE_2D, 0, 0, 0, 0, w, h, 1)


def clear_int_texture(tex: moderngl.Texture, value: int = -1) -> None:
    """Every texel of level 0 of an R32I texture set to `value` (glClearTexImage). A framebuffer
    clear (glClear with the float clear colour) leaves an integer attachment undefined by the GL
    spec: Mesa stores the float's bits (-1.0 -> 0xBF800000, negative), another driver may convert or
    not write it at all."""
    if tex.dtype != "i4" or tex.components != 1:
        raise RtwalkError("clear_int_texture: not an R32I texture")
    gl = _gl()
    v = gl["ctypes"].c_int32(int(value))
    gl["glClearTexImage"](tex.glo, 0, _GL_RED_INTEGER, _GL_INT, gl["ctypes"].byref(v))


def clear_uint_buffer(buf: moderngl.Buffer, count: int, offset: int = 0) -> None:
    """`count` uint32s of `buf` from byte `offset` set to 0 on the device (glClearNamedBufferSubData:
    no host data, no draw)."""
    if count <= 0:
        return
    gl = _gl()
    zero = gl["ctypes"].c_uint32(0)
    gl["glClearNamedBufferSubData"](buf.glo, _GL_R32UI, int(offset), 4 * int(count), _GL_RED_INTEGER,
                                    _GL_UNSIGNED_INT, gl["ctypes"].byref(zero))


def clear_float_texture(tex: moderngl.Texture, value: float) -> None:
    """Every texel of level 0 of a one-component float texture (R32F, or a float depth texture) set
    to `value` (glClearTexImage: no framebuffer, no draw)."""
    if tex.dtype != "f4" or tex.components != 1:
        raise RtwalkError("clear_float_texture: not a one-component float texture")
    gl = _gl()
    v = gl["ctypes"].c_float(float(value))
    fmt = _GL_DEPTH_COMPONENT if tex.depth else _GL_RED
    gl["glClearTexImage"](tex.glo, 0, fmt, _GL_FLOAT, gl["ctypes"].byref(v))


class IntTextures:
    """Named R32I textures at the ray-batch size, rewritten every pass (a backend's overlays):
    a texture is made again only when the size changes."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.textures: dict[str, moderngl.Texture] = {}

    def write(self, name: str, size: tuple[int, int], data) -> moderngl.Texture:
        """The texture `name` at `size` holding `data` (int32, one value per pixel, row 0 = bottom)."""
        tex = self.textures.get(name)
        if tex is None or tuple(tex.size) != tuple(size):
            if tex is not None:
                tex.release()
            tex = int_texture(self.ctx, size)
            self.textures[name] = tex
        glio.write(tex, np.ascontiguousarray(data, np.int32))
        return tex

    def release(self) -> None:
        for tex in self.textures.values():
            tex.release()
        self.textures.clear()


def texel_buffer_limit() -> tuple[int, int]:
    """(GL_MAX_TEXTURE_BUFFER_SIZE in texels, GL_TEXTURE_BUFFER_OFFSET_ALIGNMENT in bytes) of the
    current context."""
    gl = _gl()
    ct = gl["ctypes"]
    texels, align = ct.c_int(0), ct.c_int(0)
    gl["glGetIntegerv"](_GL_MAX_TEXTURE_BUFFER_SIZE, ct.byref(texels))
    gl["glGetIntegerv"](_GL_TEXTURE_BUFFER_OFFSET_ALIGNMENT, ct.byref(align))
    return int(texels.value), max(int(align.value), 1)


class TexelView:
    """A buffer texture (RGBA32UI, TEXEL_BYTES a texel) over a byte range of a storage buffer, bound
    to one texture unit: a shader reads the buffer with texelFetch(usamplerBuffer) instead of an
    SSBO load. Why: Mesa's llvmpipe (22.x) turns every SSBO load into a loop over the SIMD lanes
    with a branch and a bounds check per lane and component, while a texel fetch is one gather; the
    BVH traversals read their nodes and triangles, and CHC+RT its records' items, this way (on
    llvmpipe glsl traces 1.7-2x the rays a second on city-near and sponza, docs/results/benchmarks.md).
    On GPUs both paths go through the same caches. The shader declares
    `layout(binding = UNIT) uniform usamplerBuffer name;` (moderngl cannot set such a uniform).

    `attach` re-points the texture every time it is called (cheap state calls, no copy): a buffer
    re-made or orphaned since stays correct."""

    def __init__(self, unit: int):
        self.unit = unit
        self.name = 0

    def attach(self, buf: moderngl.Buffer, offset: int = 0, size: int | None = None) -> None:
        """View `size` bytes of `buf` from `offset` (default: to its end) and bind the view to the unit."""
        gl = _gl()
        ct = gl["ctypes"]
        size = buf.size - offset if size is None else size
        limit, align = texel_buffer_limit_cached()
        if offset % align or size > limit * TEXEL_BYTES or size <= 0:
            raise RtwalkError(f"buffer texture of {size} bytes at offset {offset}: this OpenGL device allows "
                              f"{limit} texels of {TEXEL_BYTES} bytes at offsets that are multiples of {align}")
        if not self.name:
            n = ct.c_int(0)
            gl["glCreateTextures"](_GL_TEXTURE_BUFFER, 1, ct.byref(n))
            self.name = int(n.value)
        gl["glTextureBufferRange"](self.name, _GL_RGBA32UI, buf.glo, offset, size)
        gl["glBindTextureUnit"](self.unit, self.name)

    def release(self) -> None:
        if self.name:
            gl = _gl()
            gl["glDeleteTextures"](1, gl["ctypes"].byref(gl["ctypes"].c_int(self.name)))
            self.name = 0


_texel_limit: tuple[int, int] | None = None


def texel_buffer_limit_cached() -> tuple[int, int]:
    """texel_buffer_limit(), asked once per process (a device's limit does not change)."""
    global _texel_limit
    if _texel_limit is None:
        _texel_limit = texel_buffer_limit()
    return _texel_limit

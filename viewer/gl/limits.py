"""Device limits checked before the frame-sized render targets are allocated.

A too-large `--size` must end in one line (RtwalkError), not in moderngl's "the framebuffer is not
complete" traceback or an out-of-memory kill: the side limits the driver reports
(GL_MAX_TEXTURE_SIZE, GL_MAX_RENDERBUFFER_SIZE, GL_MAX_VIEWPORT_DIMS) are checked first, then an
estimate of the targets' memory against the memory free for them (`gl_memory_available`): what
the process may still allocate where the device shares system memory (a software rasterizer), the
free video memory where the driver tells it (GL_NVX_gpu_memory_info, GL_ATI_meminfo). Core OpenGL
cannot tell it, so the allocation itself is guarded too (`allocation_guard`).

RTWALK_GL_MEMORY_MIB lowers the memory counted free (never raises it): tests simulate a small
device with it on every device, as RTWALK_CL_GLOBAL_MIB does for OpenCL.
"""

from __future__ import annotations

import ctypes
import os
from contextlib import contextmanager

import moderngl

from viewer import sysmem
from viewer.errors import RtwalkError

GL_MEMORY_ENV = "RTWALK_GL_MEMORY_MIB"
GPU_MEMORY_INFO_CURRENT_AVAILABLE_VIDMEM_NVX = 0x9049  # KiB
TEXTURE_FREE_MEMORY_ATI = 0x87FC  # 4 ints, the first: KiB free in the pool

# bytes per pixel of the renderer's own frame-sized targets: G-buffer (3 x RGBA32F + R32I id +
# 32-bit depth), the accumulators (5 x RGBA32F), the shaded colour (RGBA8), rays (2 x RGBA32F) and
# hits (R32F + R32I); backends add their own on top, so this is a lower bound
TARGET_BYTES_PER_PIXEL = 3 * 16 + 4 + 4 + 5 * 16 + 4 + 2 * 16 + 8
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "lavapipe")


def max_target_side(ctx: moderngl.Context) -> int:
    """The largest width or height a colour/depth target may have on this device."""
    info = ctx.info
    sides = [int(info.get("GL_MAX_TEXTURE_SIZE") or 0), int(info.get("GL_MAX_RENDERBUFFER_SIZE") or 0)]
    dims = info.get("GL_MAX_VIEWPORT_DIMS")
    if dims:
        sides += [int(d) for d in dims]
    sides = [s for s in sides if s > 0]
    return min(sides) if sides else 16384


def is_software_renderer(renderer: str | None) -> bool:
    """A GL_RENDERER string of a CPU rasterizer (its "device" memory is the host's, and its draws
    and dispatches run on the host's cores)."""
    return any(name in str(renderer or "").lower() for name in SOFTWARE_RENDERERS)


def shares_system_memory(ctx: moderngl.Context) -> bool:
    return is_software_renderer(ctx.info.get("GL_RENDERER"))


def host_time_label(renderer: str | None) -> str:
    """How to name iostats' python_ms on this device: on a CPU rasterizer it also holds the
    rendering that draws and dispatches run on the host, so it is not the host's own time."""
    return "host time (incl. CPU rendering)" if is_software_renderer(renderer) else "host time"


def _gl_integers(ctx: moderngl.Context, enum: int, n: int) -> list[int] | None:
    """glGetIntegerv(enum) in the current context (moderngl has no getter for extension enums);
    None where the GL library cannot be loaded or the driver sets an error."""
    from viewer.gl.textures import _gl  # the package's ctypes entry points (GLVND's libOpenGL)

    try:
        get = _gl()["glGetIntegerv"]
    except RtwalkError:
        return None
    out = (ctypes.c_int * n)(*([-1] * n))
    get(enum, out)
    ok = ctx.error == "GL_NO_ERROR"  # reads (and clears) the error flag
    return list(out) if ok and out[0] >= 0 else None


def video_memory_free(ctx: moderngl.Context) -> int | None:
    """Bytes of video memory free, where the driver tells it (NVIDIA: GL_NVX_gpu_memory_info; AMD:
    GL_ATI_meminfo), else None."""
    ext = ctx.extensions
    if "GL_NVX_gpu_memory_info" in ext:
        kib = _gl_integers(ctx, GPU_MEMORY_INFO_CURRENT_AVAILABLE_VIDMEM_NVX, 1)
    elif "GL_ATI_meminfo" in ext:
        kib = _gl_integers(ctx, TEXTURE_FREE_MEMORY_ATI, 4)
    else:
        return None
    return None if kib is None else kib[0] * 1024


def gl_memory_available(ctx: moderngl.Context) -> int | None:
    """Bytes free for new render targets, or None if unknown: the host's where the device shares
    system memory, the free video memory where the driver tells it; RTWALK_GL_MEMORY_MIB caps it."""
    found = sysmem.available_bytes() if shares_system_memory(ctx) else video_memory_free(ctx)
    text = os.environ.get(GL_MEMORY_ENV, "").strip()
    if not text:
        return found
    try:
        cap = int(float(text) * 2**20)
    except ValueError:
        raise RtwalkError(f"{GL_MEMORY_ENV}={text!r}: not a number of MiB") from None
    if not cap > 0:
        raise RtwalkError(f"{GL_MEMORY_ENV}={text!r}: must be > 0 MiB")
    return cap if found is None else min(found, cap)


def check_target_size(ctx: moderngl.Context, size: tuple[int, int], what: str = "--size") -> None:
    """RtwalkError (one line) when targets of `size` cannot exist on this device."""
    w, h = size
    side = max_target_side(ctx)
    if w > side or h > side:
        raise RtwalkError(f"{what} {w}x{h}: larger than this OpenGL device allows ({side} pixels per side, "
                          f"{ctx.info.get('GL_RENDERER', 'unknown renderer')})")
    need = w * h * TARGET_BYTES_PER_PIXEL
    avail = gl_memory_available(ctx)
    if avail is not None and need > avail:
        raise RtwalkError(f"{what} {w}x{h}: its render targets need at least {sysmem.gib(need)}, only "
                          f"{sysmem.gib(avail)} can be allocated here; choose a smaller size")


def check_storage_block(ctx: moderngl.Context, nbytes: int, what: str) -> None:
    """RtwalkError (one line) when a shader storage block of `nbytes` is larger than this device lets a
    shader address (GL_MAX_SHADER_STORAGE_BLOCK_SIZE: 128 MiB on llvmpipe, the spec's minimum)."""
    cap = int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 0) or 0)
    if cap and nbytes > cap:
        raise RtwalkError(f"{what}: {sysmem.gib(nbytes)} in one storage block, this OpenGL device addresses at "
                          f"most {sysmem.gib(cap)} ({ctx.info.get('GL_RENDERER', 'unknown renderer')}); "
                          "choose a smaller size")


@contextmanager
def allocation_guard(size: tuple[int, int], what: str = "--size"):
    """Turn moderngl's allocation failures (incomplete framebuffer, out of memory) while creating
    the targets of `size` into one line."""
    try:
        yield
    except moderngl.Error as exc:
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RtwalkError(f"{what} {size[0]}x{size[1]}: the render targets cannot be allocated on this "
                          f"device ({text}); choose a smaller size") from None

"""All OpenGL resource handling: one home for what every pass and GL backend shares.

- context: the headless EGL context (create_headless_context, shared_context)
- bindings: the one table of SSBO and image binding points (Python and, as #defines, GLSL)
- programs: shader loading with #include and a search path, the program cache, the full-screen quad
- textures: float/int textures, read-back, the 32-bit float depth texture
- buffers: stream buffers (orphaned SSBOs for per-draw records)
- scene: the scene's GPU buffers (BVH nodes, triangles, materials, vertices)

A package rather than the single viewer/gpu.py: each part has one job and the parts that need raw
GL (ctypes) or EGL stay out of the way of those that do not. viewer/gpu.py re-exports the old names.
"""

from viewer.gl.bindings import glsl_header
from viewer.gl.buffers import StreamBuffer
from viewer.gl.context import create_headless_context, shared_context
from viewer.gl.programs import SHADER_DIR, FullscreenQuad, ProgramCache, load_shader_source
from viewer.gl.textures import float_depth_texture, float_texture, int_texture, read_texture

__all__ = ["SHADER_DIR", "FullscreenQuad", "ProgramCache", "StreamBuffer", "create_headless_context",
           "float_depth_texture", "float_texture", "glsl_header", "int_texture", "load_shader_source",
           "read_texture", "shared_context"]

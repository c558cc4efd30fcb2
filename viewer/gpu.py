"""Old home of the GL helpers, kept so existing imports work: everything lives in viewer.gl now
(context, bindings, programs, textures, buffers, scene)."""

from viewer.gl.bindings import BIND_COUNTERS, BIND_MATERIALS, BIND_NODES, BIND_TRIS
from viewer.gl.context import create_headless_context
from viewer.gl.programs import SHADER_DIR, FullscreenQuad, ProgramCache, load_shader_source
from viewer.gl.scene import GpuScene
from viewer.gl.textures import float_texture, int_texture, read_texture

__all__ = ["BIND_COUNTERS", "BIND_MATERIALS", "BIND_NODES", "BIND_TRIS", "SHADER_DIR", "FullscreenQuad", "GpuScene",
           "ProgramCache", "create_headless_context", "float_texture", "int_texture", "load_shader_source",
           "read_texture"]

"""glsl: the full-BVH GLSL baseline, a backend folder with its code (glsl.py) and its shader
(trace_glsl_body.glsl, a fragment or a compute stage, run by viewer.backends.gl_traversal, which chcrt
shares)."""

from viewer.backends.glsl.glsl import GlslBackend

__all__ = ["GlslBackend"]

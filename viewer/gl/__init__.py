"""All OpenGL resource handling: one home for what every pass and GL backend shares.

- context: the headless EGL context (create_headless_context, shared_context)
- bindings: the one table of SSBO and image binding points (Python and, as #defines, GLSL)
- programs: shader loading with #include and a search path, the program cache, the full-screen quad
- textures: float/int textures, read-back, the 32-bit float depth texture
- buffers: stream buffers (orphaned SSBOs for per-draw records)
- scene: the scene's GPU buffers (BVH nodes, triangles, materials; the raster pulls vertices from the triangles)

A package of small modules: each part has one job and the parts that need raw GL (ctypes) or EGL
stay out of the way of those that do not. Import each name from its module (viewer.gl.textures,
...); this package re-exports nothing, so every name has one home.
"""

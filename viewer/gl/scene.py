"""The scene on the GPU: BVH nodes, leaf-ordered triangles and materials (the raster pulls its
vertices from the triangles: viewer/shaders/gbuffer.vert)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import moderngl
import numpy as np

from viewer.accel.bvh import BVH, gpu_triangles
from viewer.errors import RtwalkError
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_MATERIALS, BIND_NODES, BIND_TEX_NODES, BIND_TEX_TRIS, BIND_TRIS
from viewer.gl.textures import TEXEL_BYTES, TexelView, texel_buffer_limit_cached
from viewer.scene import Scene

NODE_BYTES = 64  # GPU_NODE_DTYPE
TRI_BYTES = 48  # GPU_TRI_DTYPE
FETCH_ENV = "RTWALK_SCENE_FETCH"  # "texels" or "ssbo": force the traversals' fetch path (A/B timing)


def choose_texels(triangles: int, nodes: int) -> bool:
    """Whether the traversals read nodes and triangles through buffer textures (SCENE_TEXELS): when
    both buffers fit the device's buffer-texture limit (GL_MAX_TEXTURE_BUFFER_SIZE texels: 2^27 on
    llvmpipe, about 44 M triangles), unless RTWALK_SCENE_FETCH says otherwise."""
    forced = os.environ.get(FETCH_ENV, "").strip().lower()
    if forced not in ("", "texels", "ssbo"):
        raise RtwalkError(f"{FETCH_ENV}={forced!r}: expected 'texels' or 'ssbo'")
    limit, _ = texel_buffer_limit_cached()
    fits = max(triangles * TRI_BYTES, nodes * NODE_BYTES) <= limit * TEXEL_BYTES
    if forced == "texels" and not fits:
        raise RtwalkError(f"{FETCH_ENV}=texels: the scene's buffers exceed this device's buffer-texture limit "
                          f"({limit} texels)")
    return fits if forced == "" else forced == "texels"


@dataclass
class GpuScene:
    """The scene on the GPU: BVH nodes, leaf-ordered triangles, materials.

    Triangle ids everywhere are leaf-order slots (the scene passed in must already be
    reordered with `Scene.reordered(bvh.tri_order)`).

    The BVH node buffer is made on first use (`require_nodes`, or a `bind()` that asks for it):
    only backends that traverse the tree in GLSL read it, and on a 10 M-triangle scene traced by
    an OpenCL backend its packing and upload were 1.3 s of the first frame for nothing.

    `texels` (choose_texels): the traversals read nodes and triangles through buffer textures over
    these same buffers (scene.glsl loadNode/loadTri under SCENE_TEXELS, trace_defines()); bind()
    binds them with the SSBOs.
    """

    tris: moderngl.Buffer
    materials: moderngl.Buffer
    triangle_count: int
    stack_size: int
    memory_bytes: int
    bvh: BVH  # the tree `nodes` is packed from (refits replace it through update())
    ctx: moderngl.Context
    texels: bool = False
    _nodes: moderngl.Buffer | None = None
    _views: tuple[TexelView, TexelView] = field(
        default_factory=lambda: (TexelView(BIND_TEX_NODES), TexelView(BIND_TEX_TRIS)))

    @staticmethod
    def upload(ctx: moderngl.Context, scene: Scene, bvh: BVH) -> GpuScene:
        tris = scene.gpu_triangles()
        mats = scene.albedo_table()
        # the arrays themselves (buffer protocol), not tobytes() copies: at 10 M triangles those
        # were 1.9 s of the first frame. No vertex buffer: the raster reads the triangles (vertex
        # pulling), 36 bytes a triangle less to pack, upload and keep.
        bufs = [ctx.buffer(np.ascontiguousarray(a)) for a in (tris, mats)]
        return GpuScene(*bufs, triangle_count=scene.triangle_count,
                        stack_size=int(max(16, bvh.stats.depth + 4)),
                        memory_bytes=sum(b.size for b in bufs), bvh=bvh, ctx=ctx,
                        texels=choose_texels(scene.triangle_count, len(bvh.node_min)))

    def trace_defines(self) -> dict[str, object]:
        """The `#define`s of a program that reads nodes or triangles through loadNode/loadTri."""
        return {"SCENE_TEXELS": 1} if self.texels else {}

    @property
    def has_nodes(self) -> bool:
        return self._nodes is not None

    def require_nodes(self) -> moderngl.Buffer:
        """The BVH node buffer (bvh.gpu_nodes()), uploaded now if it was not yet."""
        if self._nodes is None:
            self._nodes = self.ctx.buffer(np.ascontiguousarray(self.bvh.gpu_nodes()))
            self.memory_bytes += self._nodes.size
        return self._nodes

    @property
    def nodes(self) -> moderngl.Buffer:
        return self.require_nodes()

    def update(self, scene: Scene, bvh: BVH) -> None:
        """Moved triangles (animated scenes): rewrite nodes and triangles in place.
        The buffers keep their identity, so every holder (G-buffer VAO, backends) sees the new
        geometry; sizes must match (same triangle count, same tree topology: a refit)."""
        self.bvh = bvh
        tris = gpu_triangles(scene.triangles, scene.material_ids).tobytes()
        parts = [(self.tris, tris)]
        if self._nodes is not None:  # not made yet: made from the new tree when first needed
            parts.append((self._nodes, bvh.gpu_nodes().tobytes()))
        for buf, data in parts:
            if buf.size != len(data):
                raise ValueError(f"GpuScene.update: {len(data)} bytes for a {buf.size}-byte buffer")
            glio.write(buf, data)

    def bind(self, nodes: bool = True) -> None:
        """The scene's storage buffers at their bindings; `nodes=False` for passes that read only
        triangles and materials (the raster): the node buffer is then neither made nor bound."""
        if nodes:
            self.require_nodes().bind_to_storage_buffer(BIND_NODES)
        self.tris.bind_to_storage_buffer(BIND_TRIS)
        self.materials.bind_to_storage_buffer(BIND_MATERIALS)
        self.bind_texels(self._nodes if nodes else None, self.tris)

    def bind_texels(self, nodes: moderngl.Buffer | None, tris: moderngl.Buffer) -> None:
        """With `texels`: the buffer textures of loadNode/loadTri over `nodes` (None: left as they
        are) and `tris`. Out-of-core CHC+RT points them at its cache's buffers."""
        if not self.texels:
            return
        if nodes is not None:
            self._views[0].attach(nodes)
        self._views[1].attach(tris)

    def release(self) -> None:
        for view in self._views:
            view.release()
        for b in (self._nodes, self.tris, self.materials):
            if b is not None:
                b.release()
        self._nodes = None

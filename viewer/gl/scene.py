"""The scene on the GPU: BVH nodes, leaf-ordered triangles, materials and raster vertices."""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from viewer.accel.bvh import BVH, gpu_triangles
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_MATERIALS, BIND_NODES, BIND_TRIS
from viewer.scene import Scene


@dataclass
class GpuScene:
    """The scene on the GPU: BVH nodes, leaf-ordered triangles, materials, raster vertices.

    Triangle ids everywhere are leaf-order slots (the scene passed in must already be
    reordered with `Scene.reordered(bvh.tri_order)`).
    """

    nodes: moderngl.Buffer
    tris: moderngl.Buffer
    materials: moderngl.Buffer
    vertices: moderngl.Buffer  # float32 (3N, 3) positions, for rasterization
    triangle_count: int
    stack_size: int
    memory_bytes: int

    @staticmethod
    def upload(ctx: moderngl.Context, scene: Scene, bvh: BVH) -> GpuScene:
        nodes = bvh.gpu_nodes()
        tris = scene.gpu_triangles()
        mats = scene.albedo_table()
        verts = np.ascontiguousarray(scene.triangles.reshape(-1, 3), dtype=np.float32)
        # the arrays themselves (buffer protocol), not tobytes() copies: at 10 M triangles those
        # were 1.9 s of the first frame
        bufs = [ctx.buffer(np.ascontiguousarray(a)) for a in (nodes, tris, mats, verts)]
        return GpuScene(*bufs, triangle_count=scene.triangle_count,
                        stack_size=int(max(16, bvh.stats.depth + 4)),
                        memory_bytes=sum(b.size for b in bufs))

    def update(self, scene: Scene, bvh: BVH) -> None:
        """Moved triangles (animated scenes): rewrite nodes, triangles and raster vertices in place.
        The buffers keep their identity, so every holder (G-buffer VAO, backends) sees the new
        geometry; sizes must match (same triangle count, same tree topology: a refit)."""
        nodes = bvh.gpu_nodes().tobytes()
        tris = gpu_triangles(scene.triangles, scene.material_ids).tobytes()
        verts = np.ascontiguousarray(scene.triangles.reshape(-1, 3), dtype=np.float32).tobytes()
        for buf, data in ((self.nodes, nodes), (self.tris, tris), (self.vertices, verts)):
            if buf.size != len(data):
                raise ValueError(f"GpuScene.update: {len(data)} bytes for a {buf.size}-byte buffer")
            glio.write(buf, data)

    def bind(self) -> None:
        self.nodes.bind_to_storage_buffer(BIND_NODES)
        self.tris.bind_to_storage_buffer(BIND_TRIS)
        self.materials.bind_to_storage_buffer(BIND_MATERIALS)

    def release(self) -> None:
        for b in (self.nodes, self.tris, self.materials, self.vertices):
            b.release()

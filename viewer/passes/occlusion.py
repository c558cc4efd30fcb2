"""GPU-driven occlusion culling of the G-buffer raster (CHC++'s temporal coherence, as two passes).

CHC++ (Mattausch, Bittner, Wimmer 2008) draws what was visible last frame first and then queries
the rest against the depth that drew. Waiting for occlusion query results is what a GPU-shaped
frame must not do, so the queries here are a compute pass over a distance pyramid (Hi-Z) instead,
and the draws are multi-draw-indirect commands written on the device; the host sends camera
uniforms and reads nothing. Per frame, over the BVH cut of viewer.passes.cull:

1. `occlusion_select.comp` phase 1: a draw command per cut node in the view pyramid that was
   visible last frame (the others get zero instances); one multi-draw-indirect.
2. `hiz.comp`: the farthest drawn distance per pyramid texel, level 0 from the G-buffer, then one
   dispatch per level (log2 of the size: the count does not depend on the scene).
3. phase 2: draw the other nodes in the view pyramid whose box the pyramid cannot prove hidden;
   one multi-draw-indirect.
4. the pyramid again, and phase 3: the nodes not hidden by the final image are next frame's set.

With no last frame (the first draw) or a camera jump (`jumped`: moved or turned too far for last
frame's set to hide much), phase 1's set is a guess made on the host instead (`seed`): the nodes in
the view pyramid nearest the camera, up to SEED_TRIANGLES_PER_PIXEL triangles a pixel. What is
near hides what is far, so phase 2 then culls nearly as well as with a real last frame (city 10 M
at 320x180: first frame 7.9 M triangles drawn, 3.9 s on llvmpipe -> 1.17 M, 0.74 s). A guess only
decides the draw order: the picture is the same.

Exact: a node is dropped only when every fragment it could produce would fail the depth test, so
the G-buffer is the unculled one (tests/test_gbuffer_cull.py; ties between equal distances on shared
edges may resolve in the other order, as the draw order changes). A camera move costs raster work
(phase 2 draws what became visible), never a wrong pixel.

Buffers (std430): nodes (K, 8) of {vec3 lo; int first; vec3 hi; int count} = 32 bytes per node,
visible uint32 (K,), two command buffers uint32 (K, 5) (DrawArraysIndirectCommand + a padding word,
moderngl's stride), stats uint32 [tris, nodes] per phase 1 and 2.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from viewer import iostats
from viewer.accel.bvh import BVH
from viewer.camera import Camera
from viewer.gl import io as glio
from viewer.gl.bindings import BIND_CULL_CMDS, BIND_CULL_NODES, BIND_CULL_STATS, BIND_CULL_VISIBLE, BIND_IMG_HIZ
from viewer.gl.programs import compute_shader
from viewer.passes.cull import Cut, frustum_planes
from viewer.passes.uniforms import apply, camera_uniforms

HIZ_TEXTURE_UNIT = 7  # texture units used while culling (the G-buffer pass binds none of its own)
SEED_TRIANGLES_PER_PIXEL = 1.0  # phase 1's guessed set without a last frame: the nearest nodes, up to this
JUMP_DISTANCE = 0.1  # a camera jump: moved this fraction of the cut's extent, or turned by over
JUMP_COS = 0.7  # ~45 degrees (cosine between the old and new view directions below this)


def pyramid_levels(size: tuple[int, int]) -> int:
    """Mip levels down to 1x1 (GL's floor halving): log2 of the larger side, plus one."""
    return 1 + int(math.floor(math.log2(max(size))))


class OcclusionCuller:
    """The device state of the two-pass culling for one cut; `draw` replaces the raster's draw."""

    def __init__(self, ctx: moderngl.Context, cut: Cut, bvh: BVH):
        self.ctx = ctx
        self.select = compute_shader(ctx, "occlusion_select.comp")
        self.reduce = compute_shader(ctx, "hiz.comp")
        self.count = len(cut.nodes)
        k = max(self.count, 1)
        self.nodes = ctx.buffer(reserve=k * 32)
        self.visible = ctx.buffer(np.ones(k, np.uint32).tobytes())  # replaced by `seed` on the first draw
        self.cmds = (ctx.buffer(reserve=k * 20), ctx.buffer(reserve=k * 20))
        self.stats = ctx.buffer(reserve=16)
        self._hiz: moderngl.Texture | None = None
        self._cut = cut
        self._last_view: tuple[np.ndarray, np.ndarray] | None = None  # (eye, forward) of the last draw
        self.seeded = 0  # nodes the last `seed` put in phase 1's set (0: last frame's set was used)
        self.seeded_triangles = 0  # and the triangles they hold
        self.set_boxes(bvh)

    def set_boxes(self, bvh: BVH) -> None:
        """The cut nodes' boxes (again after a refit: same topology, new boxes)."""
        rec = np.zeros((max(self.count, 1), 8), np.float32)
        n = self.count
        rec[:n, 0:3] = bvh.node_min[self._cut.nodes]
        rec[:n, 4:7] = bvh.node_max[self._cut.nodes]
        ints = rec.view(np.int32)
        ints[:n, 3] = self._cut.first
        ints[:n, 7] = self._cut.count
        glio.write(self.nodes, rec)
        self._lo = bvh.node_min[self._cut.nodes].astype(np.float64)  # for `seed`
        self._hi = bvh.node_max[self._cut.nodes].astype(np.float64)
        extent = (self._hi.max(axis=0) - self._lo.min(axis=0)) if n else np.zeros(3)
        self._extent = float(np.linalg.norm(extent))

    def jumped(self, camera: Camera) -> bool:
        """No last frame, or the camera moved or turned so far that last frame's set says little."""
        if self._last_view is None:
            return True
        eye, fwd = self._last_view
        new_eye = np.asarray(camera.position, np.float64)
        new_fwd = np.asarray(camera.forward, np.float64)
        return bool(np.linalg.norm(new_eye - eye) > JUMP_DISTANCE * self._extent
                    or float(new_fwd @ fwd) < JUMP_COS)

    def seed(self, camera: Camera, size: tuple[int, int]) -> None:
        """Phase 1's set guessed on the host (see the module docstring): the nodes in the view
        pyramid by distance from the camera to their box, nearest first, until they hold
        SEED_TRIANGLES_PER_PIXEL triangles a pixel (at least one node). One vectorised pass over
        the cut and one small upload (4 bytes a node), only on a first draw or a jump."""
        if self.count == 0:
            return
        eye = np.asarray(camera.position, np.float64)
        lo, hi = self._lo - eye, self._hi - eye
        near = np.linalg.norm(np.maximum(np.maximum(lo, -hi), 0.0), axis=1)  # 0 when the eye is inside
        planes = frustum_planes(camera, size[0] / size[1])
        far = np.where(planes[None, :, :] >= 0, hi[:, None, :], lo[:, None, :])
        inside = (np.einsum("kpj,pj->kp", far, planes) >= 0).all(axis=1)  # a guess: no tolerance needed
        order = np.argsort(np.where(inside, near, np.inf), kind="stable")[: int(inside.sum())]
        held = np.cumsum(self._cut.count[order])
        take = int(np.searchsorted(held, SEED_TRIANGLES_PER_PIXEL * size[0] * size[1])) + 1
        visible = np.zeros(self.count, np.uint32)
        visible[order[:take]] = 1
        glio.write(self.visible, visible)
        self.seeded = min(take, len(order))
        self.seeded_triangles = int(held[self.seeded - 1]) if self.seeded else 0

    def _pyramid(self, size: tuple[int, int]) -> moderngl.Texture:
        if self._hiz is None or self._hiz.size != tuple(size):
            if self._hiz is not None:
                self._hiz.release()
            self._hiz = self.ctx.texture(size, 1, dtype="f4")
            self._hiz.build_mipmaps()  # allocates every level (written by hiz.comp)
            self._hiz.filter = (moderngl.NEAREST_MIPMAP_NEAREST, moderngl.NEAREST)
        return self._hiz

    def _build_pyramid(self, position: moderngl.Texture, tri_id: moderngl.Texture,
                       depth: tuple[moderngl.Texture, float] | None = None) -> int:
        """Levels 0..L of the distance pyramid from the G-buffer as drawn so far; returns L + 1.
        Distances from position.w, or with `depth` = (texture, depth scale) an upper bound from the
        exact raster's depth t / (t + scale) (hiz.comp distanceAbove)."""
        ctx, red = self.ctx, self.reduce
        hiz = self._pyramid(position.size)
        w, h = position.size
        levels = pyramid_levels((w, h))
        (position if depth is None else depth[0]).use(HIZ_TEXTURE_UNIT)
        tri_id.use(HIZ_TEXTURE_UNIT + 1)
        hiz.use(HIZ_TEXTURE_UNIT + 2)
        # both samplers on the one source's unit (the other is unread): a sampler left on unit 0 would
        # see whatever the frame's last pass bound there, and llvmpipe keys a program's machine code
        # by its samplers' textures (frame 1 compiled hiz.comp again: 50 ms without a shader cache)
        red["gPosition"] = red["gDepth"] = HIZ_TEXTURE_UNIT
        red["fromDepth"] = int(depth is not None)
        if depth is not None:
            red["depthScale"] = float(depth[1])
        red["gTriId"] = HIZ_TEXTURE_UNIT + 1
        red["src"] = HIZ_TEXTURE_UNIT + 2
        ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.FRAMEBUFFER_BARRIER_BIT)
        for level in range(levels):  # log2 of the image size: fixed per size, not per scene
            lw, lh = max(1, w >> level), max(1, h >> level)
            hiz.bind_to_image(BIND_IMG_HIZ, read=False, write=True, level=level)
            red["srcLevel"] = level - 1
            red.run(-(-lw // 8), -(-lh // 8))
            ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        iostats.gl_draw(levels)
        return levels

    def _run(self, phase: int, levels: int) -> None:
        self.select["phase"] = phase
        self.select["hizLevels"] = levels
        self.select.run(-(-max(self.count, 1) // 64))
        self.ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        iostats.gl_draw()

    def draw(self, vao: moderngl.VertexArray, camera: Camera, size: tuple[int, int],
             position: moderngl.Texture, tri_id: moderngl.Texture,
             depth: tuple[moderngl.Texture, float] | None = None) -> None:
        """The raster's draw, culled: 3 selection dispatches, 2 multi-draws, 2 pyramids (from
        `position`, or from `depth`: see _build_pyramid)."""
        if self.count == 0:
            return
        # last draw's selection wrote `visible` and `stats` from the shader; the seed's upload and
        # the stats clear below (glBufferSubData / glClearBufferData) must wait for those writes.
        # The renderer's counter reads (viewer.gl.io.read) issue it too, a bare G-buffer loop not
        self.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
        self.seeded = self.seeded_triangles = 0
        if self.jumped(camera):
            self.seed(camera, size)
        sel = self.select
        eye = np.asarray(camera.position, np.float64)
        self._last_view = (eye, np.asarray(camera.forward, np.float64))
        apply(sel, camera_uniforms(camera, size))
        sel["nNodes"] = self.count
        sel["planes"].write(frustum_planes(camera, size[0] / size[1]).astype(np.float32).tobytes())
        sel["apexTol"] = 4.0 * float(np.spacing(np.float32(np.abs(eye).max())))
        sel["hiz"] = HIZ_TEXTURE_UNIT + 2
        self.nodes.bind_to_storage_buffer(BIND_CULL_NODES)
        self.visible.bind_to_storage_buffer(BIND_CULL_VISIBLE)
        self.stats.bind_to_storage_buffer(BIND_CULL_STATS)
        self.stats.clear()
        levels = pyramid_levels(size)
        self._pyramid(size).use(HIZ_TEXTURE_UNIT + 2)
        for phase, cmds in ((1, self.cmds[0]), (2, self.cmds[1])):
            if phase == 2:
                levels = self._build_pyramid(position, tri_id, depth)
            cmds.bind_to_storage_buffer(BIND_CULL_CMDS)
            self._run(phase, levels)
            iostats.gl_draw()
            vao.render_indirect(cmds, moderngl.TRIANGLES, count=self.count)
        self._build_pyramid(position, tri_id, depth)
        self._run(3, levels)

    def drawn(self) -> tuple[int, int]:
        """(triangles, nodes) the last `draw` submitted: a read-back, for panels and tests."""
        s = np.frombuffer(glio.read(self.stats), np.uint32)
        return int(s[0] + s[2]), int(s[1] + s[3])

    def release(self) -> None:
        for obj in (self.select, self.reduce, self.nodes, self.visible, *self.cmds, self.stats):
            obj.release()
        if self._hiz is not None:
            self._hiz.release()

"""G-buffer pass: rasterizes position, facing normal, albedo, triangle id and ray-distance depth.

Only what can be seen is drawn: the BVH subtrees inside the view pyramid (viewer.passes.cull) and,
of those, the ones not hidden behind what was drawn (viewer.passes.occlusion: GPU-driven, two
multi-draw-indirect calls). `occlusion = False` keeps the frustum culling alone (one multi-draw
from the host's list), `cull = False` draws every triangle; tests compare the three.

The exact raster pays for its coverage: a geometry shader expands every triangle so the fragment
shader can keep exactly the pixels whose primary ray hits it (triangles crossing the camera plane
are clipped in double first, no longer drawn as screen rectangles; triangles with no pixel centre
near their screen box emit nothing), and the fragment shader writes the exact distance as depth.
Each corner carries the triangle's depth lower bound and the shader declares it writes no less
(depth_greater), so a GPU may drop fragments behind what is already drawn before the exact test.
llvmpipe does not: a shader that writes depth runs for every rasterized fragment, ~10 per covered
pixel on city-near even after the occlusion culling (2.4 M for 217 k pixels at 640x360, 60 % of
them behind the stored depth). So the per-fragment work is what counts: the geometry shader hands
the triangle's vertices to the fragment shader as flat inputs (no SSBO gather per fragment, the
largest single cost), and the exact raster writes a visibility buffer (Burns and Hunt 2013): the
triangle id and the depth, 4 colour bytes per fragment instead of 52. One full-screen resolve
(gbuffer_fill.frag with RESOLVE) then writes position, normal and albedo once per pixel from the id,
with the same watertight test on the same pixel ray: the targets are bit for bit those the
4-target raster wrote. The occlusion pyramid reads an upper bound of the distance from that depth
(hiz.comp), as no position exists before the resolve. Exact / preview time on llvmpipe at 640x360
(docs/window-and-reports.md): city-near 2.3-2.4x -> 1.0-1.1x, the 1 M-triangle city 2.6-2.9x ->
0.9-1.6x. Moving frames in the window need no such exactness, only speed, so two other sources
serve them (the renderer's `gbuffer_source`):
- "preview": `render(camera, preview=True)`, a plain raster of the same culled triangles without
  the geometry shader, writing all four targets itself with early depth tests (edge pixels may
  differ from the traced primary rays by the rasterizer's sub-pixel rules);
- "trace": `fill_from_hits` writes the same targets from the backend's traced primary rays (cost
  follows the pixels, not the triangles).
"""

from __future__ import annotations

import moderngl
import numpy as np

from viewer import iostats
from viewer.accel.bvh import BVH
from viewer.camera import Camera
from viewer.gl.programs import FullscreenQuad, ProgramCache
from viewer.gl.scene import GpuScene
from viewer.gl.textures import clear_int_texture, float_depth_texture, float_texture, int_texture
from viewer.passes.cull import Cut, bvh_cut, cut_target, indirect_commands, visible_ranges
from viewer.passes.occlusion import OcclusionCuller
from viewer.passes.targets import SizedTargets
from viewer.passes.uniforms import apply, camera_uniforms


class GBufferPass(SizedTargets):
    def __init__(self, ctx: moderngl.Context, programs: ProgramCache, gpu_scene: GpuScene,
                 size: tuple[int, int], depth_scale: float, scene_diagonal: float):
        self.ctx = ctx
        self.gpu_scene = gpu_scene
        self.depth_scale = depth_scale
        self.diagonal = scene_diagonal
        fetch = gpu_scene.trace_defines()  # how the shaders read the triangles (scene.glsl loadTri)
        self.program = programs.get("gbuffer.vert", "gbuffer.frag", fetch, geometry="gbuffer.geom")
        self.fill = programs.get("fullscreen.vert", "gbuffer_fill.frag", fetch)
        self.resolve = programs.get("fullscreen.vert", "gbuffer_fill.frag", {"RESOLVE": 1, **fetch})
        self._quad = FullscreenQuad(ctx)  # the resolve's draw (counted by viewer.gl.io)
        self.vao = ctx.vertex_array(self.program, [])
        self._programs = programs
        self._preview: tuple[moderngl.Program, moderngl.VertexArray] | None = None  # made on first use
        self.cull = True  # frustum culling by BVH subtrees (False: draw every triangle)
        self.occlusion = True  # and occlusion culling on the device (False: frustum culling alone)
        self.bvh: BVH | None = None
        self._cut: Cut | None = None
        self._indirect: moderngl.Buffer | None = None
        self._occluder: OcclusionCuller | None = None
        self._drawn_host = 0  # triangles the last host-listed draw submitted
        self.resize(size)

    def set_bvh(self, bvh: BVH) -> None:
        """The tree whose boxes cull the raster (a refit keeps the topology, so the cut is kept; a
        rebuild, even to as many nodes, gets a new cut)."""
        same_topology = (self.bvh is not None and np.array_equal(bvh.node_first, self.bvh.node_first)
                         and np.array_equal(bvh.node_count, self.bvh.node_count))
        if self._cut is None or not same_topology:
            self._cut = bvh_cut(bvh, cut_target(len(bvh.tri_order)))
            if self._indirect is not None:
                self._indirect.release()
            self._indirect = self.ctx.buffer(reserve=max(len(self._cut.nodes), 1) * 20)
            if self._occluder is not None:
                self._occluder.release()
            self._occluder = OcclusionCuller(self.ctx, self._cut, bvh)
        elif self._occluder is not None and bvh is not self.bvh:
            self._occluder.set_boxes(bvh)
        self.bvh = bvh

    @property
    def drawn_triangles(self) -> int:
        """Triangles submitted by the last render() (a panel/test counter; with occlusion culling
        a read-back of the device's count)."""
        if self._drawn_host < 0 and self._occluder is not None:
            return self._occluder.drawn()[0]
        return self._drawn_host

    def create_targets(self, size: tuple[int, int]) -> None:
        self.position = float_texture(self.ctx, size, 4)
        self.normal = float_texture(self.ctx, size, 4)
        self.albedo = float_texture(self.ctx, size, 4)
        self.tri_id = int_texture(self.ctx, size)
        # float depth: t / (t + scale) of surfaces a hair apart right in front of the camera must order
        self.depth = float_depth_texture(self.ctx, size)
        self.depth.compare_func = ""  # read as a value by the occlusion pyramid (hiz.comp), not compared
        self.fbo = self.ctx.framebuffer(color_attachments=[self.position, self.normal, self.albedo, self.tri_id],
                                        depth_attachment=self.depth)
        # the exact raster's visibility buffer (id + depth), then its resolve into the other three
        self.vis_fbo = self.ctx.framebuffer(color_attachments=[self.tri_id], depth_attachment=self.depth)
        self.resolve_fbo = self.ctx.framebuffer(color_attachments=[self.position, self.normal, self.albedo])

    def _preview_program(self) -> tuple[moderngl.Program, moderngl.VertexArray]:
        if self._preview is None:
            prog = self._programs.get("gbuffer.vert", "gbuffer.frag", {"PREVIEW": 1, **self.gpu_scene.trace_defines()})
            self._preview = prog, self.ctx.vertex_array(prog, [])
        return self._preview

    def render(self, camera: Camera, preview: bool = False) -> None:
        """The exact conservative raster (a visibility buffer, then its resolve), or with `preview`
        the plain one (moving frames only)."""
        program, vao = self._preview_program() if preview else (self.program, self.vao)
        ctx = self.ctx
        if preview:
            self.clear()
        else:
            self.vis_fbo.use()
            self.vis_fbo.clear(-1.0, 0.0, 0.0, 0.0, depth=1.0)
            clear_int_texture(self.tri_id, -1)  # id < 0: no triangle (see clear)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        ctx.depth_func = "<"
        w, h = self.size
        pos = np.asarray(camera.position, np.float64)
        lo_near = max(self.diagonal * 1e-5, 1e-6)
        far = self.diagonal * 4 + float(np.linalg.norm(pos)) * 2
        proj = camera.projection_matrix(w / h, lo_near, far)
        view_rot = np.eye(4)
        view_rot[:3, :3] = camera.rotation.T
        vp = (proj @ view_rot).astype(np.float32)
        program["viewProjRel"].write(vp.T.tobytes())  # GL expects column-major
        program["camPosV"].value = tuple(float(x) for x in pos)
        if "depthScale" in program:  # the preview uses the rasterizer's depth
            program["depthScale"].value = float(self.depth_scale)
        apply(program, camera_uniforms(camera, self.size))
        self.gpu_scene.bind(nodes=False)
        self._draw(vao, camera, (w, h), preview)
        ctx.disable(ctx.DEPTH_TEST)
        if not preview:
            self._resolve(camera)

    def _resolve(self, camera: Camera) -> None:
        """Position, facing normal and albedo from the visibility buffer, once per pixel (every
        pixel written: misses get the clear values)."""
        self.resolve_fbo.use()
        p = self.resolve
        apply(p, camera_uniforms(camera, self.size))
        self.tri_id.use(0)
        p["visId"] = 0
        self._quad.render(p)

    def clear(self) -> None:
        self.fbo.use()
        self.fbo.clear(-1.0, 0.0, 0.0, 0.0, depth=1.0)
        # the R32I id attachment explicitly: a float clear colour leaves an integer target undefined
        # (Mesa stores -1.0's bits, 0xBF800000); -1 is "no triangle" to every reader (id < 0)
        clear_int_texture(self.tri_id, -1)

    def fill_from_hits(self, camera: Camera, hits, quad) -> None:
        """The targets from traced primary rays (`hits`: a viewer.rays.HitBuffer of rays through the
        pixel centres): per pixel the same outputs the raster writes for the hit triangle."""
        ctx = self.ctx
        self.clear()
        ctx.enable(ctx.DEPTH_TEST)  # depth is written only with the test on; every pixel passes
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        ctx.depth_func = "1"
        p = self.fill
        p["depthScale"].value = float(self.depth_scale)
        apply(p, camera_uniforms(camera, self.size))
        self.gpu_scene.bind(nodes=False)
        hits.t.use(0)
        hits.id.use(1)
        p["hitT"] = 0
        p["hitId"] = 1
        quad.render(p)  # counted by FullscreenQuad (viewer.gl.io)
        ctx.depth_func = "<"
        ctx.disable(ctx.DEPTH_TEST)

    def _draw(self, vao: moderngl.VertexArray, camera: Camera, size: tuple[int, int], preview: bool) -> None:
        """Every triangle; the visible subtrees' ranges as one multi-draw-indirect; or, with
        occlusion culling, the device's two multi-draws (its pyramid reads the preview's distances,
        or the exact raster's depth: no position is written before the resolve)."""
        if self.cull and self.occlusion and self._occluder is not None:
            self._drawn_host = -1  # counted on the device
            self._occluder.draw(vao, camera, size, self.position, self.tri_id,
                                None if preview else (self.depth, self.depth_scale))
            return
        iostats.gl_draw(1)
        if not self.cull or self._cut is None or self.bvh is None:
            self._drawn_host = self.gpu_scene.triangle_count
            vao.render(moderngl.TRIANGLES, vertices=self.gpu_scene.triangle_count * 3)
            return
        ranges = visible_ranges(self._cut, self.bvh.node_min, self.bvh.node_max, camera, size[0] / size[1])
        self._drawn_host = int(ranges[:, 1].sum()) if len(ranges) else 0
        if not len(ranges):
            return
        cmd = indirect_commands(ranges)
        self._indirect.write(cmd.tobytes())
        iostats.to_device(cmd.nbytes)
        vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=len(cmd))

    def release_targets(self) -> None:
        for obj in (self.fbo, self.vis_fbo, self.resolve_fbo, self.position, self.normal, self.albedo,
                    self.tri_id, self.depth):
            obj.release()

    def release(self) -> None:
        self.release_targets()
        self.vao.release()
        self._quad.release()
        if self._preview is not None:
            self._preview[1].release()  # the program belongs to the cache
        if self._indirect is not None:
            self._indirect.release()
        if self._occluder is not None:
            self._occluder.release()

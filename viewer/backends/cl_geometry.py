"""The base of OpenCL backends whose structures follow the scene's triangles (ugrid, pgrid,
voxelwalk): the triangles in one device buffer, rebuilt when the geometry moves.

Why one base: each of these backends needs the same four things, and had its own copy of each:
a key that says whether the triangles changed (their array and the scene's geometry_version, which
an animated scene bumps), the float4 triangle buffer grown and re-uploaded (limit-checked and
counted), `scene_changed` rebuilding at once (timed as the backend's build phase), and
`begin_frame` rebuilding when the key changed or the backend rebuilds every frame. A subclass
implements `_rebuild()` (typically: `tris = self._upload_triangles(label)` inside its phase, then
its structure) and may override `_frame_started()`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from viewer.accel.grid import triangles_f4
from viewer.backends.base import BackendContext, StatelessBackend
from viewer.cl import io as clio
from viewer.cl.limits import new_buffer


class GeometryBackend(StatelessBackend):
    """Defaults for a CL backend built over the scene's triangles (see the module docstring).
    Subclasses set `bc`, `ctx` (viewer.cl.ClContext) and `params` (with a `rebuild` flag) before
    the first `_rebuild()`."""

    bc: BackendContext
    ctx: Any
    params: Any
    _tris: Any = None  # float4 triangle buffer (3 float4 per triangle, viewer.accel.grid.triangles_f4)
    _tris_key: tuple[int, int] | None = None

    def _start(self, bc: BackendContext, params: Any) -> None:
        """The common start of a constructor: the context, the parameters (the info's defaults when
        None), no overlays, the shared CL context, a uniform grid, and int textures for overlays."""
        from viewer.accel.grid import UniformGrid
        from viewer.cl import cl_context
        from viewer.gl.textures import IntTextures

        self.bc = bc
        self.params = params or self.info.params()
        self.overlays_enabled = False
        self.ctx = cl_context()
        self.grid = UniformGrid(self.ctx)
        self.textures = IntTextures(bc.ctx)

    def _geometry_key(self) -> tuple[int, int]:
        return id(self.bc.scene.triangles), int(getattr(self.bc.scene, "geometry_version", 0))

    def _upload_triangles(self, label: str) -> np.ndarray:
        """The scene's triangles (float32 (N, 3, 3)) into the device buffer, grown when too small;
        remembers the geometry they came from."""
        ctx = self.ctx
        tris = np.asarray(self.bc.scene.triangles, np.float32).reshape(-1, 3, 3)
        f4 = triangles_f4(tris)
        if self._tris is None or self._tris.size < f4.nbytes:
            if self._tris is not None:
                self._tris.release()
            self._tris = new_buffer(ctx, ctx.cl.mem_flags.READ_ONLY, f4.nbytes, label)
        if f4.nbytes:  # no wait: pyopencl holds f4 until the copy has landed
            clio.copy(ctx.queue, self._tris, f4, is_blocking=False)
        self._tris_key = self._geometry_key()
        return tris

    def _rebuild(self) -> None:
        raise NotImplementedError

    def _frame_started(self) -> None:
        """Per-frame bookkeeping after a possible rebuild (statistics reported by the first pass)."""

    def scene_changed(self, bc: BackendContext) -> None:
        """The triangles moved: rebuild now (timed as this backend's build phase) rather than
        lazily at the next begin_frame."""
        self.bc = bc
        self._rebuild()

    def begin_frame(self, frame_index: int) -> None:
        if getattr(self.params, "rebuild", False) or self._geometry_key() != self._tris_key:
            self._rebuild()
        self._frame_started()

    def _release_own(self) -> None:
        """Release what _start and _upload_triangles made (and the ray stages)."""
        self.stages.release()
        self.textures.release()
        if self._tris is not None:
            self._tris.release()
            self._tris = None
        self.grid.release()

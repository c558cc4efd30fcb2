"""Which filter the window's picture goes through (--denoise on): cost chosen by frame budget.

Moving, refining or full-quality-every-frame: the device a-trous pass (a few draws, no read-back),
run inside every rendered frame (Renderer.denoise: phase "denoise" of its report). Converged (the
still camera has all its samples, the window then idles): Open Image Denoise once on that final
image (a few hundred ms, paid once, not per frame), uploaded to a texture shown until the next
change. Where pyoidn is missing the device filter stays. Views other than "final" are shown raw.
"""

from __future__ import annotations

import moderngl
import numpy as np

from viewer import iostats


class DisplayDenoiser:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.still: moderngl.Texture | None = None  # the library-filtered converged image
        self.shown: moderngl.Texture | None = None  # what was shown last (idle frames reuse it)
        self.method = ""  # "device", "library" or "" (raw): the panel/status can say which

    def texture(self, renderer, camera, step, rendered: bool) -> moderngl.Texture:
        """The texture to blit this frame. `step`: the progressive step (None without progressive
        refinement); `rendered`: a frame was rendered this call (False: idle, keep the last)."""
        from viewer.denoise import library_missing

        if renderer.view != "final" or renderer.is_overlay_view or not renderer.noisy:
            self.method = ""
            return renderer.final_texture
        if not rendered and self.shown is not None:
            return self.shown
        if step is not None and step.converged and library_missing() is None:
            img = renderer.read_denoised("library", camera)
            h, w = img.shape[:2]
            if self.still is None or self.still.size != (w, h):
                if self.still is not None:
                    self.still.release()
                self.still = self.ctx.texture((w, h), 3, dtype="f1")
                self.still.filter = (moderngl.LINEAR, moderngl.LINEAR)
            data = np.ascontiguousarray(img[::-1])  # GL rows bottom first
            self.still.write(data.tobytes())
            iostats.to_device(data.nbytes)
            self.shown, self.method = self.still, "library"
        else:  # filtered inside the frame (Renderer.denoise), its cost in the frame's time
            self.shown = renderer.shown_texture
            self.method = "device" if renderer.denoised else ""
        return self.shown

    def release(self) -> None:
        if self.still is not None:
            self.still.release()
            self.still = None
        self.shown = None

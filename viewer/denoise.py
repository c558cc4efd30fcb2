"""Denoising the displayed or saved picture, guided by the G-buffer's albedo and normal.

Two filters, one job: remove the grain of few-sample effects (AO, soft shadows, diffuse) from the
picture a person looks at. Neither touches what the renderer measures: Renderer.read_image() stays
the raw frame (backend agreement, image tests and the bench's Embree comparison use it).

- "library": Intel Open Image Denoise (pyoidn, CPU device, quality "fast"): still frames, replays
  and screenshots, where a few hundred ms per picture fit. Linear radiance in [0, 1] (the display
  image with its gamma undone), albedo and normal from the G-buffer. Mirror and background
  pixels get their own colour as albedo: what they show is detail, not noise.
- "device": the a-trous wavelet pass on the GPU (viewer.passes.denoise): moving frames in the
  window, a few ms of full-screen draws, and the fallback where pyoidn is missing.

`--denoise on|off` (view, demo, render; on by default) picks whether the picture is filtered;
frames without sampled effects (only point-light shadows and mirrors: exact) are never filtered.
"""

from __future__ import annotations

import numpy as np

QUALITY = "fast"  # 233 ms at 640x360 on a 2-core machine ("high": 446 ms), issue 23
GAMMA = 2.2  # the shade pass's display encoding (shade.frag toDisplay)


def library_missing() -> str | None:
    """None when Open Image Denoise can run here, else why not (one line)."""
    try:
        import pyoidn  # noqa: F401
    except ImportError as exc:  # the wheel holds the native library: an import error says it all
        return f"pyoidn is not installed ({exc}); pip install pyoidn==2.5.1"
    except OSError as exc:
        return f"pyoidn cannot load its library ({exc})"
    return None


def library_denoise(image: np.ndarray, albedo: np.ndarray, normal: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """OIDN on a display image: uint8 (H, W, 3) in and out; albedo, normal float (H, W, 3) and
    kept (H, W) bool (background and mirror pixels), all top row first."""
    import pyoidn

    lin = (np.asarray(image, np.float32) / 255.0) ** GAMMA
    alb = np.where(kept[..., None], lin, np.clip(albedo, 0.0, 1.0)).astype(np.float32)
    nrm = np.where(kept[..., None], 0.0, np.clip(normal, -1.0, 1.0)).astype(np.float32)
    out = pyoidn.denoise(np.ascontiguousarray(lin), np.ascontiguousarray(alb), np.ascontiguousarray(nrm),
                         quality=QUALITY)
    out = np.where(kept[..., None], lin, out)
    return np.round(255.0 * np.clip(out, 0.0, 1.0) ** (1.0 / GAMMA)).astype(np.uint8)


def image_mae(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two uint8 images, in 1/255 units."""
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def filter_line(denoise: bool, renderer) -> str:
    """What the saved picture went through, for a CLI's closing line."""
    if not denoise or renderer.view != "final":
        return ""
    if not renderer.noisy:
        return "; not denoised: no sampled effect (soft, ao, diffuse)"
    why = library_missing()
    return "; denoised: Open Image Denoise" if why is None else f"; denoised: device a-trous filter ({why})"

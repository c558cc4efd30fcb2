"""`rtwalk bench-denoise`: the denoisers' own error and cost against a many-sample reference.

One recording frame is rendered raw with the bench's effects (few AO samples: the grain), then
filtered by Open Image Denoise (viewer.denoise, "library") and by the device a-trous pass
("device"); the reference is the same frame with the AO (and soft, diffuse) sample counts raised
to --reference-samples. Printed and returned: MAE (1/255 units) of raw, library and device images
against the reference, and each filter's cost in ms (library: G-buffer read-back + OIDN; device:
the draws, timed with a finish). The bench's Embree comparison is untouched: it measures the raw
frame before any filter.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from viewer.denoise import image_mae, library_missing

DEFAULT_EFFECTS = "shadows,ao:4,reflections"
REFERENCE_SAMPLES = 256


def reference_settings(settings, samples: int):
    """The same effects with every sampled one (soft, ao, diffuse) at `samples` passes."""
    return replace(settings,
                   soft_samples=samples if settings.soft else settings.soft_samples,
                   ao_samples=samples if settings.ao else settings.ao_samples,
                   diffuse_samples=samples if settings.diffuse else settings.diffuse_samples)


def measure(prepared, rec, frame: int, settings, size: tuple[int, int], ctx, reference_samples: int,
            backend: str | None = None, repeats: int = 3, backend_options: dict[str, str] | None = None) -> dict:
    """{raw_mae, library_mae, device_mae, library_ms, device_ms, ...} for one frame (medians of
    `repeats` timings; library entries None without pyoidn)."""
    import numpy as np

    from viewer.renderer import Renderer

    cam = rec.camera_for_frame(frame)
    renderer = Renderer(ctx, prepared.scene, prepared.bvh, size, backend,
                        reference_settings(settings, reference_samples), backend_options)
    try:
        renderer.set_scene_time(rec.scene_time_for_frame(frame))
        renderer.render(cam)
        ref = renderer.read_image()
        renderer.settings = settings
        renderer.render(cam)
        raw = renderer.read_image()
        out = {"frame": frame, "size": list(size), "reference_samples": reference_samples,
               "raw_mae": image_mae(raw, ref)}
        dev_ms = []
        for _ in range(repeats):
            ctx.finish()
            t0 = time.perf_counter()
            renderer.denoise_on_device(cam)
            ctx.finish()
            dev_ms.append((time.perf_counter() - t0) * 1e3)
        dev = renderer.read_denoised("device", cam)
        out.update(device_mae=image_mae(dev, ref), device_ms=float(np.median(dev_ms)),
                   device_draws=renderer.device_denoiser.draws)
        out.update(library_mae=None, library_ms=None, library_missing=library_missing())
        if out["library_missing"] is None:
            lib_ms = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                lib = renderer.read_denoised("library", cam, raw)
                lib_ms.append((time.perf_counter() - t0) * 1e3)
            out.update(library_mae=image_mae(lib, ref), library_ms=float(np.median(lib_ms)))
        out["kept"] = renderer.read_guides()[2]  # background and mirror pixels (left unfiltered)
        out["images"] = {"raw": raw, "reference": ref, "device": dev,
                         **({"library": lib} if out["library_missing"] is None else {})}
        return out
    finally:
        renderer.release()


HELP = "denoisers (OIDN, device a-trous) against a 256-sample reference: MAE raw vs filtered and cost in ms"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from viewer.cli_args import add_effect_args

    add_effect_args(p, DEFAULT_EFFECTS)
    p.set_defaults(size="320x180")
    p.add_argument("--recording", default="city-near", help="shipped recording name or file (default city-near)")
    p.add_argument("--frame", type=int, default=120, help="frame of the recording (default 120)")
    p.add_argument("--reference-samples", type=int, default=REFERENCE_SAMPLES,
                   help=f"sample passes of the reference's sampled effects (default {REFERENCE_SAMPLES})")
    p.add_argument("--repeats", type=int, default=3, help="timings per filter (median)")
    p.add_argument("--save", default=None, help="folder for raw/reference/library/device PNGs")
    p.add_argument("--quiet", action="store_true", help="no progress output")


SAVED_IMAGES = ("raw", "reference", "device", "library")  # --save: <name>.png


def run(args) -> int:
    from PIL import Image

    from viewer.cli_args import check_at_least, check_output_dir, check_report_free, request_from
    from viewer.gl.context import create_headless_context
    from viewer.gl.limits import check_target_size
    from viewer.paths import resolve_recording
    from viewer.recording import load_recording
    from viewer.session import prepare_scene_for_recording

    req = request_from(args)  # backend (was checked only after the scene loaded), size, effects
    size, settings = req.size, req.settings
    check_at_least(args.reference_samples, 1, "--reference-samples")
    check_at_least(args.repeats, 1, "--repeats")
    check_at_least(args.frame, 0, "--frame")
    save = check_output_dir(args.save, "--save")
    if save is not None:  # the images of an earlier run are kept unless --force
        check_report_free([save / f"{n}.png" for n in SAVED_IMAGES], getattr(args, "force", False), "--save")
    rec = load_recording(resolve_recording(args.recording))
    rec.camera_for_frame(args.frame)  # in range
    ctx = create_headless_context()
    check_target_size(ctx, size)  # before the scene (it was refused only after the load and BVH build)
    prepared = prepare_scene_for_recording(rec, quiet=args.quiet)
    r = measure(prepared, rec, args.frame, settings, size, ctx, args.reference_samples, args.backend,
                args.repeats, req.backend_options)  # --backend-params were parsed, then dropped
    print(f"{rec.scene_name} frame {args.frame}, {size[0]}x{size[1]}, effects {args.effects}, "
          f"reference: {args.reference_samples} samples; MAE in 1/255 against the reference")
    print(f"  raw             MAE {r['raw_mae']:7.3f}")
    if r["library_mae"] is not None:
        print(f"  library (OIDN)  MAE {r['library_mae']:7.3f}   cost {r['library_ms']:8.1f} ms")
    else:
        print(f"  library (OIDN)  not run: {r['library_missing']}")
    print(f"  device a-trous  MAE {r['device_mae']:7.3f}   cost {r['device_ms']:8.1f} ms ({r['device_draws']} draws)")
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)  # a missing folder was a traceback after the measurement
        for name, img in r["images"].items():
            Image.fromarray(img).save(save / f"{name}.png")
        print(f"images: {save}")
    return 0

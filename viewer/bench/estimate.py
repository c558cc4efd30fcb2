"""Up-front time estimate of a benchmark command: a per-ray cost model per backend.

Only for the plan printed before a long run (and `--dry-run`); tqdm shows the real rate. The
pixel and fixed costs below were fitted to the Table 2 recordings (city-near, city-far,
sibenik-walk, sponza-walk, conference-walk) at 1920x1080 and city-near at 640x360 on a 2-core
machine with Mesa llvmpipe (2026-11-29; the first fit, two sessions of speed-ups earlier,
over-estimated those runs 6-7x); the per-ray costs are given by each study.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

US_PER_PIXEL_FRAME = 0.35  # G-buffer + shading (a steady frame's wall time minus its tracing)
US_PER_PIXEL_PASS = 0.03  # ray generation + accumulation, per sample pass
RUN_FIXED_S = 0.5  # renderer, shader variants
SCENE_LOAD_S = {"builtin": 1.0, "file": 6.0}


@dataclass(frozen=True)
class CostModel:
    """Steady-state microseconds per ray of one backend, per effect; a cold frame (first after a
    reset) costs `cold_factor[effect]` (else `cold_default`) times that; `aggressive` (a factor a
    study passes for approximate settings) scales the per-ray cost when `scales_aggressive`."""

    us_per_ray: dict[str, float]
    us_per_ray_other: float = 1.0
    cold_factor: dict[str, float] = field(default_factory=dict)
    cold_default: float = 1.0
    scales_aggressive: bool = False


def estimate_frame_s(model: CostModel, effect: str, size: tuple[int, int], cold: bool = False,
                     aggressive: float = 1.0, warm_up: bool = False) -> float:
    """Model of one frame's wall time (seconds) from rays per pass and a per-ray cost."""
    from viewer.bench.harness import effect_settings, warmup_settings
    from viewer.effects import EFFECT_NAMES

    s = warmup_settings(effect) if warm_up else effect_settings(effect)
    px = size[0] * size[1]
    total_us = px * US_PER_PIXEL_FRAME
    for name in EFFECT_NAMES:
        if not getattr(s, name):
            continue
        passes = {"soft": s.soft_samples, "ao": s.ao_samples, "diffuse": s.diffuse_samples}.get(name, 1)
        per_ray = model.us_per_ray.get(name, model.us_per_ray_other)
        if model.scales_aggressive:
            per_ray *= aggressive
        if cold:
            per_ray *= model.cold_factor.get(name, model.cold_default)
        total_us += passes * px * (per_ray + US_PER_PIXEL_PASS)
    return total_us / 1e6


def run_estimate(model: CostModel, effect: str, size: tuple[int, int], frames: int, aggressive: float = 1.0) -> float:
    """One harness run: fixed cost, warm-up frames (the first cold), cold frame, steady frames."""
    from viewer.bench.harness import WARMUP_FRAMES

    warm = min(WARMUP_FRAMES, frames)
    return (RUN_FIXED_S + estimate_frame_s(model, effect, size, True, aggressive, warm_up=True)
            + (warm - 1) * estimate_frame_s(model, effect, size, False, aggressive, warm_up=True)
            + estimate_frame_s(model, effect, size, True, aggressive)
            + (frames - 1) * estimate_frame_s(model, effect, size, False, aggressive))


def scenes_estimate(recordings: set[Path] | list[Path]) -> float:
    """Seconds to load the distinct scenes of these recordings once each."""
    from viewer.recording import load_recording

    specs = {}
    for p in recordings:
        rec = load_recording(p)
        specs[json.dumps(rec.scene, sort_keys=True)] = "builtin" if "builtin" in rec.scene else "file"
    return sum(SCENE_LOAD_S[k] for k in specs.values())


def format_estimate(est: dict[str, float]) -> str:
    parts = ", ".join(f"{k} {v / 60:.1f} min" for k, v in est.items())
    return f"estimate: {sum(est.values()) / 60:.0f} min ({parts}; model of a 2-core llvmpipe machine)"

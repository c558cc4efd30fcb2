"""Which secondary effects are on and their parameters; the ray types they generate."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from enum import IntEnum

from viewer.errors import RtwalkError


class RayType(IntEnum):
    """Ray types; values match the RAY_* constants in shaders/raygen.frag."""

    PRIMARY = 0
    SHADOW = 1
    SOFT = 2
    AO = 3
    DIFFUSE = 4
    REFLECT = 5

    @property
    def any_hit(self) -> bool:
        """Shadow and AO rays only need to know whether anything is hit."""
        return self in (RayType.SHADOW, RayType.SOFT, RayType.AO)

    @property
    def samples_share_origins(self) -> bool:
        """Every sample pass of this effect in a frame gives a pixel's ray the same origin, tmin, tmax
        and activity, only another direction (shaders/raygen.frag and cl/kernels/frame.cl: AO and
        diffuse rays leave the pixel's offset G-buffer point with the effect's ray length). A backend
        may share among a frame's samples the per-pixel work that reads no direction (say, culling
        screen tiles by the rays' reach)."""
        return self in (RayType.AO, RayType.DIFFUSE)

    @property
    def label(self) -> str:
        return EFFECT_OF_RAY[self]


# Command-line effect names, in composition order.
EFFECT_OF_RAY = {RayType.PRIMARY: "primary", RayType.SHADOW: "shadows", RayType.SOFT: "soft",
                 RayType.AO: "ao", RayType.DIFFUSE: "diffuse", RayType.REFLECT: "reflections"}
EFFECT_NAMES = list(EFFECT_OF_RAY.values())


@dataclass
class EffectSettings:
    """Effect toggles and parameters. Sample counts are rays per pixel (one pass each)."""

    primary: bool = False  # also trace primary rays (raster gives the G-buffer either way)
    shadows: bool = True
    soft: bool = False
    ao: bool = False
    diffuse: bool = False
    reflections: bool = True
    soft_samples: int = 4
    ao_samples: int = 4
    diffuse_samples: int = 4
    ao_length: float = 0.05  # fraction of the scene diagonal
    perturb_deg: float = 36.0  # per-pixel random rotation of the shared sample direction
    exposure: float = 1.0
    ambient: float = 0.35

    def enabled(self, ray: RayType) -> bool:
        return bool(getattr(self, EFFECT_OF_RAY[ray]))

    def samples(self, ray: RayType) -> int:
        return {RayType.SOFT: self.soft_samples, RayType.AO: self.ao_samples,
                RayType.DIFFUSE: self.diffuse_samples}.get(ray, 1)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


GBUFFER_VIEWS = ("albedo", "normal", "depth", "triangle_id")  # shade views of the G-buffer alone


def effects_for_view(settings: EffectSettings, view: str) -> EffectSettings:
    """The effects a still of `view` needs traced: none for a G-buffer view, that pass alone for a
    pass view (shadows, soft, ao, diffuse, reflections: the shade pass reads only its accumulator),
    all of `settings` for 'final' and the backends' overlay views (they show the traced passes).
    `render --view depth` traced the default shadow and reflection rays for a picture without them."""
    if view in GBUFFER_VIEWS:
        kept: set[str] = set()
    elif view in EFFECT_NAMES and view != "primary":
        kept = {view}
    else:
        return settings
    return replace(settings, **{name: bool(getattr(settings, name)) and name in kept for name in EFFECT_NAMES})


def parse_effects(text: str, base: EffectSettings | None = None) -> EffectSettings:
    """'shadows,ao:20,diffuse:8' -> settings with exactly those effects on (':N' = samples)."""
    s = base or EffectSettings()
    for name in EFFECT_NAMES:
        setattr(s, name, False)
    if not text.strip():
        raise RtwalkError("--effects is empty (name effects, e.g. shadows,ao:4, or 'none' for the raster image alone)")
    if text.strip().lower() == "none":
        return s
    if text.strip().lower() == "all":
        for name in EFFECT_NAMES:
            setattr(s, name, name != "primary")
        return s
    seen: set[str] = set()
    for item in text.split(","):
        name, _, count = item.strip().lower().partition(":")
        name = {"shadow": "shadows", "hard": "shadows", "reflection": "reflections", "refl": "reflections",
                "soft_shadows": "soft", "indirect": "diffuse"}.get(name, name)
        if not name:
            raise RtwalkError(f"empty effect name in --effects '{text}'")
        if name not in EFFECT_NAMES:
            raise RtwalkError(f"unknown effect '{name}' (choose from {', '.join(EFFECT_NAMES)}, all, none)")
        if name in seen:
            raise RtwalkError(f"effect {name} is given twice in --effects '{text}' (give it once, e.g. {name}:N)")
        seen.add(name)
        setattr(s, name, True)
        if count:
            if not count.isdigit() or not 1 <= int(count) <= 1024:
                raise RtwalkError(f"bad sample count '{count}' for effect {name} (1..1024)")
            if name in ("soft", "ao", "diffuse"):
                setattr(s, f"{name}_samples", int(count))
    return s


# The sample pattern of an effect's passes: pass k of every pixel shares Halton point k (CHC+RT 5.3),
# the same on every device (raygen.frag and the OpenCL ray generation take it as a uniform).
def radical_inverse(base: int, index: int) -> float:
    """Van der Corput radical inverse of `index` in `base` (Halton component)."""
    inv, f, i = 0.0, 1.0 / base, index
    while i > 0:
        inv += f * (i % base)
        i //= base
        f /= base
    return inv


def halton2(index: int) -> tuple[float, float]:
    """The index-th 2D Halton point (bases 2 and 3); index 0 is skipped (it is (0, 0))."""
    return radical_inverse(2, index + 1), radical_inverse(3, index + 1)

"""The backend contract: what a backend says about itself, and what it is told per pass.

Generic code (renderer, passes, panel, bench harness, CLI) knows backends only through this
module: a backend class carries a `BackendInfo` (`info` class attribute) that declares its
parameters (a dataclass, parsed generically from `--backend-params KEY=VALUE,...` and the
environment variable RTWALK_<NAME>), the overlays it can produce, the counters and phase names
the panel shows, and its device ("gl", "cl" or "cpu"). Each `trace()` call gets a `PassInfo`
saying which ray type, sample and light the pass belongs to.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from viewer.errors import RtwalkError
from viewer.rays import PassInfo

if TYPE_CHECKING:  # the GL-side types live in viewer.rays / viewer.backends.base
    from viewer.backends.base import BackendContext, TraceResult
    from viewer.rays import HitBuffer, RayBatch

__all__ = ["PassInfo", "OverlaySpec", "BackendInfo", "Backend", "ParamDoc", "param", "param_docs", "parse_params",
           "params_text", "resolve_params"]

OVERLAY_KINDS = ("heat", "ids")
DEVICES = ("gl", "cl", "cpu")


@dataclass(frozen=True)
class OverlaySpec:
    """An overlay view a backend can feed. `texture` names the R32I texture in
    TraceResult.overlays holding one value per pixel (at the ray-batch size, row 0 = bottom).

    kind "heat": non-negative counts drawn as a heat map with a legend (e.g. query fragments,
    triangles tested per ray, tile divergence). kind "ids": an id per pixel (-1 = none) drawn in
    random colours; `counts` optionally names a second R32I texture whose per-pixel values are
    printed per tile (tile outlines come from the backend's `tile_level`)."""

    name: str  # view name (`render --view NAME`, the window's View combo)
    kind: str
    texture: str
    label: str = ""  # legend / panel text, e.g. "query fragments per pixel"
    counts: str | None = None

    def __post_init__(self) -> None:
        assert self.kind in OVERLAY_KINDS, self.kind


@dataclass(frozen=True)
class BackendInfo:
    """What a backend declares about itself; generic code reads only this."""

    name: str
    description: str
    params: type | None = None  # a dataclass with defaults (see parse_params); None: no parameters
    overlays: tuple[OverlaySpec, ...] = ()
    counters: tuple[str, ...] = ()  # TraceResult.stats keys the panel shows per frame, in order
    phases: tuple[str, ...] = ()  # profiler phase names the panel stacks per frame (else trace:*)
    device: str = "gl"
    exact: bool = True  # False: approximate by design (agreement tests report instead of assert)

    def __post_init__(self) -> None:
        assert self.device in DEVICES, self.device

    @property
    def env_var(self) -> str:
        return "RTWALK_" + self.name.upper()


def _parse_bool(v: str) -> bool:
    v = v.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off"):
        return False
    raise ValueError(v)


_KINDS = {"float": float, "int": int, "str": str, "bool": _parse_bool,
          float: float, int: int, str: str, bool: _parse_bool}


def param(default: Any, help: str) -> Any:
    """A parameter field with its documentation: `stack: int = param(8, "short-stack entries")`.
    The help is what `rtwalk info --backend NAME` prints and the window's panel shows as a tooltip."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class ParamDoc:
    """One documented backend parameter."""

    name: str
    type: str
    default: Any
    help: str


def param_docs(cls: type | None) -> list[ParamDoc]:
    """Name, type, default and help of every field of a parameter dataclass ([] for None)."""
    if cls is None:
        return []
    out = []
    for f in dataclasses.fields(cls):
        kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
        out.append(ParamDoc(f.name, kind, f.default, str(f.metadata.get("help", ""))))
    return out


def describe(info: BackendInfo) -> str:
    """A backend's self-description for `rtwalk info --backend NAME`: what it is, its device,
    whether it is exact, and every parameter with its default and help."""
    lines = [f"backend {info.name}: {info.description}",
             f"  device: {info.device}; {'exact' if info.exact else 'approximate by design'}",
             f"  parameters (--backend-params key=value,... or {info.env_var}):"]
    docs = param_docs(info.params)
    if not docs:
        lines[-1] = "  parameters: none"
    for d in docs:
        lines.append(f"    {d.name}={d.default} ({d.type}): {d.help}")
    if info.overlays:
        lines.append("  views: " + ", ".join(f"{o.name} ({o.label or o.kind})" for o in info.overlays))
    if info.counters:
        lines.append("  counters: " + ", ".join(info.counters))
    return "\n".join(lines)


def parse_params(cls: type | None, text: str | None, source: str) -> Any:
    """An instance of the dataclass `cls` from "key=value,key=value" on top of its defaults.
    Unknown keys and bad values raise RtwalkError naming `source`; afterwards the instance's
    `validate(source)` is called when it has one. `cls` None accepts only empty text."""
    items = [s.strip() for s in (text or "").split(",") if s.strip()]
    if cls is None:
        if items:
            raise RtwalkError(f"{source}: this backend has no parameters (got '{text}')")
        return None
    p = cls()
    types = {f.name: f.type for f in dataclasses.fields(cls)}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip()
        if key not in types or not sep:
            raise RtwalkError(f"{source}: expected key=value with key one of {', '.join(types)} (got '{item}')")
        conv = _KINDS.get(types[key], str)
        try:
            setattr(p, key, conv(val.strip()))
        except ValueError as exc:
            raise RtwalkError(f"{source}: bad value for {key}: '{val}'") from exc
    if hasattr(p, "validate"):
        p.validate(source)
    return p


def params_text(params: Any) -> str:
    """"key=value,..." of a parameter dataclass ('' for None): goes into reports."""
    if params is None:
        return ""
    return ",".join(f"{f.name}={getattr(params, f.name)}" for f in dataclasses.fields(params))


def resolve_params(info: BackendInfo, text: str | None, source: str = "--backend-params") -> Any:
    """The backend's parameters: defaults, then RTWALK_<NAME> from the environment, then `text`."""
    env = os.environ.get(info.env_var, "")
    if env.strip():
        base = parse_params(info.params, env, info.env_var)
        merged = ",".join(t for t in (params_text(base), text or "") if t.strip())
        return parse_params(info.params, merged, source if text else info.env_var)
    return parse_params(info.params, text, source)


class Backend(Protocol):
    """Every backend: a class with `info`, constructed as cls(bc, params) by the registry.

    Optional, for `info.device == "cl"` (viewer/cl/frame.py picks the device-resident frame when
    present): `trace_device(rays, pinfo, hits) -> TraceResult` traces CL ray buffers
    (viewer.cl.RayStage layout) into CL hit buffers (HitStage) with nothing crossing the host, and
    `end_frame() -> dict[str, float]` returns counters kept on the device over such a frame. Any
    backend may have `end_frame`: after a frame of GL passes the renderer calls it once, after the
    frame's own finish, so a read there waits for nothing (chcrt's device fronts report that way)."""

    info: ClassVar[BackendInfo]
    params: Any  # an instance of info.params, or None
    overlays_enabled: bool  # set by the renderer each frame: fill overlay textures only when True

    def __init__(self, bc: BackendContext, params: Any) -> None: ...

    def begin_frame(self, frame_index: int) -> None:
        """Called before the first pass of a frame (temporal state lives in the backend)."""

    def trace(self, rays: RayBatch, pinfo: PassInfo, hits: HitBuffer) -> TraceResult:
        """Trace every active ray of `rays` into `hits`; time phases with bc.profiler."""

    def tile_level(self, size: tuple[int, int]) -> int:
        """Quadtree level of the backend's finest screen tiles (overlay outlines); -1: none."""

    def reset(self) -> None:
        """Forget temporal state (the next frame is a cold start)."""

    def scene_changed(self, bc: BackendContext) -> None:
        """The scene's triangles moved (animated scenes): `bc` holds the new leaf-order scene, the
        refitted BVH (same topology, same triangle ids) and the GpuScene, whose buffers were
        rewritten in place. Rebuild every structure that depends on the geometry before the next
        trace, timing each build as a profiler phase named "build:<structure>"."""

    def release(self) -> None: ...

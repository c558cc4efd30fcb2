"""The backend registry: one line per backend, "name": "module:Class".

Classes are imported on first use, so a backend whose device or package is missing costs nothing
until it is asked for. Everything generic code needs (parameters, overlays, counters, phases) is
read from the class's `info` (viewer.backends.interface.BackendInfo).
"""

from __future__ import annotations

import importlib

from viewer.backends.base import BackendContext
from viewer.backends.interface import Backend, BackendInfo, params_text, resolve_params
from viewer.errors import RtwalkError

BACKENDS: dict[str, str] = {
    "glsl": "viewer.backends.glsl.glsl:GlslBackend",
    "chcrt": "viewer.backends.chcrt.chcrt:ChcrtBackend",
    "embree": "viewer.backends.embree:EmbreeBackend",
    "clbvh": "viewer.backends.clbvh:ClbvhBackend",
    "ugrid": "viewer.backends.ugrid:UgridBackend",
    "pgrid": "viewer.backends.pgrid:PgridBackend",
    "voxelwalk": "viewer.backends.voxelwalk:VoxelwalkBackend",
    "voxels": "viewer.backends.voxels:VoxelsBackend",
}
#: the backend used when none is named: the first line (needs only OpenGL, exact)
DEFAULT_BACKEND: str = next(iter(BACKENDS))
#: older command-line spellings of a backend's parameters, kept working: option -> backend
#: (read without importing the backend, so the CLI starts fast)
PARAM_OPTIONS: dict[str, str] = {"--chcrt": "chcrt"}


def backend_names() -> list[str]:
    return list(BACKENDS)


def backend_class(name: str) -> type:
    target = BACKENDS.get(name)
    if target is None:
        raise RtwalkError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})")
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)


def backend_info(name: str) -> BackendInfo:
    return backend_class(name).info


def check_params(name: str, text: str | None, source: str = "--backend-params") -> str:
    """Parse and validate a backend's parameter text before any work; returns the full
    "key=value,..." text (defaults, RTWALK_<NAME>, then `text`)."""
    return params_text(resolve_params(backend_info(name), text, source))


def create_backend(name: str, bc: BackendContext, params: str | None = None) -> Backend:
    """`params`: the backend's "key=value,..." text (--backend-params), or None for defaults."""
    cls = backend_class(name)
    return cls(bc, resolve_params(cls.info, params))


def registered_infos() -> list[BackendInfo]:
    """Every registered backend's `info` whose module imports here (a backend whose package is
    missing offers no views): what view checks and the window's view list are made from."""
    infos = []
    for name in backend_names():
        try:
            infos.append(backend_class(name).info)
        except Exception:  # noqa: BLE001 (an optional backend's import error of any kind)
            continue
    return infos

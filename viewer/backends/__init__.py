"""Tracing backends, by name. Each module registers a factory taking a BackendContext."""

from __future__ import annotations

from collections.abc import Callable

from viewer.backends.base import Backend, BackendContext
from viewer.errors import RtwalkError


def _glsl(bc: BackendContext) -> Backend:
    from viewer.backends.glsl import GlslBackend

    return GlslBackend(bc)


def _embree(bc: BackendContext) -> Backend:
    from viewer.backends.embree import EmbreeBackend

    return EmbreeBackend(bc)


def _chcrt(bc: BackendContext) -> Backend:
    from viewer.backends.chcrt import ChcrtBackend, ChcrtParams

    return ChcrtBackend(bc, ChcrtParams.from_env())


BACKENDS: dict[str, Callable[[BackendContext], Backend]] = {"glsl": _glsl, "embree": _embree, "chcrt": _chcrt}


def create_backend(name: str, bc: BackendContext) -> Backend:
    factory = BACKENDS.get(name)
    if factory is None:
        raise RtwalkError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})")
    return factory(bc)

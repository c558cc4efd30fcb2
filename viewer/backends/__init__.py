"""Tracing backends, by name. Each module registers a factory taking a BackendContext."""

from __future__ import annotations

import os
from collections.abc import Callable

from viewer.backends.base import Backend, BackendContext
from viewer.errors import RtwalkError


def _glsl(bc: BackendContext, options: str | None = None) -> Backend:
    from viewer.backends.glsl import GlslBackend

    return GlslBackend(bc)


def _embree(bc: BackendContext, options: str | None = None) -> Backend:
    from viewer.backends.embree import EmbreeBackend

    return EmbreeBackend(bc)


def _chcrt(bc: BackendContext, options: str | None = None) -> Backend:
    """Parameters: RTWALK_CHCRT first, then `options` (the --chcrt text) on top."""
    from viewer.backends.chcrt import ChcrtBackend, ChcrtParams

    env = os.environ.get("RTWALK_CHCRT", "")
    text = ",".join(t for t in (env, options or "") if t.strip())
    return ChcrtBackend(bc, ChcrtParams.parse(text, "--chcrt" if options else "RTWALK_CHCRT"))


BackendFactory = Callable[[BackendContext, str | None], Backend]
BACKENDS: dict[str, BackendFactory] = {"glsl": _glsl, "embree": _embree, "chcrt": _chcrt}


def create_backend(name: str, bc: BackendContext, options: str | None = None) -> Backend:
    """`options`: the backend's "key=value,..." parameter text (e.g. --chcrt), or None."""
    factory = BACKENDS.get(name)
    if factory is None:
        raise RtwalkError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})")
    return factory(bc, options)

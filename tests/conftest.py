"""Shared fixtures: one headless EGL context per test session, prepared scenes cached."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = REPO.parent / "shared" / "scenes"
RECORDINGS = REPO / "recordings"

_prepared: dict = {}


@pytest.fixture(scope="session")
def gl_ctx():
    from viewer.tracing import shared_context

    return shared_context()


def prepared_scene(spec: str, size: int | None = None):
    """Scene + BVH, cached across tests (loading and building is the slow part)."""
    from viewer.session import prepare_scene

    key = (spec, size)
    if key not in _prepared:
        _prepared[key] = prepare_scene(spec, scene_size=size, quiet=True)
    return _prepared[key]


def shared_scene(rel: str) -> str:
    path = SHARED_SCENES / rel
    if not path.exists():
        pytest.skip(f"{path} not present")
    return str(path)

"""Shared fixtures: one headless EGL context per test session, prepared scenes cached; the session
fails when the tests leave anything new in the checkout (they write under tmp_path)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from viewer.paths import SHARED_SCENES

_prepared: dict = {}


@pytest.fixture(scope="session")
def gl_ctx():
    from viewer.gl.context import shared_context

    return shared_context()


def prepared_scene(spec: str, size: int | None = None):
    """Scene + BVH, cached across tests (loading and building is the slow part)."""
    from viewer.session import prepare_scene

    key = (spec, size)
    if key not in _prepared:
        _prepared[key] = prepare_scene(spec, scene_size=size, quiet=True)
    return _prepared[key]


_references: dict = {}


def reference_float64(triangles, origins, directions, tmin, tmax, any_hit: bool = False):
    """viewer.reference.trace_float64, memoised on its inputs (bytes, dtypes, shapes): the float64
    reference of one ray set is the same for every backend a parametrized test traces it with, so it
    is computed once (the needle tests of test_exactness spent ~0.7 s per backend on it)."""
    import hashlib

    import numpy as np

    from viewer.reference import trace_float64

    h = hashlib.sha1(str(any_hit).encode())
    for a in (triangles, origins, directions, tmin, tmax):
        a = np.asarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    key = h.hexdigest()
    if key not in _references:
        if len(_references) >= 64:
            _references.clear()
        _references[key] = trace_float64(triangles, origins, directions, tmin, tmax, any_hit=any_hit)
    t, tri = _references[key]
    return t.copy(), tri.copy()


def shared_scene(rel: str) -> str:
    path = SHARED_SCENES / rel
    if not path.exists():
        pytest.skip(f"{path} not present")
    return str(path)


# ----------------------------------------------------------------------------------------------
# backends from the registry: every registered backend meets the same bars without new test code
# ----------------------------------------------------------------------------------------------

REFERENCE_BACKEND = "embree"  # the judge: not compared with itself in agreement / image tests

_opencl_reason: list[str | None] = []


def opencl_missing() -> str | None:
    """None when an OpenCL device can be used here, else why not (checked once per session)."""
    if not _opencl_reason:
        reason = None
        try:
            import pyopencl as cl

            devices = []
            for platform in cl.get_platforms():
                try:
                    devices += platform.get_devices()
                except cl.Error:  # a platform without devices raises DEVICE_NOT_FOUND
                    pass
            if not devices:
                reason = "no OpenCL device: no platform lists a device (install pocl-opencl-icd)"
        except ImportError as exc:
            reason = f"no OpenCL: pyopencl cannot be imported ({exc})"
        except Exception as exc:  # pyopencl raises LogicError/RuntimeError when no ICD is installed
            reason = f"no OpenCL device ({type(exc).__name__}: {exc}; install pocl-opencl-icd)"
        _opencl_reason.append(reason)
    return _opencl_reason[0]


def backend_params(reference: bool) -> list:
    """pytest params, one per registered backend (registry order), with skip marks where a backend
    cannot run here or is not held to the exact bars.

    `reference`: include the reference backend (hard cases judge it against the float64 tracer);
    agreement and image tests leave it out. An OpenCL backend skips only when no OpenCL device
    exists; a backend whose class cannot be imported while OpenCL is there errors in the test
    (`backend_info` raises again there), it is never skipped silently. `info.exact` False: skipped
    with the reason (approximate by design; these tests hold exact bars)."""
    from viewer.backends import backend_info, backend_names

    params = []
    for name in backend_names():
        if name == REFERENCE_BACKEND and not reference:
            continue
        marks = []
        try:
            info = backend_info(name)
        except ImportError as exc:
            reason = opencl_missing()
            if reason is not None:
                marks.append(pytest.mark.skip(reason=f"backend '{name}' cannot be imported ({exc}); {reason}"))
            params.append(pytest.param(name, marks=marks, id=name))
            continue
        if info.device == "cl":
            reason = opencl_missing()
            if reason is not None:
                marks.append(pytest.mark.skip(reason=f"backend '{name}' runs on OpenCL: {reason}"))
        if not info.exact:
            marks.append(pytest.mark.skip(reason=f"backend '{name}' is approximate by design (info.exact = False): "
                                                 "not held to the exact bars of this test"))
        params.append(pytest.param(name, marks=marks, id=name))
    return params


def checked_backend(name: str) -> str:
    """The backend name after importing its class (raises where it is broken: an error, not a skip)."""
    from viewer.backends import backend_info

    backend_info(name)
    return name


# ----------------------------------------------------------------------------------------------
# the suite leaves the checkout as it was: every file or folder that appears in the repository
# during the session (an empty out/bench/ included, which `git status` would not show) fails it
# ----------------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
_NOT_CHECKOUT = {".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", ".gl", ".whl"}  # tool caches


def checkout_paths(root: Path = REPO) -> set[str]:
    """Every file and folder under `root`, relative, outside version control's and tools' caches."""
    found: set[str] = set()
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if d not in _NOT_CHECKOUT and not d.endswith(".egg-info")]
        rel = Path(folder).relative_to(root)
        found.update(str(rel / n) for n in dirs + files)
    return found


def pytest_sessionstart(session):
    session.config.stash[_BEFORE] = checkout_paths()


def pytest_sessionfinish(session, exitstatus):
    before = session.config.stash.get(_BEFORE, None)
    if before is None or hasattr(session.config, "workerinput"):  # an xdist worker: the controller checks
        return
    new = sorted(checkout_paths() - before)
    if new:
        shown = ", ".join(new[:10]) + (f" (+{len(new) - 10} more)" if len(new) > 10 else "")
        msg = f"the tests left new files in the checkout {REPO} (write under tmp_path instead): {shown}"
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(msg, red=True, bold=True)
        else:
            print(msg)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


_BEFORE = pytest.StashKey[set]()

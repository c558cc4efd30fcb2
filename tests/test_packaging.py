"""A non-editable install works: build a wheel of this checkout, install it into a fresh virtual
environment, and from a directory outside the repository render one frame headless with the
installed `viewer`. Also: every shader and kernel file of the source tree is inside the wheel
(editable installs read them from the checkout and hide a missing package-data pattern)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHADER_SUFFIXES = {".glsl", ".vert", ".frag", ".geom", ".comp", ".cl", ".h", ".json"}  # + scene presets
NO_BACKEND_HINT = ("No matching distribution", "Could not find a version", "Failed to establish",
                   "Temporary failure in name resolution", "Network is unreachable")


def source_shader_files() -> list[str]:
    """Shader/kernel files under viewer/ as paths inside the wheel (viewer/shaders/x.frag, ...)."""
    root = REPO / "viewer"
    return sorted(p.relative_to(REPO).as_posix() for p in root.rglob("*")
                  if p.is_file() and p.suffix in SHADER_SUFFIXES and "__pycache__" not in p.parts)


def _setuptools_ok() -> bool:
    try:
        import setuptools
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 68 and importlib.util.find_spec("wheel") is not None


def _run(cmd: list[str], cwd: Path, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of this checkout: built offline (no build isolation) when setuptools >= 68 and
    wheel are installed (the test extras), else with pip's isolated build environment."""
    out = tmp_path_factory.mktemp("wheel")
    # a clean copy of what the build reads: setuptools reuses build/ and *.egg-info of an earlier
    # build, which would hide a missing package-data pattern (and would litter the checkout)
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE", "setup.cfg", "setup.py", "MANIFEST.in"):
        if (REPO / name).is_file():
            shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "viewer", src / "viewer", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--disable-pip-version-check", "-q", "-w", str(out)]
    if _setuptools_ok():
        cmd.append("--no-build-isolation")
    proc = _run([*cmd, str(src)], cwd=out)
    if proc.returncode != 0 and any(h in proc.stdout + proc.stderr for h in NO_BACKEND_HINT):
        pytest.skip("cannot build a wheel: no setuptools>=68/wheel installed and no package index "
                    "(pip install 'setuptools>=68' wheel)")
    assert proc.returncode == 0, proc.stderr[-3000:]
    wheels = list(out.glob("rtwalk-*.whl"))
    assert len(wheels) == 1, list(out.iterdir())
    return wheels[0]


def test_wheel_holds_every_shader_and_kernel(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    wanted = source_shader_files()
    assert "viewer/shaders/gbuffer.geom" in wanted and "viewer/shaders/fullscreen.vert" in wanted
    missing = [f for f in wanted if f not in names]
    assert not missing, f"not in {wheel.name}: {missing}"


def _fresh_venv_seeing_our_packages(venv: Path) -> Path:
    """A new virtual environment whose heavy dependencies are those of the interpreter running the
    tests; returns its python. From a system Python that is --system-site-packages; from inside a
    virtual environment (the project's .venv) that flag would give the base interpreter's packages
    (no moderngl), so the new venv gets a .pth naming this one's site-packages instead: plain path
    lines, after its own site-packages, and their .pth files (an editable install of the
    checkout) are not run, so `viewer` can only come from the wheel."""
    import site

    inside = sys.prefix != sys.base_prefix
    cmd = [sys.executable, "-m", "venv", *([] if inside else ["--system-site-packages"]), str(venv)]
    proc = _run(cmd, cwd=venv.parent)
    assert proc.returncode == 0, proc.stderr[-3000:]
    py = venv / "bin" / "python"
    if inside:
        own = _run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=venv.parent)
        assert own.returncode == 0, own.stderr[-3000:]
        Path(own.stdout.strip(), "rtwalk-test-parent.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    return py


def test_installed_wheel_renders_headless(wheel, tmp_path):
    """Fresh venv (heavy dependencies from the running interpreter's packages), the wheel installed without
    dependencies; run from outside the repo, `viewer` must come from the venv and render a frame."""
    from PIL import Image

    venv = tmp_path / "venv"
    py = _fresh_venv_seeing_our_packages(venv)
    proc = _run([str(py), "-m", "pip", "install", "--no-deps", "--disable-pip-version-check", "-q", str(wheel)],
                cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    where = _run([str(py), "-c", "import viewer, viewer.gl.programs as p; print(viewer.__file__); print(p.SHADER_DIR)"],
                 cwd=work, env=env)
    assert where.returncode == 0, where.stderr[-3000:]
    module_file, shader_dir = (Path(line) for line in where.stdout.split())
    assert module_file.is_relative_to(venv), f"viewer imported from {module_file}, not the venv"
    assert shader_dir.is_relative_to(venv) and (shader_dir / "gbuffer.geom").is_file()
    out = work / "frame.png"
    proc = _run([str(py), "-m", "viewer.cli", "render", "--scene-size", "20000", "--size", "64x36",
                 "--effects", "shadows,reflections", "-o", str(out), "--quiet"], cwd=work, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (36, 64, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 20  # a rendered city, not a cleared target


def _import_graph() -> dict[str, set[str]]:
    """viewer module -> viewer modules it imports, at module level or inside functions (both run
    sooner or later); imports under `if TYPE_CHECKING:` are left out (never executed)."""
    import ast

    mods = {}
    for p in (REPO / "viewer").rglob("*.py"):
        name = ".".join(p.relative_to(REPO).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = p
    graph: dict[str, set[str]] = {}
    for name, p in mods.items():
        tree = ast.parse(p.read_text())
        skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                and getattr(node.test, "id", None) == "TYPE_CHECKING" for n in ast.walk(node)}
        deps: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                deps.add(node.module)
                deps.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[name] = {d for d in deps if d in mods and d != name}
    return graph


def test_no_import_cycles():
    """No viewer module imports, directly or through others, a module that imports it back (the CLI
    helpers live in viewer.cli_args for this); nothing but the entry point imports viewer.cli."""
    graph = _import_graph()
    assert not [m for m, deps in graph.items() if "viewer.cli" in deps], "viewer.cli is only the entry point"
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)

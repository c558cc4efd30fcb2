"""Bad input: one line on stderr, exit code 2, no traceback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def run_cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "viewer.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def assert_one_line_error(proc: subprocess.CompletedProcess, needle: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.startswith("rtwalk: error")]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert needle in lines[0], lines[0]


def test_missing_scene_file(tmp_path):
    missing = tmp_path / "nope.obj"
    assert_one_line_error(run_cli("render", str(missing), "-o", str(tmp_path / "x.png")), "nope.obj")


def test_corrupt_scene_file(tmp_path):
    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01garbage")
    assert_one_line_error(run_cli("render", str(bad), "-o", str(tmp_path / "x.png")), "garbage.ply")


def test_empty_mesh(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\nv 0 0 0\n")
    assert_one_line_error(run_cli("render", str(empty), "-o", str(tmp_path / "x.png")), "empty.obj")


def test_nan_mesh(tmp_path):
    nan = tmp_path / "nan.obj"
    nan.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert_one_line_error(run_cli("render", str(nan), "-o", str(tmp_path / "x.png")), "nan.obj")


@pytest.mark.parametrize("content", ["{not json", json.dumps({"format": "rtwalk-recording", "version": 99}),
                                     json.dumps({"format": "other"})])
def test_bad_recording(tmp_path, content):
    rec = tmp_path / "bad.json"
    rec.write_text(content)
    assert_one_line_error(run_cli("bench", "room", "--recording", str(rec)), "bad.json")


def test_missing_recording(tmp_path):
    assert_one_line_error(run_cli("bench", "room", "--recording", str(tmp_path / "gone.json")), "gone.json")


@pytest.mark.parametrize("args,needle", [
    (["render", "room", "--size", "0x10"], "--size"),
    (["render", "room", "--effects", "sparkles"], "sparkles"),
    (["render", "room", "--backend", "magic"], "magic"),
    (["render", "nosuchbuiltin"], "nosuchbuiltin"),
    (["render", "room", "--camera", "1,2,3"], "--camera"),
    (["render", "room", "--view", "xray"], "xray"),
])
def test_bad_arguments(tmp_path, args, needle):
    assert_one_line_error(run_cli(*args, "-o", str(tmp_path / "x.png")), needle)


def test_missing_egl_is_one_line(monkeypatch):
    import moderngl

    from viewer.errors import RtwalkError
    from viewer.gl.context import create_headless_context

    def broken(*a, **k):
        raise Exception("eglInitialize failed")

    monkeypatch.setattr(moderngl, "create_context", broken)
    with pytest.raises(RtwalkError) as exc:
        create_headless_context()
    assert "EGL" in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("command", ["render", "bench", "demo"])
@pytest.mark.parametrize("args,needle", [
    (["--backend", "chcrt", "--backend-params", "nosuch=1"], "nosuch"),
    (["--backend", "chcrt", "--backend-params", "t_q=fast"], "t_q"),
    (["--backend", "chcrt", "--backend-params", "max_batch=99"], "max_batch"),
    (["--backend", "glsl", "--backend-params", "t_q=1"], "--backend-params"),
    (["--backend", "magic", "--backend-params", "t_q=1"], "magic"),
], ids=["unknown-key", "bad-value", "out-of-range", "no-params", "unknown-backend"])
def test_backend_params_fail_before_the_scene(tmp_path, monkeypatch, command, args, needle):
    """The backend and its parameters are checked before anything is loaded: the scene named here
    does not exist, and the error is still about the parameters."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):  # demo: the headless replay path
        monkeypatch.delenv(var, raising=False)
    missing = str(tmp_path / "never-loaded.obj")
    extra = ["--recording", str(tmp_path / "never-read.json")] if command == "bench" else []
    proc = run_cli(command, missing, *args, *extra, "--quiet", timeout=60)
    assert_one_line_error(proc, needle)
    assert "never-loaded" not in proc.stderr and "never-read" not in proc.stderr


def test_backend_help_lists_the_registry():
    from viewer.backends import backend_names

    out = run_cli("render", "--help", timeout=60).stdout
    assert "--backend-params" in out
    for name in backend_names():
        assert name in out


def test_backend_options_merge_alias_and_params():
    """--chcrt stays an alias for chcrt's parameters; --backend-params belongs to --backend and is
    applied after it (later keys win in the registry's parser)."""
    import argparse

    from viewer.backends import check_params
    from viewer.cli_args import backend_options_from

    ns = argparse.Namespace(backend="chcrt", chcrt="t_q=0.7,max_batch=4", backend_params="t_q=0.9")
    opts = backend_options_from(ns)
    assert set(opts) == {"chcrt"}
    full = check_params("chcrt", opts["chcrt"])
    assert "t_q=0.9" in full and "max_batch=4" in full
    assert backend_options_from(argparse.Namespace(backend="glsl", chcrt="t_q=0.7", backend_params=None)) == {
        "chcrt": "t_q=0.7"}
    assert backend_options_from(argparse.Namespace(backend="glsl", chcrt=None, backend_params=None)) == {}

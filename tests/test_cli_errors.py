"""Bad input: one line on stderr, exit code 2, no traceback.

`run_cli` runs the command in this process (tests/cli_runner.py); the tests where the process
boundary matters (signals, resource limits, environment read at library load, warnings, every
line a process prints, the entry points' exit status) run a real child (`subprocess=True`)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cli_runner import run_cli


def assert_one_line_error(proc: subprocess.CompletedProcess, needle: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.startswith("rtwalk: error")]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert needle in lines[0], lines[0]


def _entry_point(kind: str) -> list[str]:
    if kind == "module":
        return [sys.executable, "-m", "viewer.cli"]
    script = Path(sys.executable).with_name("rtwalk")  # the console script of this environment
    if not script.exists():
        pytest.skip(f"no console script {script} (pip install -e .)")
    return [str(script)]


@pytest.mark.parametrize("kind", ["module", "script"])
def test_entry_points_exit_2_with_one_line(tmp_path, kind):
    """What the shell sees from a real process: `python -m viewer.cli` and the installed `rtwalk`
    script exit 2 with one line, no traceback, for a bad scene (RtwalkError) and a bad flag value
    (argparse's message, in one line)."""
    cmd = _entry_point(kind)
    proc = subprocess.run([*cmd, "render", str(tmp_path / "nope.obj"), "-o", str(tmp_path / "x.png")],
                          capture_output=True, text=True, timeout=60)
    assert_one_line_error(proc, "nope.obj")
    proc = subprocess.run([*cmd, "render", "room", "--frame", "x"], capture_output=True, text=True, timeout=60)
    assert_one_line_error(proc, "invalid int value")  # argparse's usage block before
    assert "rtwalk render --help" in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr


def test_in_process_runs_match_the_interpreter(monkeypatch):
    """run_cli in this process: argparse's exit is its status (2 with its line, 0 for --help), an
    escaping exception is exit 1 with its traceback on stderr, and process state comes back."""
    import os

    proc = run_cli("render", "room", "--frame", "x")
    assert proc.returncode == 2 and "rtwalk render --help" in proc.stderr and "invalid int value" in proc.stderr
    assert run_cli("info", "--help").returncode == 0

    import viewer.cli

    def boom(args) -> int:
        os.environ["RTWALK_TEST_LEAK"] = "1"
        os.chdir("/")
        raise ValueError("escaped")

    monkeypatch.setattr(viewer.cli, "cmd_info", boom)
    cwd = os.getcwd()
    proc = run_cli("info", "room")
    assert proc.returncode == 1 and "Traceback" in proc.stderr and "ValueError: escaped" in proc.stderr
    assert os.getcwd() == cwd and "RTWALK_TEST_LEAK" not in os.environ


def test_in_process_render_leaves_the_shared_context_working(gl_ctx, tmp_path):
    """A render in this process makes (and run_cli releases) its own EGL context; the session's
    shared context still draws and reads back afterwards."""
    import numpy as np

    def clear_and_read() -> list[int]:
        fbo = gl_ctx.simple_framebuffer((4, 4))
        fbo.use()
        gl_ctx.clear(64 / 255, 128 / 255, 191 / 255, 1.0)  # exact in 8 bits: no device's rounding of a tie
        px = np.frombuffer(fbo.read(components=4), np.uint8)[:4].tolist()
        fbo.release()
        return px

    before = clear_and_read()
    proc = run_cli("render", "room", "--size", "32x18", "--effects", "primary", "-o", str(tmp_path / "x.png"),
                   "--quiet")
    assert proc.returncode == 0 and proc.stderr == "" and (tmp_path / "x.png").stat().st_size > 0, proc.stderr
    assert clear_and_read() == before == [64, 128, 191, 255]


def test_missing_scene_file(tmp_path):
    missing = tmp_path / "nope.obj"
    assert_one_line_error(run_cli("render", str(missing), "-o", str(tmp_path / "x.png")), "nope.obj")


def test_corrupt_scene_file(tmp_path):
    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01garbage")
    assert_one_line_error(run_cli("render", str(bad), "-o", str(tmp_path / "x.png")), "garbage.ply")


def test_truncated_stl_is_not_a_missing_module(tmp_path):
    """A binary STL cut short: trimesh falls back to its ASCII reader, which imports an optional
    module; the line said only "No module named 'charset_normalizer'", as if rtwalk were broken."""
    import struct

    tri = struct.pack("<12fH", *([0.0] * 3), 0, 0, 0, 1, 0, 0, 0, 1, 0, 0)
    stl = tmp_path / "cut.stl"
    stl.write_bytes(b"\0" * 80 + struct.pack("<I", 1000) + tri * 10 + tri[:20])
    proc = run_cli("info", str(stl))
    assert_one_line_error(proc, "cut.stl")
    line = proc.stderr.strip().splitlines()[-1]
    assert not line.endswith("(No module named 'charset_normalizer')"), line


@pytest.mark.parametrize("fmt", ["ascii.ply", "binary.ply", "off", "glb", "ascii.stl"])
def test_truncated_file_says_truncated(tmp_path, fmt):
    """A file cut at 60%: a PLY or OFF states its vertex and face counts, a GLB its chunk lengths,
    an ASCII STL ends with 'endsolid'. An ASCII PLY loaded the faces it found (a cut bunny: "no
    triangles in file", or part of the mesh without a word), an OFF gave NumPy's message cut
    mid-word, an ASCII STL "no triangles in file". (A cut OBJ states no counts: it is a smaller
    valid OBJ; the binary STL case is test_truncated_stl_is_not_a_missing_module.)"""
    import trimesh

    mesh = trimesh.creation.icosphere(3)
    ext = fmt.rsplit(".", 1)[-1]
    name = f"cut.{ext}"
    file_type = "stl_ascii" if fmt == "ascii.stl" else ext
    data = mesh.export(file_type=file_type, **({"encoding": "ascii"} if fmt == "ascii.ply" else {}))
    data = data.encode() if isinstance(data, str) else data
    path = tmp_path / name
    path.write_bytes(data[: len(data) * 6 // 10])
    proc = run_cli("info", str(path))
    assert_one_line_error(proc, name)
    line = proc.stderr.strip().splitlines()[-1]
    assert "truncated or corrupt" in line and "inhomogeneous" not in line, line
    if fmt.endswith(("ply", "off")):
        assert "declares 642 vertices and 1,280 faces" in line, line
    whole = tmp_path / f"whole.{name.rsplit('.', 1)[1]}"
    whole.write_bytes(data)
    assert run_cli("info", str(whole)).returncode == 0


def test_truncated_shared_bunny(tmp_path):
    """The walkthrough's case: `head -c 1500000 bun_zipper.ply` (ASCII, cut inside the vertices)."""
    from tests.conftest import shared_scene

    cut = tmp_path / "t.ply"
    cut.write_bytes(Path(shared_scene("bunny/bun_zipper.ply")).read_bytes()[:1_500_000])
    assert_one_line_error(run_cli("info", str(cut)), "declares 35,947 vertices and 69,451 faces")


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
    (["render", "room", "--camera", "0,1,5,0,1,0,500"], "fov_deg"),
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
    (["--backend", "embree", "--backend-params", "t_q=1"], "--backend-params"),
    (["--backend", "magic", "--backend-params", "t_q=1"], "magic"),
    (["--backend", "glsl", "--backend-params", "stage=vertex"], "stage"),
], ids=["unknown-key", "bad-value", "out-of-range", "no-params", "unknown-backend", "bad-stage"])
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


# ---------------------------------------------------------------------------------------------
# issue 13: every check that needs no scene runs before the scene is loaded (the scene named here
# does not exist, and the error is still about the flag), one line, exit 2


def _never_loaded(tmp_path) -> str:
    return str(tmp_path / "never-loaded.obj")


@pytest.mark.parametrize("args,needle", [
    (["bench", "--frames", "0"], "--frames"),
    (["bench", "--frames", "-1"], "--frames"),
    (["--frames", "0"], "--frames"),  # bare `rtwalk` (demo), headless
    (["bench", "--fps", "0"], "--fps"),
    (["bench", "--fps", "nan"], "--fps"),
    (["bench", "--reference-every", "0"], "--reference-every"),
    (["bench", "--frame-every", "0"], "--frame-every"),
    (["view", "--frame-target-ms", "0"], "--frame-target-ms"),  # the window took 0 and nan
    (["view", "--frame-target-ms", "nan"], "--frame-target-ms"),
    (["render", "--seed", "-1"], "--seed"),  # was a ValueError traceback from NumPy's seeding
    (["render", "--seed", str(2**32)], "--seed"),
    (["render", "--effects", "primary", "--view", "shadows"], "--view shadows"),  # an all-black image
    (["render", "--effects", "shadows", "--view", "ao"], "--view ao"),
    (["render", "--exposure", "nan"], "--exposure"),
    (["render", "--exposure", "-1"], "--exposure"),
    (["render", "--exposure", "inf"], "--exposure"),
    (["render", "--exposure", "0"], "--exposure"),
    (["render", "--effects", ""], "--effects"),
    (["render", "--effects", "ao:2,ao:3"], "twice"),
    (["render", "--effects", "shadow,shadows"], "twice"),
    (["render", "--effects", "ao,,shadows"], "empty"),
    (["render", "--frame", "-1"], "--frame"),
    (["render", "-o", "/proc/x.png"], "/proc/x.png"),
    (["render", "-o", "somefile.xyz"], ".xyz"),
    (["render", "-o", "noextension"], "noextension"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_checks_before_the_scene(tmp_path, monkeypatch, args, needle):
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):  # demo: the headless replay path
        monkeypatch.delenv(var, raising=False)
    command, rest = (args[0], args[1:]) if not args[0].startswith("-") else ("demo", args)
    extra = ["-o", str(tmp_path / "x.png")] if command == "render" and "-o" not in rest else []
    if command == "bench":
        extra += ["--recording", "recordings/city-near.json", "--out", str(tmp_path / "bench")]
    proc = run_cli(command, _never_loaded(tmp_path), *rest, *extra, "--quiet", timeout=60)
    assert_one_line_error(proc, needle)
    assert "never-loaded" not in proc.stderr


@pytest.mark.parametrize("args,needle", [
    (["render", "room", "--size", "-5x5"], "--size"),
    (["render", "room", "--bvh-builder", "nosuch"], "nosuch"),
    (["render", "room", "--nosuch-flag"], "--nosuch-flag"),
    (["bench-grids", "--scene", "nosuch"], "nosuch"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_argparse_errors_are_one_line(args, needle):
    """Bad flags and values argparse rejects: one `rtwalk: error:` line, exit 2 (a usage block of
    ~10 lines and "rtwalk render: error: ..." before)."""
    proc = run_cli(*args)
    assert_one_line_error(proc, needle)
    assert proc.stderr.count("\n") == 1 and "--help" in proc.stderr, proc.stderr


def test_bare_rtwalk_takes_a_scene(tmp_path, monkeypatch):
    """README: `rtwalk [demo] [SCENE] ...`: a scene as the first word runs the main job (it was
    refused as an unknown subcommand); the demo's checks then run before that scene is loaded."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(var, raising=False)
    proc = run_cli(_never_loaded(tmp_path), "--frames", "0", "--quiet")
    assert_one_line_error(proc, "--frames")
    assert "never-loaded" not in proc.stderr and "invalid choice" not in proc.stderr


def test_mistyped_command_is_not_replayed_as_a_scene(monkeypatch):
    """`rtwalk rendr`: one line that names the commands and built-in scenes (it printed "no display:
    replaying recordings/city-near.json", a recording-scene warning, then "unknown built-in scene")."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(var, raising=False)
    proc = run_cli("rendr", "--frames", "1")
    assert_one_line_error(proc, "'rendr' is neither a command")
    assert "render" in proc.stderr and "room" in proc.stderr and "replaying" not in proc.stderr


def test_headless_demo_replays_the_scenes_own_recording(tmp_path, monkeypatch):
    """The headless demo of another scene replays a recording made for it (it replayed city-near's
    street cameras, an empty grey frame in the room), or says there is none, in one line."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.chdir(tmp_path)
    assert_one_line_error(run_cli("room", "--frames", "1", "--quiet"), "room")
    assert not (tmp_path / "out").exists()
    proc = run_cli("room-anim", "--frames", "1", "--size", "32x18", "--effects", "primary", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "room-anim-walk" in proc.stderr
    report = json.loads((tmp_path / "out/demo/room-anim-walk.json").read_text())
    assert report["frames"] and report["complete"] is True


def test_render_keeps_an_existing_image(tmp_path):
    """-o naming an existing file: refused before the scene without --force (it was replaced silently)."""
    old = tmp_path / "x.png"
    old.write_bytes(b"earlier")
    proc = run_cli("render", _never_loaded(tmp_path), "-o", str(old))
    assert_one_line_error(proc, "--force")
    assert "never-loaded" not in proc.stderr and old.read_bytes() == b"earlier"
    proc = run_cli("render", "room", "--size", "16x9", "--effects", "primary", "-o", str(old), "--force", "--quiet")
    assert proc.returncode == 0 and old.read_bytes()[:4] == b"\x89PNG", proc.stderr


def test_output_is_an_existing_folder(tmp_path):
    folder = tmp_path / "adir"
    folder.mkdir()
    proc = run_cli("render", _never_loaded(tmp_path), "-o", str(folder), timeout=60)
    assert_one_line_error(proc, "folder")
    assert "never-loaded" not in proc.stderr


@pytest.mark.parametrize("name", ["../escaped", "sub/x", ".."])
def test_bench_name_is_a_stem(tmp_path, name):
    """--name is the report's file stem: `../escaped` wrote the report beside --out, not in it."""
    proc = run_cli("bench", _never_loaded(tmp_path), "--recording", "recordings/city-near.json",
                   "--out", str(tmp_path / "out"), "--name", name)
    assert_one_line_error(proc, "--name")
    assert "never-loaded" not in proc.stderr


def test_bench_progressive_saves_no_frames(tmp_path):
    """--progressive with --save-frames: refused (the frames were silently not saved)."""
    proc = run_cli("bench", _never_loaded(tmp_path), "--recording", "recordings/city-near.json", "--progressive",
                   "--save-frames", str(tmp_path / "frames"), "--out", str(tmp_path / "out"))
    assert_one_line_error(proc, "--save-frames")
    assert "never-loaded" not in proc.stderr


def test_bench_keeps_saved_frames(tmp_path):
    """--save-frames into a folder holding an earlier run's frames: refused without --force (the
    reports were protected, the frames silently replaced)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frame_00000.png").write_bytes(b"earlier")
    proc = run_cli("bench", _never_loaded(tmp_path), "--recording", "recordings/city-near.json", "--save-frames",
                   str(frames), "--out", str(tmp_path / "out"))
    assert_one_line_error(proc, "--force")
    assert "never-loaded" not in proc.stderr and (frames / "frame_00000.png").read_bytes() == b"earlier"


@pytest.mark.parametrize("flag", ["--out", "--save-frames"])
def test_bench_output_folder_is_a_file(tmp_path, flag):
    """Checked before the benchmark runs (it used to crash at the end and lose the report)."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    proc = run_cli("bench", _never_loaded(tmp_path), "--recording", "recordings/city-near.json", flag, str(afile),
                   timeout=60)
    assert_one_line_error(proc, "not a folder")
    assert "never-loaded" not in proc.stderr and afile.read_text() == "x"


@pytest.mark.parametrize("command", ["bench-chcrt", "bench-pgrid", "bench-voxelwalk", "bench-voxels"])
def test_study_bench_output_folder_is_a_file(tmp_path, command):
    """`--out` naming a file: one line before anything runs (these four used to measure, then die
    in mkdir with a FileExistsError traceback)."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    proc = run_cli(command, "--out", str(afile), timeout=60)
    assert_one_line_error(proc, "not a folder")
    assert afile.read_text() == "x"


@pytest.mark.parametrize("args,needle", [
    (["--offset", "nan"], "--offset"),  # was a ValueError traceback from the BVH build
    (["--offset", "1e300"], "--offset"),
    (["--rounds", "0"], "--rounds"),  # was run as one round, silently
    (["--rounds", "-1"], "--rounds"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_bench_grids_bad_numbers(args, needle):
    assert_one_line_error(run_cli("bench-grids", "--scene", "mixed", *args, timeout=60), needle)


def test_bench_grids_huge_size_is_one_line(gl_ctx, monkeypatch):
    """--size the GL device cannot hold: one line before the scene (a moderngl.Error traceback from
    the ray targets). The available memory is pinned low so the test allocates nothing."""
    import viewer.bench.grids_far as gf
    import viewer.sysmem

    def never(*a):
        raise AssertionError("the scene was built before the size was checked")

    monkeypatch.setattr(viewer.sysmem, "available_bytes", lambda: 1 << 30)
    monkeypatch.setenv("RTWALK_GL_MEMORY_MIB", "1024")  # the same on a GPU, whose video memory is counted
    monkeypatch.setattr(gf, "scene_mixed", never)
    assert_one_line_error(run_cli("bench-grids", "--scene", "mixed", "--size", "16384x16384"), "16384x16384")


@pytest.mark.parametrize("args", [["bench-gbuffer", "--size"], ["bench-denoise", "--size"], ["bench-trace", "--sizes"]],
                         ids=lambda v: v[0])
def test_huge_bench_size_before_the_scene(gl_ctx, monkeypatch, tmp_path, args):
    """A size the device cannot hold is refused before the scene is loaded (after it, before)."""
    import viewer.session
    import viewer.sysmem

    def never(*a, **k):
        raise AssertionError("the scene was loaded before the size was checked")

    monkeypatch.setattr(viewer.sysmem, "available_bytes", lambda: 1 << 30)
    monkeypatch.setenv("RTWALK_GL_MEMORY_MIB", "1024")  # the same on a GPU, whose video memory is counted
    for name in ("prepare_scene", "prepare_scene_for_recording"):
        monkeypatch.setattr(viewer.session, name, never)
    extra = ["--out", str(tmp_path / "o")] if args[0] != "bench-denoise" else []
    proc = run_cli(*args, "4096x4096", "--recording" + ("s" if args[0] == "bench-trace" else ""), "room-anim-walk",
                   *extra, "--quiet")
    assert_one_line_error(proc, "4096x4096")


def test_bench_grids_json_is_checked_first(tmp_path):
    """--json: an existing file is kept (it was overwritten without --force), a folder or a path under
    a file is refused before the scene is built (it used to fail after the whole run)."""
    taken = tmp_path / "grids.json"
    taken.write_text("keep")
    assert_one_line_error(run_cli("bench-grids", "--scene", "mixed", "--json", str(taken)), "--force")
    assert taken.read_text() == "keep"
    assert_one_line_error(run_cli("bench-grids", "--scene", "mixed", "--json", str(tmp_path)), "folder")
    assert_one_line_error(run_cli("bench-grids", "--scene", "mixed", "--json", str(taken / "x.json")), "not a folder")


@pytest.mark.parametrize("args,needle", [
    (["--city-size", "0"], "--city-size"),  # was accepted; the city study failed (or ran) minutes later
    (["--distances", "abc"], "--distances"),  # was a ValueError after table41
    (["--distances", "1,-2"], "--distances"),
    (["--light-scene", "nosuch"], "--light-scene"),
    (["--pgrid-params", "nosuch=1"], "nosuch"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_bench_pgrid_checks_before_the_studies(tmp_path, args, needle):
    proc = run_cli("bench-pgrid", "--scene-dir", str(tmp_path / "never-read"), "--out", str(tmp_path / "out"), *args,
                   timeout=60)
    assert_one_line_error(proc, needle)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("size", ["0x1", "1x0", "99999x10", "10x"])
def test_bench_voxels_size_before_the_scene(tmp_path, size):
    """--size as every other command reads it (0x1 passed, loaded conference, then failed in the GL)."""
    proc = run_cli("bench-voxels", "--size", size, "--scenes", _never_loaded(tmp_path), "--out", str(tmp_path / "o"))
    assert_one_line_error(proc, "--size")
    assert "never-loaded" not in proc.stderr


def test_bench_denoise_checks_first_and_saves_into_a_new_folder(tmp_path):
    """bench-denoise: --backend is checked before the scene (it was after the city's BVH build), the
    images of an earlier run are kept without --force, and --save's folder is created (a missing
    one was a FileNotFoundError traceback after the measurement)."""
    proc = run_cli("bench-denoise", "--backend", "nosuch", "--size", "32x18")
    assert_one_line_error(proc, "nosuch")
    assert "BVH" not in proc.stderr
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "raw.png").write_bytes(b"keep")
    assert_one_line_error(run_cli("bench-denoise", "--save", str(taken)), "--force")
    assert (taken / "raw.png").read_bytes() == b"keep"
    save = tmp_path / "new" / "images"
    proc = run_cli("bench-denoise", "--recording", "room-anim-walk", "--frame", "10", "--size", "32x18",
                   "--effects", "ao:1", "--reference-samples", "2", "--repeats", "1", "--save", str(save), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert {"raw.png", "reference.png", "device.png"} <= {f.name for f in save.iterdir()}


def test_bench_denoise_uses_the_backend_params(gl_ctx, monkeypatch):
    """--backend-params reach the renderer (they were checked, then dropped)."""
    import viewer.renderer

    seen = []
    real = viewer.renderer.Renderer.__init__

    def spy(self, *a, **k):
        seen.append(a[6] if len(a) > 6 else k.get("backend_options"))
        real(self, *a, **k)

    monkeypatch.setattr(viewer.renderer.Renderer, "__init__", spy)
    proc = run_cli("bench-denoise", "--recording", "room-anim-walk", "--frame", "10", "--size", "16x9",
                   "--effects", "ao:1", "--reference-samples", "1", "--repeats", "1", "--backend", "chcrt",
                   "--backend-params", "t_q=0.5", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert seen and all(o == {"chcrt": "t_q=0.5"} for o in seen), seen


@pytest.mark.parametrize("args,needle", [
    (["--study", "ooc", "--ooc-scene-size", "0"], "--ooc-scene-size"),  # 0 ran the 10 M default city
    (["--study", "ooc", "--ooc-scene-size", "999999999"], "--ooc-scene-size"),
    (["--study", "tuning", "--tuning-grid", "foo=1"], "--tuning-grid"),  # was reported as --chcrt
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_bench_chcrt_study_options(tmp_path, args, needle):
    proc = run_cli("bench-chcrt", *args, "--out", str(tmp_path / "out"))
    assert_one_line_error(proc, needle)
    assert not (tmp_path / "out").exists()


def test_missing_opencl_device_before_the_scene(tmp_path, monkeypatch):
    from viewer.backends import backend_info, backend_names

    cl_backends = [n for n in backend_names() if backend_info(n).device == "cl"]
    if not cl_backends:
        pytest.skip("no OpenCL backend registered")
    monkeypatch.setenv("RTWALK_CL_DEVICE", "no-such-device-anywhere")
    # a child: the device is chosen once per process (viewer.cl.context caches it)
    proc = run_cli("render", _never_loaded(tmp_path), "--backend", cl_backends[0], "-o", str(tmp_path / "x.png"),
                   timeout=60, subprocess=True)
    assert_one_line_error(proc, "OpenCL")
    assert "never-loaded" not in proc.stderr


def test_missing_egl_before_the_scene(tmp_path, monkeypatch):
    """No EGL vendor library (glvnd finds no device): one line about EGL, before any loading."""
    monkeypatch.setenv("__EGL_VENDOR_LIBRARY_FILENAMES", str(tmp_path / "no-vendor.json"))
    # a child: glvnd reads the variable when libEGL is loaded
    proc = run_cli("render", _never_loaded(tmp_path), "-o", str(tmp_path / "x.png"), timeout=60, subprocess=True)
    assert_one_line_error(proc, "EGL")
    assert "never-loaded" not in proc.stderr


def test_scene_size_takes_suffixes():
    """--scene-size 2M as `city:2M` and --triangles 2M (it was "invalid int value")."""
    from viewer.cli_args import scene_size_arg

    assert [scene_size_arg(t) for t in ("150000", "400k", "2M", "1_000_000", "1e6", "1.5k")] == [
        150000, 400000, 2000000, 1000000, 1000000, 1500]
    proc = run_cli("render", "city", "--scene-size", "2.5", "-o", "x.png")
    assert proc.returncode == 2 and "--scene-size" in proc.stderr and "Traceback" not in proc.stderr
    assert_one_line_error(run_cli("info", "city", "--scene-size", "99M"), "out of range")


def test_closed_stdout_is_no_traceback():
    """`rtwalk info room | head -1`: the reader closes the pipe; a BrokenPipeError traceback before."""
    proc = subprocess.Popen([sys.executable, "-m", "viewer.cli", "info", "room", "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 1 and "Traceback" not in err and "BrokenPipe" not in err, err


def test_bench_voxels_ctrl_c_names_the_partial_report(gl_ctx, tmp_path, monkeypatch):
    """Ctrl-C after a finished resolution: one line naming the report on disk ("complete": false);
    it said only "rtwalk: interrupted"."""
    import viewer.bench.voxels as vb

    real = vb.study_scene

    def ctrl_c_after_the_first_checkpoint(*a):
        def checkpoint(partial):
            a[-1](partial)
            raise KeyboardInterrupt
        return real(*a[:-1], checkpoint)

    monkeypatch.setattr(vb, "study_scene", ctrl_c_after_the_first_checkpoint)
    out = tmp_path / "vox"
    proc = run_cli("bench-voxels", "--scenes", "room", "--resolutions", "32", "--structures", "bvh", "--stacks", "4",
                   "--size", "32x18", "--rounds", "1", "--no-image", "--out", str(out), "--quiet")
    assert proc.returncode == 130, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if ln.startswith("rtwalk:")]
    assert len(said) == 1 and str(out / "bench_voxels.json") in said[0], proc.stderr
    assert json.loads((out / "bench_voxels.json").read_text())["complete"] is False


def test_scene_size_of_a_file_is_refused(tmp_path):
    """--scene-size with a scene file (or a recording of one): one line (it was ignored)."""
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert_one_line_error(run_cli("info", str(mesh), "--scene-size", "5"), "--scene-size")
    assert run_cli("info", "room", "--scene-size", "2").returncode == 0


def test_seed_of_a_builtin_scene(tmp_path):
    """`rtwalk render room --seed -1` and bench-bvh's city: one line (a NumPy traceback before)."""
    assert_one_line_error(run_cli("info", "room", "--seed", "-1"), "--seed")
    assert_one_line_error(run_cli("bench-bvh", "--seed", "-1", "--triangles", "1000", "--out", str(tmp_path)),
                          "--seed")


@pytest.mark.parametrize("sizes,needle", [("abc", "--triangles"), ("0", "out of range"), ("-5", "--triangles"),
                                          ("1000,x", "--triangles"), ("40000001", "out of range")])
def test_bench_bvh_sizes(tmp_path, sizes, needle):
    """Same range as --scene-size; nothing is built (the first size is valid in the mixed case)."""
    proc = run_cli("bench-bvh", "--triangles", sizes, "--out", str(tmp_path), timeout=60)
    assert_one_line_error(proc, needle)
    assert "tris: build" not in proc.stdout


def _address_space_limit(gib: int):
    import resource

    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (gib << 30, gib << 30))

    return apply


def test_scene_size_memory_estimate_refuses_before_building():
    """Under a 3 GiB address-space limit the largest city (40M triangles, ~16 GiB) is refused with
    the figure, at once; a small one still loads under the same limit."""
    limit = _address_space_limit(3)
    proc = run_cli("info", "--scene-size", "40000000", timeout=60, subprocess=True, preexec_fn=limit)
    assert_one_line_error(proc, "GiB")
    assert "40,000,000" in proc.stderr and "available" in proc.stderr
    ok = run_cli("info", "--scene-size", "2000", "--quiet", timeout=120, subprocess=True, preexec_fn=limit)
    assert ok.returncode == 0, ok.stderr


def test_memory_estimate_covers_a_measured_build():
    """The per-triangle figure is not below what a build here really takes (peak RSS growth of
    prepare_scene on a 300k-triangle city in a fresh process)."""
    from viewer.procedural import BUILTIN_SCENES

    code = ("import resource; from viewer.session import prepare_scene; "
            "r0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss; "
            "prepare_scene('city', scene_size=300000, quiet=True); "
            "print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - r0) * 1024)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, check=True)
    grown = int(out.stdout.strip().splitlines()[-1])
    assert BUILTIN_SCENES["city"].memory_estimate(300_000) >= grown


def test_nan_vertices_one_line_no_numpy_warning(tmp_path):
    mesh = tmp_path / "partly-nan.obj"
    mesh.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nv inf 1 1\nv 0 0 1\nf 1 2 3\nf 2 3 4\nf 2 3 5\n")
    proc = run_cli("info", str(mesh), timeout=60, subprocess=True)  # what a fresh interpreter prints
    assert proc.returncode == 0, proc.stderr
    assert "Warning" not in proc.stderr, proc.stderr
    assert sum("dropped 2 triangles with NaN/Inf" in ln for ln in proc.stderr.splitlines()) == 1, proc.stderr


def test_info_prints_short_albedo(tmp_path):
    proc = run_cli("info", "room", "--quiet", timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "albedo [" in proc.stdout and "0000000" not in proc.stdout and "9999999" not in proc.stdout, proc.stdout


def test_every_option_has_help():
    from viewer.cli import build_parser

    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    missing = [f"{name} {a.option_strings[0]}" for name, p in sub.choices.items() for a in p._actions
               if a.option_strings and a.dest != "help" and not a.help]
    assert not missing, missing
    helps = {a.dest: a.help for a in sub._choices_actions}
    assert set(helps) == set(sub.choices) and all(helps.values()), helps


def test_help_shows_the_defaults():
    """--help names each option's default (--size, --effects, --backend did not; view's size is not
    render's), once: a help text that already says its default is left alone."""
    import re

    def option_help(command: str, option: str) -> str:
        text = run_cli(command, "--help").stdout
        block = re.search(rf"^  {re.escape(option)}\b.*?(?=^  -|\Z)", text, re.S | re.M).group(0)
        return " ".join(block.split())

    assert "(default: 640x360)" in option_help("render", "--size")
    assert "(default: 896x504)" in option_help("view", "--size")
    assert "(default: shadows,reflections)" in option_help("view", "--effects")
    assert "(default: glsl)" in option_help("bench", "--backend")
    assert "(default: 24)" in option_help("demo", "--frames")
    assert "(default: 0)" in option_help("bench-voxels", "--record-passes")
    assert "default: " not in option_help("render", "--quiet")  # a flag
    assert option_help("bench", "--frames").count("default") == 1  # its text says "default 48"


def test_force_only_where_reports_are_written():
    """--force "overwrites reports already in the output folder": offered only by the commands that
    write some (bench-light and bench-bvh-trace print a table and had a --force that did nothing)."""
    from viewer.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    with_force = {name for name, p in sub.choices.items() if any("--force" in a.option_strings for a in p._actions)}
    assert {"bench", "bench-bvh", "bench-cl", "bench-trace", "bench-chcrt", "bench-pgrid", "bench-voxelwalk",
            "bench-voxels", "bench-gbuffer", "bench-grids", "bench-denoise"} <= with_force
    assert not with_force & {"bench-light", "bench-bvh-trace"}


def test_default_report_folders_are_ignored_by_git():
    """Every --out default lies under out/ (.gitignore'd): bench-trace and bench-voxels wrote
    bench-trace/ and bench-voxels/ into the checkout, untracked."""
    from pathlib import Path

    from viewer.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    outs = {name: a.default for name, p in sub.choices.items() for a in p._actions if a.dest == "out" and a.default}
    assert outs and all(Path(v).parts[0] == "out" for v in outs.values()), outs
    assert "/out/" in (Path(__file__).parents[1] / ".gitignore").read_text().split()


def test_readme_lists_every_command():
    from pathlib import Path

    from viewer.cli import build_parser

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    commands = readme.split("## Commands", 1)[1].split("\n- ", 1)[0]
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name in sub.choices:
        assert f"rtwalk {name}" in commands or f"rtwalk [{name}]" in commands, name


def test_default_bench_is_minutes_not_hours():
    """The default replays a bounded number of frames spread over the path and checks a few
    against Embree (city-near has 361 frames; every one, each with an Embree render, took over an
    hour on 2 cores)."""
    from viewer.bench.harness import frame_numbers
    from viewer.cli import build_parser
    from viewer.cli_args import DEFAULT_RECORDING
    from viewer.recording import load_recording

    args = build_parser().parse_args(["bench"])
    rec = load_recording(DEFAULT_RECORDING)
    frames = frame_numbers(rec, args.fps, args.frames, args.first_frame)
    assert rec.frame_count() > 300 and len(frames) <= 60
    assert frames[0] == 0 and frames[-1] == rec.frame_count() - 1  # spread over the whole path
    assert len(range(0, len(frames), args.reference_every)) <= 10


def test_bench_prints_its_estimate(tmp_path):
    proc = run_cli("bench", "room", "--recording", "recordings/city-near.json", "--frames", "3",
                   "--reference-every", "2", "--size", "48x27", "--effects", "shadows", "--out", str(tmp_path),
                   timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "3 of the path's" in proc.stderr and "2 checked against Embree" in proc.stderr, proc.stderr
    assert "estimated" in proc.stderr, proc.stderr


def test_readme_is_a_short_manual_with_working_links():
    """The README says what rtwalk is, how to set up and use it; architecture and measured studies
    live in docs/ (a README of 900 lines hid the set-up commands). Every relative link resolves."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    assert len(readme.splitlines()) < 250
    for doc in [root / "README.md", *sorted((root / "docs").rglob("*.md"))]:
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", doc.read_text()):
            assert (doc.parent / target).exists(), f"{doc.relative_to(root)} links to missing {target}"


# ---------------------------------------------------------------------------------------------
# issue 23: nothing lost, nothing silent


def _long_room_path(tmp_path, seconds: float = 60.0):
    """A room walk long enough that a bench of it is still running when interrupted."""
    from viewer.camera import Camera
    from viewer.recording import Keyframe, Recording, save_recording

    cams = [Camera.look_at([-1.5, 1.2, 2.0], [0.5, 0.8, -1.0]), Camera.look_at([1.0, 1.4, 2.2], [-0.5, 0.6, -1.0])]
    keys = [Keyframe.from_camera(t, c) for t, c in zip((0.0, seconds), cams, strict=True)]
    return save_recording(Recording({"builtin": "room"}, (32, 18), 10.0, keys), tmp_path / "room-long.json")


def test_bench_refuses_to_overwrite_a_report(tmp_path):
    """A report already in --out/--name is kept: one line naming it and --force, exit 2, before any
    work; with --force the run replaces it."""
    path = _long_room_path(tmp_path, 0.2)
    out = tmp_path / "bench"
    out.mkdir()
    old = out / "t.json"
    old.write_text('{"finished": "earlier"}')
    args = ["bench", "--recording", str(path), "--size", "16x9", "--effects", "primary", "--reference", "none",
            "--frames", "1", "--out", str(out), "--name", "t", "--quiet"]
    proc = run_cli(*args, timeout=120)
    assert_one_line_error(proc, "--force")
    assert str(old) in proc.stderr and old.read_text() == '{"finished": "earlier"}'
    assert sorted(p.name for p in out.iterdir()) == ["t.json"]
    proc = run_cli(*args, "--force", timeout=180)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(old.read_text())
    assert report["format"] == "rtwalk-bench" and report["complete"] is True and len(report["frames"]) == 1


@pytest.mark.parametrize("command,report", [("bench-bvh", "bvh-build.json"), ("bench-cl", "bench_cl.json"),
                                            ("bench-pgrid", "table41.json"), ("bench-voxelwalk", "table51.json"),
                                            ("bench-trace", "bench_trace.json"),
                                            ("bench-voxels", "bench_voxels.json")])
def test_every_bench_command_refuses_to_overwrite(tmp_path, capsys, command, report):
    """Each report-writing benchmark checks its report names before it measures anything."""
    from viewer.cli import main

    (tmp_path / report).write_text("kept")
    extra = {"bench-pgrid": ["--study", "table41"], "bench-voxelwalk": ["--study", "table51"],
             "bench-voxels": ["--scenes", "room"]}.get(command, [])  # the rest: their defaults (nothing runs)
    assert main([command, *extra, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and report in err
    assert (tmp_path / report).read_text() == "kept"


def test_bench_chcrt_refuses_to_overwrite(tmp_path, capsys):
    from viewer.cli import main

    (tmp_path / "table4.json").write_text("kept")
    assert main(["bench-chcrt", "--quick", "--study", "table4", "--out", str(tmp_path), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err and (tmp_path / "table4.json").read_text() == "kept"


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_sigint_keeps_the_frames_done(tmp_path, signame):
    """Ctrl-C (or SIGTERM: `timeout`, a scheduler) during a bench: the frames finished so far are
    written, marked "complete": false (SIGTERM wrote nothing)."""
    import signal
    import threading
    import time

    path = _long_room_path(tmp_path)
    out = tmp_path / "bench"
    proc = subprocess.Popen([sys.executable, "-m", "viewer.cli", "bench", "--recording", str(path), "--size", "16x9",
                             "--effects", "primary", "--reference", "none", "--frames", "600", "--out", str(out),
                             "--name", "cut"], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(iter(lambda: proc.stderr.read(1), "")), daemon=True)
    reader.start()
    deadline = time.monotonic() + 240
    while "bench: estimated" not in "".join(err):  # printed once the first frame is done
        assert proc.poll() is None and time.monotonic() < deadline, "".join(err)[-2000:]
        time.sleep(0.05)
    proc.send_signal(getattr(signal, signame))
    code = proc.wait(timeout=120)
    reader.join(timeout=10)
    text = "".join(err)
    assert code == 130, "\n".join(ln for ln in text.replace("\r", "\n").splitlines() if "frame/s" not in ln)[-3000:]
    assert "Traceback" not in text and "partial report" in text, text[-2000:]
    said = [ln for ln in text.replace("\r", "\n").splitlines() if ln.startswith("rtwalk:")]
    assert len(said) == 1 and said[0].startswith("rtwalk: interrupted after"), said  # was two lines
    report = json.loads((out / "cut.json").read_text())
    assert report["complete"] is False and 1 <= len(report["frames"]) < 600
    assert report["summary"]["frames"] == len(report["frames"])


def test_huge_size_is_one_line(tmp_path):
    """--size 16384x16384: refused before allocation (here: the targets' memory estimate against a
    16 GiB address-space limit on a CPU rasterizer, RTWALK_GL_MEMORY_MIB's 16 GiB on a GPU), one
    line, exit 2."""
    import os
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (16 << 30, 16 << 30))

    env = {**os.environ, "RTWALK_GL_MEMORY_MIB": "16384"}
    proc = run_cli("render", "room", "--size", "16384x16384", "--effects", "primary", "-o", str(tmp_path / "x.png"),
                   timeout=180, subprocess=True, preexec_fn=limit, env=env)
    assert_one_line_error(proc, "16384x16384")
    assert not (tmp_path / "x.png").exists()
    assert "BVH" not in proc.stderr + proc.stdout  # refused before the scene was loaded (it was after)
    proc = run_cli("bench", _never_loaded(tmp_path), "--recording", "recordings/city-near.json", "--size",
                   "16384x16384", "--out", str(tmp_path / "b"), timeout=180, subprocess=True, preexec_fn=limit, env=env)
    assert_one_line_error(proc, "16384x16384")
    assert "never-loaded" not in proc.stderr


def test_target_limits_and_allocation_errors(gl_ctx, monkeypatch):
    """The side limits the driver reports, the memory estimate, and moderngl's own failure at target
    creation all end as one-line RtwalkErrors."""
    import moderngl

    from viewer import sysmem
    from viewer.errors import RtwalkError
    from viewer.gl import limits

    side = limits.max_target_side(gl_ctx)
    assert side == min(gl_ctx.info["GL_MAX_TEXTURE_SIZE"], gl_ctx.info["GL_MAX_RENDERBUFFER_SIZE"],
                       *gl_ctx.info["GL_MAX_VIEWPORT_DIMS"])
    with pytest.raises(RtwalkError, match="per side"):
        limits.check_target_size(gl_ctx, (side + 1, 8))
    limits.check_target_size(gl_ctx, (64, 36))
    if limits.shares_system_memory(gl_ctx):
        monkeypatch.setattr(sysmem, "available_bytes", lambda: 64 * 36 * limits.TARGET_BYTES_PER_PIXEL - 1)
        with pytest.raises(RtwalkError, match="can be allocated"):
            limits.check_target_size(gl_ctx, (64, 36))
        monkeypatch.undo()
    else:  # a GPU: the free video memory, where the driver tells it, within the device's whole memory
        free = limits.video_memory_free(gl_ctx)
        assert free is None or 0 < free < 1 << 50, free
    # the env cap, on every device
    monkeypatch.setenv("RTWALK_GL_MEMORY_MIB", "1")
    assert limits.gl_memory_available(gl_ctx) == 1 << 20
    limits.check_target_size(gl_ctx, (64, 36))  # 64 x 36 x 180 B < 1 MiB
    with pytest.raises(RtwalkError, match="can be allocated"):
        limits.check_target_size(gl_ctx, (128, 128))
    for bad in ("x", "0", "-5"):
        monkeypatch.setenv("RTWALK_GL_MEMORY_MIB", bad)
        with pytest.raises(RtwalkError, match="RTWALK_GL_MEMORY_MIB"):
            limits.gl_memory_available(gl_ctx)
    monkeypatch.delenv("RTWALK_GL_MEMORY_MIB")
    with pytest.raises(RtwalkError) as exc:
        with limits.allocation_guard((9000, 9000)):
            raise moderngl.Error("the framebuffer is not complete")
    assert "9000x9000" in str(exc.value) and "\n" not in str(exc.value)


def test_recording_of_another_scene_warns(capsys):
    """`render room --recording city-near.json` replays the street cameras in the room (a grey frame)
    without a word before; its own scene, or none named, gives no warning."""
    from viewer.cli_args import warn_other_scene
    from viewer.recording import load_recording

    rec = load_recording("recordings/city-near.json")
    assert "made for scene 'city'" in warn_other_scene(rec, "room")
    assert warn_other_scene(rec, "city") is None and warn_other_scene(rec, "city:2M") is None
    sponza = load_recording("recordings/sponza-walk.json")
    assert warn_other_scene(sponza, "room") is not None
    assert "warning" in capsys.readouterr().err


def test_reflections_without_mirrors_warn(tmp_path):
    """--effects reflections on a scene without mirror materials: one warning line that says how to
    add mirrors; the frame is still rendered (exit 0)."""
    scene = tmp_path / "plain.obj"
    scene.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    # a child: every line on the process's stderr counts, also what Mesa or PoCL would print there
    proc = run_cli("render", str(scene), "--effects", "reflections", "--size", "32x18", "-o",
                   str(tmp_path / "x.png"), "--quiet", timeout=120, subprocess=True)
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("rtwalk: warning:") and "--mirror PATTERN" in lines[0], lines
    assert (tmp_path / "x.png").exists()


def test_mirrors_or_no_reflections_do_not_warn(capsys):
    from types import SimpleNamespace

    from viewer.cli_args import warn_no_mirrors
    from viewer.effects import parse_effects

    plain = SimpleNamespace(name="plain", materials=[SimpleNamespace(mirror=False)])
    mirrored = SimpleNamespace(name="m", materials=[SimpleNamespace(mirror=False), SimpleNamespace(mirror=True)])
    assert warn_no_mirrors(parse_effects("shadows"), plain) is None
    assert warn_no_mirrors(parse_effects("reflections"), mirrored) is None
    assert capsys.readouterr().err == ""
    assert "--mirror" in warn_no_mirrors(parse_effects("reflections"), plain)


def test_deferred_interrupt_sets_a_flag_then_raises():
    """viewer.interrupt: the first SIGINT inside the block only sets the flag (nothing is raised
    wherever the interpreter happens to be, e.g. in a destructor); a second one raises
    KeyboardInterrupt; the previous handler is back after the block."""
    import signal
    import time

    from viewer.interrupt import deferred_interrupt

    def spin_until(done) -> None:  # the handler runs at a bytecode boundary of this thread
        deadline = time.monotonic() + 5.0
        while not done() and time.monotonic() < deadline:
            pass

    # The handler before the block is Python's own (a test worker's may be another, left by what ran
    # in it before); raise_signal delivers to this, the main, thread (os.kill let the kernel pick any
    # thread of the process, an OpenCL worker among them)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with deferred_interrupt() as ctrl_c:
            assert not ctrl_c.requested
            signal.raise_signal(signal.SIGINT)
            spin_until(lambda: ctrl_c.requested)
            assert ctrl_c.requested
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
                spin_until(lambda: False)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, outer if outer is not None else signal.default_int_handler)


def test_info_scene_with_backend_shows_both():
    """`rtwalk info SCENE --backend NAME` printed the backend alone and ignored SCENE without a
    word: now the scene's statistics, then the backend; --backend alone loads no scene."""
    from viewer.backends import backend_info
    from viewer.backends.interface import describe

    both = run_cli("info", "room", "--backend", "glsl", "--quiet")
    assert both.returncode == 0, both.stderr
    assert both.stdout.startswith("scene room: ") and both.stdout.rstrip().endswith(describe(backend_info("glsl")))
    alone = run_cli("info", "--backend", "glsl", "--quiet")
    assert alone.returncode == 0 and alone.stdout.strip() == describe(backend_info("glsl")), alone.stdout
    assert_one_line_error(run_cli("info", "room", "--backend", "nope"), "unknown backend 'nope'")


def test_demo_window_opens_at_the_view_size(monkeypatch):
    """`rtwalk demo` with a display opened the window at demo's 640x360 (the headless replay's
    size), not at view's 896x504; --size still wins, and the headless replay keeps 640x360."""
    import viewer.cli

    seen = []
    monkeypatch.setattr(viewer.cli, "cmd_view", lambda args: seen.append(("view", args.size)) or 0)
    monkeypatch.setattr(viewer.cli.bench_module("bench"), "run", lambda args: seen.append(("bench", args.size)) or 0)
    monkeypatch.setattr(viewer.cli, "demo_recording", lambda scene: Path("recordings/city-near.json"))
    monkeypatch.setenv("DISPLAY", ":4093")
    assert run_cli("demo").returncode == 0
    assert run_cli("demo", "--size", "320x180").returncode == 0
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert run_cli("demo").returncode == 0
    assert seen == [("view", viewer.cli.VIEW_SIZE), ("view", "320x180"), ("bench", "640x360")]


def test_bad_loop_limit_before_the_scene(tmp_path, monkeypatch):
    """RTWALK_LOOP_LIMIT that is neither a limit of at least 20,000 nor `none`: one line, exit 2,
    before the scene is loaded."""
    monkeypatch.setenv("RTWALK_LOOP_LIMIT", "lots")
    proc = run_cli("render", _never_loaded(tmp_path), "-o", str(tmp_path / "x.png"))
    assert_one_line_error(proc, "RTWALK_LOOP_LIMIT")
    assert "never-loaded" not in proc.stderr

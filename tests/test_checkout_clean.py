"""The session check of tests/conftest.py: what it sees as the checkout (an empty folder counts;
version control and tool caches do not)."""

from __future__ import annotations

from tests.conftest import checkout_paths


def test_checkout_paths_see_empty_folders_and_skip_caches(tmp_path):
    for d in (".git/objects", ".venv/lib", "viewer/__pycache__", "pkg.egg-info", "out/bench"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "viewer" / "a.py").write_text("x")
    (tmp_path / "viewer" / "__pycache__" / "a.pyc").write_text("x")
    before = checkout_paths(tmp_path)
    assert before == {"viewer", "viewer/a.py", "out", "out/bench"}
    (tmp_path / "out" / "bench" / "r.json").write_text("{}")
    (tmp_path / "shots").mkdir()
    assert checkout_paths(tmp_path) - before == {"out/bench/r.json", "shots"}

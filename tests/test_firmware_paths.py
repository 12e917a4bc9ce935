"""The emulated boards build wherever hapsim is installed, not only in a checkout (issue 30:
``emulated/hapkit_board.py`` built the firmware from a path only a checkout has)."""

import fnmatch
import os
import subprocess
import tomllib
from pathlib import Path

import pytest

from hapsim.emulated import hapkit_board as board
from hapsim.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_every_firmware_source_is_package_data():
    """Each tracked file make needs under firmware_protocol/{c,firmware} matches a
    package-data pattern of pyproject.toml, so a wheel carries it."""
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"]["firmware_protocol"]
    files = subprocess.run(["git", "ls-files", "firmware_protocol/c", "firmware_protocol/firmware"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout: nothing to compare the package data with")
    needed = [f[len("firmware_protocol/"):] for f in files if not f.endswith(".gitignore")]
    missing = [f for f in needed if not any(fnmatch.fnmatchcase(f, p) for p in patterns)]
    assert not missing, f"not in package data: {missing}"


def test_sources_are_found_through_the_package():
    import firmware_protocol
    assert board.PACKAGE == Path(firmware_protocol.__file__).resolve().parent
    assert (board.ROOT / "hapkit" / "main.c").is_file() or board.BUILD_TREE != board.PACKAGE


def test_a_read_only_install_builds_in_a_per_user_copy(tmp_path, monkeypatch):
    """Not writable: the build tree is a copy under the user's cache, refreshed file by
    file (a changed source is copied again, an unchanged one keeps its time stamp)."""
    pkg = tmp_path / "site" / "firmware_protocol"
    (pkg / "c").mkdir(parents=True)
    (pkg / "firmware" / "hapkit").mkdir(parents=True)
    (pkg / "c" / "hproto.c").write_text("int a;\n")
    (pkg / "firmware" / "hapkit" / "main.c").write_text("int b;\n")
    (pkg / "codec.py").write_text("# not a firmware source\n")
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == pkg / "firmware"
                        else real_access(p, mode))
    tree = board._build_tree(pkg, tmp_path / "cache")
    assert tree != pkg and tree.is_relative_to(tmp_path / "cache")
    monkeypatch.setattr(board, "PACKAGE", pkg)
    monkeypatch.setattr(board, "BUILD_TREE", tree)
    board._copy_sources()
    assert (tree / "c" / "hproto.c").read_text() == "int a;\n"
    assert (tree / "firmware" / "hapkit" / "main.c").read_text() == "int b;\n"
    assert not (tree / "codec.py").exists()
    kept = (tree / "c" / "hproto.c").stat().st_mtime_ns
    os.utime(tree / "firmware" / "hapkit" / "main.c", ns=(0, 0))
    (pkg / "firmware" / "hapkit" / "main.c").write_text("int c;\n")
    board._copy_sources()
    assert (tree / "firmware" / "hapkit" / "main.c").read_text() == "int c;\n"
    assert (tree / "firmware" / "hapkit" / "main.c").stat().st_mtime_ns > 0
    assert (tree / "c" / "hproto.c").stat().st_mtime_ns == kept


def test_a_writable_package_builds_in_place(tmp_path):
    (tmp_path / "firmware").mkdir()
    assert board._build_tree(tmp_path, tmp_path / "cache") == tmp_path


def test_the_default_scene_needs_the_checkout():
    assert Path(board.shipped_scene("hapkit.yaml")).is_file()
    with pytest.raises(ConfigError, match="--scene"):
        board.shipped_scene("no_such_scene.yaml")

"""Committed records name no machine path: what ``docs/`` and ``tests/data/`` hold reads the
same in any clone (no interpreter of the machine a tool ran on, no temporary directory, no
worktree). The tools write portable paths through ``tools/provenance.py``; this test catches
a record written before that, or by a tool that bypasses it.

``/dev/...`` names (a pty such as ``/dev/pts/3``, a serial port) are device names a user
types or hapsim prints, not machine paths, and are allowed.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: An absolute path into a user's, a build's or a temporary directory: the start of a path
#: component after a non-path character (so ``configs/tmp/x`` and ``a/work/b`` are not one),
#: on POSIX or Windows.
MACHINE_PATH = re.compile(
    rb"(?<![A-Za-z0-9_.~/\\-])"
    rb"(?:/(?:tmp|work|home|root|Users|mnt|opt|srv|var/folders|var/tmp|private/var|private/tmp)/"
    rb"|[A-Za-z]:\\\\?(?:Users|Temp|tmp)\\)")


def machine_paths(data: bytes) -> list[str]:
    """The machine paths in ``data`` (each with up to 40 bytes after it, for the message)."""
    return [data[m.start():m.start() + 40].decode("utf-8", "replace")
            for m in MACHINE_PATH.finditer(data)]


def committed_files() -> list[Path]:
    """The files under docs/ and tests/data/ and README.md that git tracks (every file of
    those folders when this is not a git checkout)."""
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--", "docs",
                              "tests/data", "README.md"], capture_output=True, check=True)
        names = [n for n in out.stdout.decode().split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        names = []
    if names:
        return [ROOT / n for n in names if (ROOT / n).is_file()]
    return sorted(p for d in ("docs", "tests/data") for p in (ROOT / d).rglob("*")
                  if p.is_file()) + [ROOT / "README.md"]


@pytest.mark.parametrize("text", [
    "command: /work/venv/bin/python tools/bench_loop.py",
    "--json /tmp/q/bench_loop_full.json",
    '"telemetry": "/tmp/s13l/soak30c_nofault.hst"',
    "later runs load them from /tmp/bench_startup_wmfn/cache_this/kernels_7e",
    "`/home/alice/hapsim/docs`", "(/Users/bob/x.json)", "/root/.cache/numba",
    "/var/folders/xy/T/tmpab/x", "C:\\Users\\carol\\x.json", "/opt/venv/bin/python",
])
def test_scanner_finds_machine_paths(text):
    """Each kind of path a tool has written (or could) is found."""
    assert machine_paths(text.encode()), text


@pytest.mark.parametrize("text", [
    "python tools/bench_loop.py --json docs/bench/bench_loop.json",
    "closing the loop on /dev/pts/0", "--port /dev/ttyACM0", "configs/tmp/wall.yaml",
    "$NUMBA_CACHE_DIR/kernels_7e03", "https://example.org/home/page", "a/work/b",
    "mock-port", "~/tmp/x",
])
def test_scanner_leaves_portable_text(text):
    """Relative paths, device names, URLs and placeholders are not machine paths."""
    assert not machine_paths(text.encode()), text


def test_committed_docs_name_no_machine_path():
    """No committed file under docs/ or tests/data/ (nor README.md) names a machine path."""
    files = committed_files()
    assert any(f.name == "bench_loop.txt" for f in files)     # the scan sees the records
    bad = {}
    for f in files:
        found = machine_paths(f.read_bytes())
        if found:
            bad[str(f.relative_to(ROOT))] = found[:3]
    assert not bad, ("committed files name machine paths (write them with "
                     f"tools/provenance.py: repo-relative, or the file name alone): {bad}")


def test_tools_write_portable_commands(tmp_path):
    """tools/provenance.py: the interpreter is 'python', paths inside the repository are
    relative to it, others keep their file name alone, relative ones stay as given."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from provenance import command_line, portable_path, scrub
    finally:
        sys.path.remove(str(ROOT / "tools"))
    inside = str(ROOT / "docs" / "bench_audio.json")
    assert portable_path(inside) == "docs/bench_audio.json"
    assert portable_path(str(tmp_path / "x.json")) == "x.json"
    assert portable_path("configs/wall.yaml") == "configs/wall.yaml"
    cmd = command_line(str(ROOT / "tools" / "bench_engine.py"),
                       ["--audio", "--json", inside, f"--out={tmp_path}/o.png", "-n", "3"])
    assert cmd == ("python tools/bench_engine.py --audio --json docs/bench_audio.json "
                   "--out=o.png -n 3")
    assert not machine_paths(cmd.encode())
    line = scrub(f"load them from {tmp_path}/cache_this/kernels_1 ...",
                 {f"{tmp_path}/cache_this": "$NUMBA_CACHE_DIR"})
    assert line == "load them from $NUMBA_CACHE_DIR/kernels_1 ..."

"""The README's test command is never silent on a terminal for over 2 s (issue 31): the
suite's controller marks every :data:`conftest.HEARTBEAT_S` without a test result with a
dim ``·`` (``tests/conftest.py``, ``_Heartbeat``), on a terminal only.

Checked through a real pseudo-terminal: pytest on one pytest-xdist worker (as the README's
command runs, ``-n auto``; the controller writes the marks) on a test that waits 3.5 s of
wall clock (``tests/heartbeat_inner.py``, a file pytest collects only when named: longer
than the limit, as the tests that wait on JACK or a device do) prints marks while it
waits, and its output's longest silence stays under 2 s; piped into a file (a CI log) it
prints none."""

from __future__ import annotations

import os
import pty
import select
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The wait of the test run inside [s]: over the 2 s limit by 1.5 s.
WAIT_S = 3.5
#: The limit the issue sets on a silence [s].
SILENCE_S = 2.0
MARK = "\u00b7".encode()


def _command():
    return [sys.executable, "-m", "pytest", "-q", "-n", "1", "-p", "no:cacheprovider",
            "heartbeat_inner.py"]


def _env():
    return dict(os.environ, HAPSIM_HEARTBEAT_WAIT=str(WAIT_S))


def test_a_terminal_sees_a_mark_at_least_every_two_seconds():
    master, slave = pty.openpty()
    p = subprocess.Popen(_command(), cwd=ROOT / "tests", env=_env(), stdin=subprocess.DEVNULL,
                         stdout=slave, stderr=slave, close_fds=True)
    os.close(slave)
    out = b""
    t0 = last = time.monotonic()
    longest = 0.0
    try:
        while time.monotonic() - t0 < 120:
            r, _, _ = select.select([master], [], [], 0.05)
            if r:
                try:
                    chunk = os.read(master, 65536)
                except OSError:           # the child closed the terminal
                    break
                if not chunk:
                    break
                now = time.monotonic()
                if out:                   # from the first output on: the start-up's is
                    longest = max(longest, now - last)   # the interpreter's, not the suite's
                last = now
                out += chunk
            elif p.poll() is not None:
                break
    finally:
        p.wait(30)
        os.close(master)
    assert p.returncode == 0, out.decode(errors="replace")
    assert b"1 passed" in out, out.decode(errors="replace")
    # 3.5 s of waiting with a mark per HEARTBEAT_S (1 s): at least two marks, whatever the load
    assert out.count(MARK) >= 2, out.decode(errors="replace")
    assert longest < SILENCE_S, (longest, out.decode(errors="replace"))


def test_a_log_gets_no_marks():
    res = subprocess.run(_command(), cwd=ROOT / "tests", env=_env(), capture_output=True,
                         timeout=120)
    assert res.returncode == 0, res.stdout.decode(errors="replace")
    assert b"1 passed" in res.stdout and MARK not in res.stdout + res.stderr

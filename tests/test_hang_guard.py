"""tests/hang_guard.py: a test that hangs, even on a GIL no thread will give back, ends
its process with every thread's traceback; under xdist the run goes on, fails that test
and prints the traceback; without xdist the traceback is on standard error."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: A module of tests: one whose process hangs for ever in C with the GIL held (as a thread
#: cancelled inside Python leaves it: nothing of Python runs again), and one that passes.
HANGING = '''
import ctypes, time

def test_stuck_holding_the_gil():
    # pthread_mutex_lock twice on a default mutex: blocks for ever in C; ctypes.PyDLL
    # keeps the GIL through the call, so no other Python thread runs again
    lib = ctypes.PyDLL(None)
    m = ctypes.create_string_buffer(64)
    lib.pthread_mutex_init(m, None)
    lib.pthread_mutex_lock(m)
    lib.pthread_mutex_lock(m)

def test_passes():
    time.sleep(0.1)
'''


def _run(tmp_path, *args):
    (tmp_path / "test_hanging.py").write_text(HANGING)
    env = dict(os.environ, HAPSIM_TEST_HANG_S="3",
               PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
    env.pop("HAPSIM_TEST_HANG_DIR", None)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "-p", "no:hypothesispytest", "-p", "hang_guard", "-o", "addopts=",
                           "--rootdir", str(tmp_path), *args, str(tmp_path)],
                          capture_output=True, text=True, timeout=120, env=env,
                          cwd=tmp_path)


def test_a_test_stuck_on_the_gil_fails_with_its_traceback_and_the_run_goes_on(tmp_path):
    """Under two xdist workers: the stuck test fails (its worker ended), the other passes,
    pytest exits 1, and the summary names the test and shows the stuck frame."""
    out = _run(tmp_path, "-n", "2")
    text = out.stdout + out.stderr
    assert out.returncode == 1, text
    assert "1 failed, 1 passed" in text, text
    assert "tests that hung past 3 s" in text, text
    assert "test_hanging.py::test_stuck_holding_the_gil" in text, text
    assert 'in test_stuck_holding_the_gil' in text, text


def test_without_xdist_the_traceback_is_on_stderr(tmp_path):
    """``-p no:xdist``: the process ends at the stuck test, the traceback on stderr."""
    out = _run(tmp_path, "-p", "no:xdist")
    assert out.returncode != 0
    assert "in test_stuck_holding_the_gil" in out.stderr, out.stderr

"""Nothing left behind by a stopped command (issue 31 item 3): whatever the moment a
``hapsim run`` is stopped (Ctrl-C, SIGTERM, during its imports, its numba warm-up, its
loop, or not at all), its temporary directory is empty afterwards and no child it started
(the embedded mock) is still running.

Each run gets a private ``TMPDIR`` (``tempfile`` honours it), so the files other processes
of the machine put in /tmp cannot count, and the embedded mock's command line names that
directory (its ``--report`` file), which finds a child still alive in ``/proc``.
The moments are random (a seeded generator: printed with any failure to replay it); the
SIGINT goes to the process group, as a terminal's Ctrl-C does.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The longest a run is given to end after the signal [s]: the host ends its child with
#: SIGTERM and a 2 s grace before SIGKILL (hapsim.spawn.PtyChild.end), plus a loaded
#: machine's exit (measured under 1 s at load 5 on 2 cores): 10 s leaves a margin of 3.
END_S = 10.0


def _alive_naming(text: str) -> list[str]:
    """Command lines of the live processes that contain ``text`` (from /proc)."""
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if text in cmd and "pytest" not in cmd:
            found.append(f"{pid}: {cmd}")
    return found


def _stopped_run(argv, tmp_path, after, sig):
    """Run ``hapsim ARGV`` with a private TMPDIR, send ``sig`` ``after`` seconds later
    (None: let it end); return (exit code, what is left in TMPDIR, live children)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp)}
    p = subprocess.Popen([sys.executable, "-m", "hapsim", *argv], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    if after is not None:
        time.sleep(after)
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:      # it had ended already: the normal exit path
            pass
    try:
        out, err = p.communicate(timeout=END_S + (0 if after is not None else 120))
    except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
        pytest.fail(f"hapsim {' '.join(argv)} did not end {END_S} s after the signal")
    # the report's end beside stderr: an unexpected exit code says why (a safety stop, a
    # fault, an unfit link: hapsim.pipeline.report), not only that it happened
    return (p.returncode, sorted(os.listdir(tmp)), _alive_naming(str(tmp)),
            err + ("\n--- stdout's end:\n" + out[-4000:] if out else ""))


_RNG = random.Random(31)
#: (signal, moment [s]) pairs: random moments from the start of the interpreter to the
#: end of a 1.5 s lockstep run on a loaded machine (imports, warm-up, loop, report).
_MOMENTS = [(s, round(_RNG.uniform(0.2, 3.0), 2))
            for s in (signal.SIGINT, signal.SIGINT, signal.SIGINT, signal.SIGTERM,
                      signal.SIGTERM)]


@pytest.mark.parametrize("sig, after", _MOMENTS,
                         ids=[f"{signal.Signals(s).name}-{t}s" for s, t in _MOMENTS])
def test_a_stopped_run_leaves_nothing(sig, after, tmp_path):
    code, left, alive, err = _stopped_run(
        ["run", "configs/first_wall.yaml", "--duration", "1.5", "--loop", "python"], tmp_path,
        after, sig)
    assert not left and not alive, (sig, after, code, left, alive, err)
    # stopped: 130 (Ctrl-C) / 143 (SIGTERM) before the loop is armed, 0 once it stops
    # cleanly; or it had finished (0). Or a safety stop's 1, where the report says so:
    # the first wall is stable up to a delay of 5 samples, and beside the suite's
    # real-time loops and CI's load its host has been late enough for a safety stop
    # (30 late FORCEs in 161 ticks, braked to rest; once, 57 late in 284 ticks, the
    # device naming none of the host's FORCEs, STOP sent at once): the scene's
    # documented behaviour under load (docs/reliability.md, "The lateness guard"), not
    # this test's subject, which is what is left behind.
    safety = code == 1 and "stop: safety: " in err
    assert code in (0, 130 if sig == signal.SIGINT else 143) or safety, (code, err)


def test_a_finished_and_a_failed_run_leave_nothing(tmp_path):
    """The normal exit and an error exit (a port that does not exist) leave nothing.
    (The normal run on the wall stable up to 10 samples late, test_daemon.
    late_tolerant_wall: on configs/wall.yaml, stable at its own delay only, a fresh
    clone's CI saw 309 late FORCEs in 608 ticks end the run on its safety stop, exit 1:
    the scene's documented behaviour under load, not this test's subject.)"""
    from test_daemon import late_tolerant_wall          # same directory
    wall = late_tolerant_wall(tmp_path)
    code, left, alive, err = _stopped_run(
        ["run", wall, "--duration", "0.3", "--loop", "python"], tmp_path / "a", None, None)
    assert code == 0 and not left and not alive, (code, left, alive, err)
    code, left, alive, err = _stopped_run(
        ["run", "configs/wall.yaml", "--port", "/dev/hapsim-no-such-port"],
        tmp_path / "b", None, None)
    assert code == 1 and not left and not alive, (code, left, alive, err)


def test_a_stopped_two_d_run_leaves_nothing(tmp_path):
    """The n-D run's own temporary folder (its mock's report) goes too."""
    code, left, alive, err = _stopped_run(
        ["run", "configs/pantograph_wall.yaml"], tmp_path, 2.0, signal.SIGINT)
    assert not left and not alive, (code, left, alive, err)

"""A device on a port paced by the FORCEs, driven as a real-time one (issue 19).

``hapsim run --port`` without ``--lockstep`` takes the device for a real-time one: it
counts late ticks, runs under ``SCHED_FIFO`` and declares the device lost after 50 ms of
silence. A device that waits for each FORCE (``hapsim mock --lockstep``, the emulated
Hapkit in lockstep: ``hapsim mock --firmware --lockstep``) ticks as fast as the host
answers; HELLO does not say so, its clock does: the report measures the device's ticks per
second of wall time and warns, with the fix, when they run faster than real time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from hapsim.pipeline.report import FAST_CLOCK_RATIO, device_clock_warning
from inproc import hapsim_main
from tolerance import rel_tol

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("ticks, rate, wall_s", [(1000, 1000.0, 0.4), (4000, 4000.0, 2.0),
                                                 (300, 1000.0, 0.1), (1000, 1000.0, 1.1)])
def test_the_ratio_is_ticks_over_the_rate_per_wall_second(ticks, rate, wall_s):
    ratio, warn = device_clock_warning(ticks, rate, 10.0, 10.0 + wall_s, real_time=True)
    # two divisions each side and the rounding of 10 + wall_s, which the (exact, Sterbenz)
    # subtraction of 10 leaves relative to wall_s amplified by (10 + wall_s) / wall_s:
    # derived rel_tol(5, that condition number)
    assert ratio == pytest.approx(ticks / rate / wall_s, rel=rel_tol(5, (10.0 + wall_s) / wall_s))
    assert (warn is not None) == (ratio > FAST_CLOCK_RATIO)
    if warn:
        assert "--lockstep" in warn and f"{ratio:.2f}x" in warn
    # a run that is not taken for real time (lockstep, host-clocked, a driver) is not warned
    # (the same arithmetic on the same inputs: exact)
    assert device_clock_warning(ticks, rate, 10.0, 10.0 + wall_s, real_time=False) == (
        ratio, None)


def test_too_short_or_untimed_runs_say_nothing():
    assert device_clock_warning(100, 1000.0, 1.0, 1.01, True) == (None, None)   # < 0.2 s
    assert device_clock_warning(1000, 1000.0, None, 5.0, True) == (None, None)
    assert device_clock_warning(1000, 1000.0, 0.0, 5.0, True) == (None, None)  # not armed
    assert device_clock_warning(1000, 1000.0, 5.0, 5.0, True) == (None, None)


def _env():
    e = dict(os.environ)
    e["PYTHONPATH"] = ROOT + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    return e


def test_run_port_to_a_lockstep_mock_without_lockstep_warns_with_the_fix(tmp_path):
    """``hapsim mock --lockstep`` on a pty, ``hapsim run --port`` without ``--lockstep``:
    the run completes (exit 0, stdout only JSON) and the report and stderr say that the
    device ticked faster than the wall clock, with the fix (--lockstep). At 100 Hz a
    lockstep tick is 10 ms of device time for the same wall time as at 1 kHz: 36x real
    time at load 19 on 2 cores (at 1 kHz the same load slowed it to 0.81x, when nothing
    tells it from a real-time device)."""
    from test_daemon import wall_text          # same directory (prepend mode)
    scene = tmp_path / "wall_100hz.yaml"
    scene.write_text(wall_text(20.0, 0.5, rate=100.0))
    link = str(tmp_path / "port")
    mock = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--lockstep", "--once",
                             "--scene", str(scene), "--link", link], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=_env())
    try:
        assert mock.stdout.readline().startswith("PORT ")
        # the run in this process (inproc: its stdout and stderr are file descriptors 1
        # and 2 while it runs, as a child's pipes)
        # (--lost-timeout 0.5: the mock's process starved 50 ms by a loaded machine made
        # the host declare it lost, and a --once mock does not take the reconnect: exit 1
        # in a loaded suite; what is tested is the clock's warning, not the loss rule)
        code, out, err = hapsim_main(["run", str(scene), "--port", link, "--duration", "2",
                                      "--lost-timeout", "0.5", "--json"])
        assert code == 0, err
        lp = json.loads(out)["loop"]               # stdout: only the JSON
        assert lp["device_clock_ratio"] > FAST_CLOCK_RATIO, lp["device_clock_ratio"]
        assert len(lp["warnings"]) == 1 and "--lockstep" in lp["warnings"][0]
        assert "hapsim run: warning: the device ticked" in err
        assert "run with --lockstep" in err
    finally:
        if mock.poll() is None:
            mock.kill()
        mock.wait(timeout=10)

"""hapsim.spawn.PtyChild: the host's side of an embedded mock's child process (its end and
its report), shared by hapsim.emulated.links.EmbeddedMock and
hapsim.emulated.driver_mock.EmbeddedDriverMock."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

from hapsim.spawn import PtyChild


class _Child(PtyChild):
    def __init__(self, code: str, report_path: str) -> None:
        self.report_path = report_path
        self._slave = os.open(os.devnull, os.O_RDONLY)
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)


STUBBORN = ("import signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "print('ready', flush=True); time.sleep(60)")


def test_a_child_that_ignores_sigterm_is_killed_after_the_grace_and_reaped(tmp_path):
    c = _Child(STUBBORN, str(tmp_path / "r.json"))
    assert c.proc.stdout.readline().strip() == b"ready"   # SIGTERM is ignored from now on
    c.end(grace_s=0.2)
    assert c.proc.returncode == -signal.SIGKILL             # reaped: the code is known
    assert c.report(timeout=0.0) is None                    # it wrote no report
    c.close()
    assert c._slave is None


def test_the_report_is_the_childs_json_and_close_removes_it(tmp_path):
    path = tmp_path / "r.json"
    c = _Child(f"import json; json.dump({{'ticks': 7}}, open({str(path)!r}, 'w'))", str(path))
    assert c.report(timeout=30.0) == {"ticks": 7} and c.proc.returncode == 0
    c.release_slave()
    c.close()                         # idempotent after release_slave; removes the file
    assert not path.exists() and c._slave is None
    c.close()
    assert json.dumps(c.report(timeout=0.0)) == "null"   # no file: None


#: A child that writes its report when it ends (SIGTERM) or after 1 s on its own.
REPORTER = ("import json, signal, sys, time\n"
            "def bye(*a):\n"
            "    json.dump({'ended': True}, open(sys.argv[1], 'w')); sys.exit(0)\n"
            "signal.signal(signal.SIGTERM, bye)\n"
            "time.sleep(1.0); bye()\n")


def test_a_stop_signal_inside_the_childs_start_ends_it_and_leaves_no_report(monkeypatch,
                                                                           tmp_path):
    """A Ctrl-C that lands inside ``subprocess.Popen`` (after the fork, before it returns)
    used to raise there and lose the child: nothing could end it, and the report it wrote
    on its own end was left in the temporary directory (once in a fresh-clone suite, a
    SIGINT 0.23 s into ``hapsim run``). Now the signal is held until ``proc`` is set and
    then delivered: the stop's :meth:`PtyChild.close` ends the child and removes the
    report. The signal is sent from inside Popen, after the child exists, every time."""
    import hapsim.spawn as spawn
    real = subprocess.Popen

    def popen_then_sigint(*a, **k):
        p = real(*a, **k)
        signal.raise_signal(signal.SIGINT)     # Ctrl-C while Popen has not returned
        return p

    monkeypatch.setattr(spawn.subprocess, "Popen", popen_then_sigint)
    c = PtyChild()
    master = c.open_pty("hapsim-test-")
    path = c.report_path
    try:
        try:
            c.start([sys.executable, "-c", REPORTER, path], master)
        except KeyboardInterrupt:
            interrupted = True
        else:
            interrupted = False
        assert interrupted and c.proc is not None      # delivered once the child is known
    finally:
        c.close()                                      # what the command's stop runs
    assert c.proc.returncode is not None               # ended and reaped
    assert not os.path.exists(path)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler

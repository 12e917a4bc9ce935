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

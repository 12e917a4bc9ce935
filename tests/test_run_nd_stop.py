"""Ctrl-C and SIGTERM in a 2-D/3-D ``hapsim run`` over a port (issue 30 item 2, "progress
and the Ctrl-C report" in every dimension): the record under way ends at its next read,
the device is sent STOP, and the run reports what it had, as the 1-D run does (exit 0,
the stop named, the verdict "not measurable" with the reason when the starts are not all
recorded) instead of an exit 130 with nothing. The embedded mock runs in a session of its
own (a terminal's Ctrl-C reaches only the host, which stops the device itself).
"""

from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import firmware_protocol as fp
from hapsim.emulated.links import InProcessTransport
from hapsim.emulated.mock import MockDeviceND
from hapsim.pipeline.felt_port import measure_felt_port, verdict_nd
from hapsim.scene import load_scene_nd
from hapsim.spawn import StopFlag

ROOT = Path(__file__).resolve().parents[1]


class _Counting(InProcessTransport):
    """The in-process lockstep transport, counting the FORCEs and STOPs the host sends
    and setting a stop flag at the ``at``-th FORCE (a Ctrl-C in the middle of a record)."""

    def __init__(self, device, stop: StopFlag, at: int | None) -> None:
        super().__init__(device)
        self.stop, self.at = stop, at
        self.forces = self.stops = 0

    def send(self, msg) -> None:
        if isinstance(msg, fp.Force):
            self.forces += 1
            if self.at is not None and self.forces == self.at:
                self.stop.request(signal.SIGINT)
        elif isinstance(msg, fp.Stop):
            self.stops += 1
        super().send(msg)


@pytest.mark.parametrize("name, at", [("pantograph_wall.yaml", 1), ("pantograph_wall.yaml", 220),
                                      ("delta_sphere.yaml", 400)])
def test_a_stop_ends_the_record_and_reports_not_measurable(name, at):
    """A stop at the ``at``-th FORCE (records of 150 rows: in the first, the second or the
    third record): no further FORCE is sent (the record ends at once in lockstep, where
    every read has its STATE), the last message is STOP, the stop is named and the
    verdict is "not measurable" with it; a record the stop cut is not counted as one cut
    short by a lost STATE."""
    sc = load_scene_nd(ROOT / "configs" / name)
    stop = StopFlag()
    tr = _Counting(MockDeviceND(sc, lockstep=True), stop, at)
    res = measure_felt_port(tr, sc, samples=150, stop=stop)
    assert tr.forces == at                   # not one FORCE after the stop
    assert tr.stops >= 1
    assert res["stop"] == "signal SIGINT"
    assert res["counts"]["cut"] == 0 and res["counts"]["configs"] == at // 150 + 1
    assert res["incomplete"] and res["incomplete"].startswith("stopped (signal SIGINT)")
    assert f"{at // 150} of the {2 * sc.dimension + 1} starts" in res["incomplete"]
    res["bound"] = None
    v = verdict_nd(res)
    assert v["verdict"] == "not measurable" and v["within"] is None
    assert "stopped (signal SIGINT)" in v["reason"]


def test_without_a_stop_the_measurement_is_whole():
    """The same run without a stop requested (a flag never set): every start recorded,
    ``stop`` "end", the felt matrices measured (the test above can fail)."""
    sc = load_scene_nd(ROOT / "configs" / "pantograph_wall.yaml")
    stop = StopFlag()
    tr = _Counting(MockDeviceND(sc, lockstep=True), stop, None)
    res = measure_felt_port(tr, sc, samples=150, stop=stop)
    assert res["stop"] == "end" and res["incomplete"] is None
    assert tr.forces == 5 * 150
    assert res["measured"]["felt_stiffness"] is not None


def _alive_naming(text: str) -> list[str]:
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if text in cmd:
                found.append(cmd)
    return found


#: The longest the run is given to end after the signal [s]: the record under way ends at
#: its next read (0.05 s), the mock child's report is awaited at most 5 s
#: (commands/run.py), plus a loaded machine's teardown: 15 s leaves a margin of 2.
END_S = 15.0
#: The longest the command may take to start measuring (its bar drawn after 1 s of the
#: measurement) [s]: start-up, the mock child's, the kernels' load; ~3 s unloaded, 60 s
#: is a loaded machine with numba's cache cold, with a margin.
START_S = 60.0


def test_ctrl_c_at_the_terminal_reports_and_leaves_nothing(tmp_path):
    """``hapsim run configs/delta_mesh.yaml --json`` (7 records of 3.2 s at 1 kHz), its
    stderr a terminal: once its progress bar is drawn, SIGINT to its process group (a
    terminal's Ctrl-C): exit 0 and the JSON report, ``stop`` "signal SIGINT", "not
    measurable" for that reason; no child left, no temporary folder left."""
    master, slave = pty.openpty()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp_path)}
    env.pop("HAPSIM_STATUS", None)
    p = subprocess.Popen([sys.executable, "-m", "hapsim", "run", "configs/delta_mesh.yaml",
                          "--json"], cwd=ROOT, env=env, stdin=subprocess.DEVNULL,
                         stdout=subprocess.PIPE, stderr=slave, start_new_session=True)
    os.close(slave)
    err = b""
    try:
        t0 = time.monotonic()
        while b"run (over the port)" not in err and time.monotonic() - t0 < START_S:
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    err += os.read(master, 4096)
                except OSError:
                    break
            if p.poll() is not None:
                break
        assert b"run (over the port)" in err, err[-2000:]
        os.killpg(p.pid, signal.SIGINT)
        out, _ = p.communicate(timeout=END_S)
    finally:
        os.close(master)
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, (p.returncode, err[-2000:])
    rep = json.loads(out)
    assert rep["stop"] == "signal SIGINT"
    assert rep["verdict"] == "not measurable" and rep["within"] is None
    assert rep["reason"].startswith("stopped (signal SIGINT)")
    assert not _alive_naming(str(tmp_path)) and not list(tmp_path.iterdir())

"""A device-specific run whose board goes away in the middle (unplugged, its process
ended). The FireFader's two faders in real time end there with their report of what was
recorded, "device lost" and the error, and exit 1, as every run's; never pyserial's
traceback (a killed emulated board gave ``SerialException: write failed: [Errno 32] Broken
pipe`` and no report before). A board that fails while it is armed, before any record, is
the error alone (exit 1 and, with ``--json``, the error object). The Haply 2DIY's run
reports the records made once its first is whole (before, every loss was the error alone,
and with ``--json`` stdout was empty before that). The 1-D driver runs' losses are
``tests/test_run_device_lost.py``'s, the framed n-D run's ``tests/test_run_nd_lost.py``'s."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from hapsim.drivers.firefader import FireFader
from hapsim.emulated.firefader_board import FireFaderDevice
from hapsim.emulated.links import LockstepBoardLink
from hapsim.errors import DeviceError
from hapsim.lockstep import excitation_starts
from hapsim.pipeline.faders_run import FADER_AMPLITUDE, measure_faders, record_faders
from hapsim.scene import load_scene_ports

from seeds import seeds  # same directory (pytest prepend import mode)

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
SCENE = CONFIGS / "two_faders.yaml"
N = 120                         # rows per record


class _FailingLink:
    """The lockstep board's link, whose ``op`` ("write" or "read") fails from its
    ``at``-th call on, as a port unplugged fails: with ``exc``."""

    def __init__(self, link, op: str, at: int, exc: BaseException) -> None:
        self.link, self.op, self.at, self.exc, self.calls = link, op, at, exc, 0

    def _count(self, op: str) -> None:
        if op == self.op:
            self.calls += 1
            if self.calls >= self.at:
                raise self.exc

    def write(self, data):
        self._count("write")
        return self.link.write(data)

    def read(self, n: int = 1):
        self._count("read")
        return self.link.read(n)

    @property
    def in_waiting(self) -> int:
        return self.link.in_waiting

    def __getattr__(self, attr):
        return getattr(self.link, attr)


def _board(scene):
    drv = FireFader()
    starts = excitation_starts(2, FADER_AMPLITUDE, scene.period)
    (_, da), (_, db) = scene.devices
    dev = FireFaderDevice(da, scene.rate_hz, None, clock="lockstep", device_b=db,
                          hand=[(x0[0], x0[1], v0[0], v0[1]) for x0, v0 in starts],
                          **drv.mock_hardware())
    return drv, len(starts), LockstepBoardLink(dev)


@pytest.mark.parametrize("seed", seeds(range(1, 25), kept=[1, 2, 3, 4]))
def test_a_board_lost_mid_run_ends_it_with_what_was_recorded(seed):
    """The board's port fails (a write or a read; pyserial's SerialException, the
    system's OSError or a write timeout) at a random call. Failing while the board is
    armed, before any record: a DeviceError naming the FireFader's port. Later: a result,
    ``stop`` "device lost: ...", ``error`` a DeviceError's, at most as many records as
    began, and the verdict of those records never "within" from rows not read (the
    records of a run cut short are "not measurable")."""
    rng = random.Random(seed)
    scene = load_scene_ports(SCENE)
    drv, starts, link = _board(scene)
    exc = rng.choice([serial.SerialException("read failed: [Errno 104] Connection reset"),
                      OSError(5, "Input/output error"),
                      serial.SerialTimeoutException("Write timeout")])
    op = rng.choice(["write", "read"])
    at = rng.choice([5, 50]) if seed % 4 == 1 else rng.randrange(100, starts * (N + 20))
    ser = _FailingLink(link, op, at, exc)
    try:
        run = record_faders(ser, scene, N, starts, force_scale=drv.force_scale, pace=False)
    except DeviceError as err:
        assert "the FireFader's port failed" in str(err)
        assert seed % 4 == 1, "a DeviceError after the arming"      # raised while arming
        return
    assert ser.calls >= at, "the port never failed"
    assert run["stop"].startswith("device lost: ") and "FireFader's port failed" in run["stop"]
    assert run["error"]["type"] == "DeviceError"
    assert len(run["records"]) <= starts
    from hapsim.analysis.ports import check_ports
    chk = check_ports(scene)
    res = measure_faders(scene, run, FADER_AMPLITUDE, samples=N, order=chk.states // 2,
                         chk=chk, force_scale=drv.force_scale)
    assert res["verdict"]["verdict"] == "not measurable", res["verdict"]
    assert "device lost" in res["verdict"]["reason"]


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read()
    except OSError:
        return b""


def _descendants(pid: int) -> list:
    """The processes below ``pid`` (from /proc: each one's parent)."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    parent[int(d)] = int(fh.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("scene, extra, board_process", [
    (SCENE, [], b"driver_mock"),
    (CONFIGS / "pantograph_spring.yaml", ["--driver", "haply"], b"haply2_embedded")],
    ids=["two_faders", "haply_2diy"])
def test_hapsim_run_whose_emulated_board_is_killed_says_so_and_exits_1(scene, extra,
                                                                       board_process):
    """``hapsim run SCENE --json`` in real time, its emulated board's process killed
    (SIGKILL) once its records have begun: exit 1, the report (the two faders') or the
    error object on stdout with the DeviceError, and no traceback on stderr."""
    proc = subprocess.Popen([sys.executable, "-m", "hapsim", "run", str(scene), "--json",
                             *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        board = None
        end = time.monotonic() + 30
        while board is None and time.monotonic() < end:
            board = next((p for p in _descendants(proc.pid)
                          if board_process in _cmdline(p)), None)
            time.sleep(0.05)
        assert board is not None, "the embedded board never started"
        time.sleep(1.5)                 # the prediction in lockstep, the arming, records
        os.kill(board, signal.SIGKILL)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 1, err
    assert "Traceback" not in err, err
    rep = json.loads(out)
    assert rep["error"]["type"] == "DeviceError", rep
    # the report of a run the loss ended (the two faders': "realtime"; the 2DIY's, once
    # its first record was whole: at the top), or the error object alone
    stop = (rep.get("realtime") or rep).get("stop")
    if stop is not None:
        assert stop.startswith("device lost: ") and rep["verdict"] == "not measurable", rep
    else:
        assert set(rep) == {"error", "exit"}, rep


class _Haply2Link:
    """A lockstep emulated 2DIY behind ``write``/``in_waiting``/``read``: each write's
    replies readable at once."""

    def __init__(self, board) -> None:
        self.board, self.out = board, bytearray()

    def write(self, data):
        self.out += self.board.feed(bytes(data))
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self.out)

    def read(self, n: int = 1):
        b = bytes(self.out[:n])
        del self.out[:n]
        return b


#: Rows per record of the 2DIY's property test, and the port's calls of each kind a whole
#: run of it makes (measured: 615 writes, 610 reads).
N_2DIY, CALLS_2DIY = 120, 615


@pytest.mark.parametrize("seed", seeds(range(1, 25), kept=[1, 2, 6]))
def test_a_2diy_lost_mid_run_reports_the_records_made(seed):
    """The Haply 2DIY's port fails (a write or a read; pyserial's SerialException, the
    system's OSError or a write timeout) at a random call of a real-time run's records
    (:func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`, the board in lockstep
    in process). Before the first record is whole: the DeviceError. After it: a result,
    never an exception, ``stop`` "device lost: ...", ``error`` a DeviceError's, the
    records made counted (each per-record entry one per record made, fewer than 5),
    nothing fitted and "not measurable" (before, any loss was the error alone, the
    records made lost with it)."""
    from hapsim.emulated.haply2_board import Haply2DIYBoard
    from hapsim.lockstep import identification_plan
    from hapsim.pipeline.haply2_host import measure_felt_haply2_port
    from hapsim.scene import load_scene_nd
    rng = random.Random(seed)
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=1e-4, clock="lockstep")
    exc = rng.choice([serial.SerialException("read failed: [Errno 104] Connection reset"),
                      OSError(5, "Input/output error"),
                      serial.SerialTimeoutException("Write timeout")])
    op = rng.choice(["write", "read"])
    at = rng.randrange(1, CALLS_2DIY + 10)
    link = _FailingLink(_Haply2Link(board), op, at, exc)
    try:
        r = measure_felt_haply2_port(link, sc, "gen3", amplitude=1e-4,
                                     resolution=2.0 ** 22, samples=N_2DIY,
                                     plan=identification_plan(sc, N_2DIY),
                                     probe_wiring=False, lockstep_board=True)
    except DeviceError as err:
        assert "2DIY" in str(err), err
        assert at <= N_2DIY + 10, ("the error alone after the first record", at)
        return
    if link.calls < at:                         # the run ended before the failing call
        assert r["stop"] == "end" and r["error"] is None and r["records"] == 4
        return
    made = r["records"] + 1
    assert r["stop"].startswith("device lost: ") and "2DIY" in r["stop"], r["stop"]
    assert r["error"]["type"] == "DeviceError" and 1 <= made < 5, (r["error"], made)
    assert r["verdict"] == "not measurable" and r["within"] is None and not r["statements"]
    assert r["measured"] is None and f"after {made} of the 5 records" in r["reason"]
    for k in ("estimated", "late_ticks", "replies", "writes", "resyncs", "left", "brake"):
        assert len(r[k]) == made, (k, r[k])
    assert r["writes"] == [N_2DIY + 2] * made       # (lockstep: every record whole)


@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_hapsim_run_reports_a_2diy_lost_after_its_records_then_the_error(as_json, capsys):
    """``hapsim run --driver haply``'s report of a run whose board was lost in its third
    record (the port's 300th write fails): what the two records made counted, "stopped:
    device lost: ...", the prediction, "not measurable" and why, text or one ``--json``
    object with ``stop`` and ``error``; then the error on stderr, exit 1."""
    import argparse

    from hapsim.commands.run_haply2 import _report_lost
    from hapsim.emulated.haply2_board import Haply2DIYBoard
    from hapsim.lockstep import identification_plan
    from hapsim.pipeline.haply2_host import measure_felt_haply2_port
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=1e-4, clock="lockstep")
    link = _FailingLink(_Haply2Link(board), "write", 300,
                        serial.SerialException("write failed: [Errno 32] Broken pipe"))
    res = measure_felt_haply2_port(link, sc, "gen3", amplitude=1e-4, resolution=2.0 ** 22,
                                   samples=N_2DIY, plan=identification_plan(sc, N_2DIY),
                                   probe_wiring=False, lockstep_board=True)
    res["scheduling"] = "SCHED_OTHER (test)"
    code = _report_lost(argparse.Namespace(json=as_json), sc, res, "gen3", 1e-4, None,
                        None, None)
    out, err = capsys.readouterr()
    assert code == 1
    assert err.strip() == ("hapsim run: DeviceError: write to the 2DIY's port failed: "
                           "write failed: [Errno 32] Broken pipe"), err
    if as_json:
        rep = json.loads(out)
        assert rep["stop"] == "device lost: " + rep["error"]["message"]
        assert rep["error"]["type"] == "DeviceError" and rep["measured"] is None
        assert rep["verdict"] == "not measurable" and rep["within"] is None
        assert rep["writes"] == [N_2DIY + 2] * 2 and rep["records"] == 1
        assert rep["predicted"]["felt_stiffness"][0][0] > 0
    else:
        assert "replies read [122, 122] of [122, 122]" in out, out
        assert "stopped: device lost: write to the 2DIY's port failed" in out, out
        assert "predicted felt stiffness k [N/m]" in out and "measured felt" not in out
        assert ("verdict: not measurable: the board was lost after 2 of the 5 records"
                in out), out

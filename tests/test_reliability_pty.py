"""Reliability over a real pseudo-terminal: the faults that are about the port, and kill -9.

``hapsim run`` runs with the embedded mock (a child process on the master side of a pty)
injecting faults with ``--faults``: in this process where its report is what is tested
(``inproc.hapsim_main``: the device stays a child, beside the host), in a subprocess where
kill -9 is; the host opens the slave (through a
symbolic link that the mock re-points when the port comes back after ``vanish``). Timing
is real, so assertions are on counters and bounded timeouts only.
"""

from __future__ import annotations

import glob
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.host.telemetry import load

from inproc import hapsim_main
from test_daemon import late_tolerant_wall  # same directory (pytest prepend import mode)

#: pytest-xdist (the README command runs several workers): its module-scoped fixture is built once, on
#: one worker.
pytestmark = pytest.mark.xdist_group("test_reliability_pty")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def hapsim(*args, env=None):
    e = dict(os.environ)
    e["PYTHONPATH"] = ROOT + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    if env:
        e.update(env)
    return subprocess.Popen([sys.executable, "-m", "hapsim", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=e)


@pytest.fixture(scope="module")
def wall(tmp_path_factory):
    """The scene these real-time runs close: configs/wall.yaml with a wall that stays
    stable when a loaded machine makes FORCEs late (test_daemon.late_tolerant_wall; the
    shipped one ended such runs on a safety stop, exit 1). What is tested here is the
    run's faults, recovery and journal, not its measurement."""
    return late_tolerant_wall(tmp_path_factory.mktemp("scene"))


#: The late-tolerant wall's lateness [ticks] (test_daemon.late_tolerant_wall's ``late``):
#: stable while every force is applied at most 1 + LATE ticks after its STATE.
LATE = 10
#: Runs of run_json in all when one fails because the host answered later than that.
TRIES = 3


def _largest_lag(tel: str) -> int | None:
    """The largest tick delay a run's telemetry rows name (``seq - force_seq``, by the
    loop's own rule: :func:`hapsim.kernels.ticks.late_ticks`): how many ticks after its
    STATE the oldest force the device held was computed (PROTOCOL.md section 4); None
    without a row that names one."""
    from hapsim.kernels.ticks import late_ticks
    try:
        t = load(tel)
    except Exception:                         # (a run that kept no telemetry)
        return None
    n = t["seq"].size
    tick = np.empty(n, np.int64)
    late_ticks(t["seq"].astype(np.int64), t["force_seq"].astype(np.int64),
               t["status"].astype(np.int64), -1, False, tick, np.empty(n, bool),
               np.empty(n, bool))
    return int(tick.max()) if n and tick.max() >= 0 else None


def run_json(wall, *args):
    """``hapsim run WALL --json ARGS`` (in this process: the host's side of the port is not
    what these tests are about); its report. Every run keeps its telemetry (in a temporary
    directory unless ARGS name one) so that a run that does not exit 0 says what came
    before its end (:func:`_loop_summary`). A run that failed while the device held a
    force older than the wall is stable for (:func:`_largest_lag` beyond ``1 + LATE``),
    or that the lateness guard stopped (:mod:`hapsim.kernels.late_growth`: the host too
    late for the wall's loop), is made again, at most :data:`TRIES` runs in all: the
    tests here are of a run's faults, recovery and journal on a machine that keeps up,
    and such a run's stop is the product's answer to one that does not."""
    import shutil
    import tempfile
    own = None
    if "--telemetry" in args:
        tel = args[list(args).index("--telemetry") + 1]
    else:
        own = tempfile.mkdtemp(prefix="hapsim-rel-")
        tel = os.path.join(own, "t.npz")
        args = (*args, "--telemetry", tel)
    try:
        for attempt in range(1, TRIES + 1):
            code, out, err = hapsim_main(["run", wall, "--json", *args])
            if code == 0:
                return json.loads(out)
            # whole, in the test's captured output (pytest cuts an assertion's message:
            # a CI failure's summary once reached the log as "'lost': 2, ...")
            print(err[-1500:])
            print(json.dumps(_loop_summary(out, tel), indent=1, default=str))
            lag = _largest_lag(tel)
            guarded = "too late for the scene's loop" in out
            if not guarded and (lag is None or lag <= 1 + LATE) or attempt == TRIES:
                break
            # the wall's premise failed, not the run: the host answered later than the
            # wall is stable for (a fresh clone's CI: a force applied 36 ticks after its
            # STATE, the loop grown to 3 cm, a loss that left the handle coasting to
            # -0.139 m, a position safety stop: the product's own stop, on a machine that
            # could not keep up). Made again, the failed run's summary printed above
            print(f"run {attempt}: a force applied {lag} ticks after its STATE (the wall "
                  f"is stable to {1 + LATE}{'; the lateness guard stopped it' if guarded else ''}"
                  f"): the machine's load; made again")
        assert code == 0, (err[-1500:], _loop_summary(out, tel),
                           f"largest lag {_largest_lag(tel)} ticks")
    finally:
        if own is not None:       # (its summary is in the message: nothing left in /tmp)
            shutil.rmtree(own, ignore_errors=True)


def _loop_summary(out: str, telemetry: str | None = None) -> dict | str:
    """What ended a run (its report's stop reason, faults, losses, the device's counters)
    and, from its telemetry, what the device did before: the message of a run that did
    not exit 0.

    Two safety stops on the late-tolerant wall (-0.176 m with no fault, stop 62; -0.231 m
    after a vanished port, stop 61) were seen once each in CI and not in 95 runs here
    beside CPU-bound processes; the coast they need (the hand at 0.1 kg, 0.5 N s/m, left
    by the 50 ms watchdog) is 0.9 m/s, more than the wall's forces give. The summary holds
    what tells a host stall (the device time's largest step, the longest stretch with no
    new FORCE applied, watchdog ticks) from a loop that grew (the largest force, the
    position's extremes) and the last rows. The first such summary (stop 78, -0.139 m
    after one loss) showed a loop that grew: the host answered 14-36 ticks after each
    STATE (:func:`_largest_lag`), the wall is stable to 11.
    """
    try:
        lp = json.loads(out)["loop"]
    except (ValueError, KeyError, TypeError):
        return out[-2000:]
    summary = {k: lp.get(k) for k in ("stop_reason", "faults", "safety_stop", "lost",
                                      "recovered", "ticks", "overruns", "late", "missed",
                                      "skipped", "stale", "v_max", "f_max", "energy_max_j",
                                      "scheduling", "loop", "turnaround_us",
                                      "safety_context")}
    summary["mock"] = {k: (lp.get("mock") or {}).get(k)
                       for k in ("ticks", "forces_rx", "late", "watchdog_trips", "overruns",
                                 "stale", "clamped")}
    summary["last_events"] = (lp.get("events") or [])[-8:]
    try:
        t = load(telemetry) if telemetry else None
    except Exception as exc:                  # a run that lost its telemetry says so
        summary["telemetry"] = f"unreadable: {exc!r}"
        t = None
    if t is not None and t["time"].size:
        x, f, tt, fs = t["position"], t["force"], t["time"], t["force_seq"]
        steps = np.diff(tt)
        held = np.flatnonzero(np.diff(fs) != 0)
        gaps = np.diff(np.concatenate(([-1], held, [fs.size - 1])))
        summary["telemetry"] = {
            "rows": int(tt.size), "device_time_s": [float(tt[0]), float(tt[-1])],
            "largest_step_s": (float(steps.max()), int(steps.argmax())) if steps.size else None,
            "longest_no_new_force_rows": int(gaps.max()),
            "watchdog_rows": int(np.count_nonzero(t["status"] & 0x0002)),
            "overrun_rows": int(np.count_nonzero(t["status"] & 0x0020)),
            "late_rows": int(np.count_nonzero(t["late"])),
            "x_min_max": [float(x.min()), int(x.argmin()), float(x.max()), int(x.argmax())],
            "f_abs_max": [float(np.abs(f).max()), int(np.abs(f).argmax())],
            "last_rows(t,x,f,seq,force_seq,late,status)": [
                [round(float(tt[i]), 6), round(float(x[i]), 6), round(float(f[i]), 4),
                 int(t["seq"][i]), int(fs[i]), int(t["late"][i]), int(t["status"][i])]
                for i in range(max(tt.size - 12, 0), tt.size)]}
    return summary


def test_port_vanishes_and_comes_back_over_a_pty(wall):
    rep = run_json(wall, "--duration", "1.5", "--faults", "vanish@400:300ms", "--fault-seed", "1")
    lp = rep["loop"]
    assert lp["lost"] >= 1 and lp["recovered"] == lp["lost"]
    assert lp["ticks"] == lp["requested"] == 1500 and lp["stop_reason"] == "duration"
    assert any("port failed" in e.get("reason", "") for e in lp["events"])
    # the scene restarted at the handle of the new session, not at a STATE the device sent
    # before it took the CONFIG (2 of 12 runs did when the mock restarted its plant at
    # x0 = 5 mm at each CONFIG: 0.105 m, a position safety stop). The mock now carries its
    # handle across CONFIGs (hapsim.emulated.mock, 'One handle'), so both sessions' STATEs
    # are where the handle is; test_reliability's
    # test_recovery_resumes_at_the_handle_of_the_new_session checks the seq-0 STATE is the
    # one taken, with that race made certain. Here: every recovery (under load a run once
    # lost and recovered 7 times in the vanish's 300 ms) at a handle inside the bound
    xs = [e["x"] for e in lp["events"] if e["event"] == "recovered"]
    assert xs and all(abs(x) < 0.1 for x in xs), xs
    assert lp["quiesced"] and lp["earlier_session"] == 0
    mk = lp["mock"]
    assert [e["name"] for e in mk["fault_events"]] == ["vanish"]
    # no FORCE reached the device while its port was gone: its watchdog zeroed the force
    assert mk["totals"]["watchdog_trips"] > 0 and mk["totals"]["configs"] >= 2
    assert mk["saw_stop"] and mk["last_applied"] == 0.0


def test_stall_and_reset_over_a_pty(wall):
    rep = run_json(wall, "--duration", "2", "--faults", "stall@300:300ms,reset@1200",
                   "--fault-seed", "2")
    lp = rep["loop"]
    mk = lp["mock"]
    assert [e["name"] for e in mk["fault_events"]] == ["stall", "reset"]
    assert lp["lost"] >= 2 and lp["recovered"] == lp["lost"]
    assert lp["ticks"] == 2000 and mk["totals"]["watchdog_trips"] > 0
    assert mk["saw_stop"] and mk["last_applied"] == 0.0


def test_wire_faults_over_a_pty_are_counted(wall):
    rep = run_json(wall, "--duration", "1.5", "--faults",
                   "drop=0.01,corrupt=0.01,garbage=0.005,dup=0.005,reorder=0.005,spike=0.002:5ms",
                   "--fault-seed", "3")
    lp = rep["loop"]
    inj = lp["fault_plan"]["injected"]
    dec = lp["decoder"]
    assert inj["drop"] > 0 and inj["corrupt"] > 0
    assert dec["bad_crc"] + dec["bad_cobs"] >= inj["corrupt"] // 2
    assert lp["missed"] > 0 and lp["ticks"] == 1500


def test_mock_vanish_needs_a_link(capsys):
    assert main(["mock", "--faults", "vanish@10:10ms"]) == 2
    assert "--link" in capsys.readouterr().err


def test_kill_9_loses_at_most_100_ms_of_telemetry(tmp_path, wall):
    path = str(tmp_path / "t.hst")
    p = hapsim("run", wall, "--duration", "30", "--telemetry", path,
               env={"TMPDIR": str(tmp_path)})
    end = time.monotonic() + 90
    rows = 0
    while rows < 1500 and time.monotonic() < end and p.poll() is None:
        time.sleep(0.1)
        if os.path.exists(path):
            rows = load(path)["seq"].size
    assert rows >= 1500, p.stderr.read() if p.poll() is not None else "too slow"
    p.send_signal(signal.SIGKILL)
    p.wait(10)
    # the mock child sees the port close (EIO) and reports how many STATEs it sent
    report = None
    end = time.monotonic() + 20
    while report is None and time.monotonic() < end:
        for f in glob.glob(str(tmp_path / "hapsim-mock-*.json")):
            report = json.load(open(f))
        time.sleep(0.1)
    assert report is not None and report["end"] == "host closed"
    info = {}
    cols = load(path, info=info)
    n = cols["seq"].size
    assert n >= rows and info["chunks"] >= 1
    # every complete chunk, in order (STATEs skipped by the backlog policy, when two were
    # waiting at once on a loaded machine, leave gaps in seq; no row is out of order).
    # A loss and its recovery, journaled (a mock starved 50 ms on a loaded machine: seen
    # beside a CPU-bound process), re-arms the device, whose seq starts again at 0 there
    seq = cols["seq"]
    again = np.flatnonzero(np.diff(seq) < 1) + 1
    recovered = [e for e in info["events"] if e["event"] == "recovered"]
    assert seq[0] == 0 and len(again) == len(recovered) and not np.any(seq[again]), (
        again, info["events"])
    # STATEs the mock sent after the last row on disk: at most 100 ms at 1 kHz
    lost = report["ticks"] - (int(cols["seq"][-1]) + 1)
    assert 0 <= lost <= 100, (report["ticks"], n)
    print(f"kill -9: {report['ticks']} STATEs sent, {n} rows on disk, {lost} lost")
    p.stdout.close()
    p.stderr.close()


def _both_faults_recovered(events) -> bool:
    """The reset's loss (the device's HELLO), then the stall's ("no STATE"), each followed
    by a recovery. A loaded machine may add a loss of its own (a 50 ms silence before the
    reset, once, a suite on three workers beside other work): it is journaled too."""
    want = ["HELLO", "no STATE"]
    lost = False
    for e in events:
        if e["event"] == "lost" and want and want[0] in e["reason"]:
            lost = True
        elif e["event"] == "recovered" and lost:
            want.pop(0)
            lost = False
    return not want


def test_kill_9_keeps_the_fault_history(tmp_path, wall):
    """A reset and a stall, then kill -9: the journal holds the losses and recoveries (the
    events, and the flagged restart rows), not only the samples."""
    from hapsim.host.telemetry import FLAG_LOST
    path = str(tmp_path / "t.hst")
    p = hapsim("run", wall, "--duration", "0", "--telemetry", path, "--faults",
               "reset@300,stall@800:200ms", env={"TMPDIR": str(tmp_path)})
    end = time.monotonic() + 90
    info = {}
    while time.monotonic() < end and p.poll() is None:
        time.sleep(0.1)
        if os.path.exists(path):
            info = {}
            rows = load(path, info=info)["seq"].size
            if rows >= 1500 and _both_faults_recovered(info["events"]):
                break
    assert p.poll() is None, p.stderr.read()
    p.send_signal(signal.SIGKILL)
    p.wait(10)
    p.stdout.close()
    p.stderr.close()
    info = {}
    cols = load(path, info=info)
    events = info["events"]
    seq = [e["event"] for e in events if e["event"] in ("lost", "recovered")]
    # each loss then its recovery (the last loss may be pending at the kill)
    assert seq == ["lost", "recovered"] * (len(seq) // 2) + ["lost"] * (len(seq) % 2), seq
    assert _both_faults_recovered(events), events
    restarts = np.flatnonzero(cols["flags"] & FLAG_LOST).tolist()
    recovered = [e["sample"] for e in events if e["event"] == "recovered"]
    assert restarts[:len(recovered)] == recovered


@pytest.mark.parametrize("ext", [".npz", ".csv"])
def test_journal_beside_npz_csv_removed_after_export(tmp_path, ext, wall):
    path = str(tmp_path / f"t{ext}")
    rep = run_json(wall, "--duration", "0.5", "--telemetry", path)
    assert rep["telemetry"]["samples"] == 500 and load(path)["seq"].size == 500
    assert not os.path.exists(path + ".hst")


def test_standalone_mock_with_faults_behind_a_link(tmp_path, wall):
    """``hapsim mock --faults ... --link PATH`` as a separate device; ``run --port PATH``."""
    link = str(tmp_path / "port")
    mock = hapsim("mock", "--faults", "vanish@300:300ms,drop=0.01", "--fault-seed", "4",
                  "--link", link, "--report", str(tmp_path / "mock.json"))
    try:
        first = mock.stdout.readline()
        assert first.strip() == f"PORT {link}" and os.path.islink(link)
        rep = run_json(wall, "--port", link, "--duration", "1.5")
        lp = rep["loop"]
        assert lp["lost"] >= 1 and lp["recovered"] == lp["lost"] and lp["ticks"] == 1500
        assert any(e["event"] == "lost" and "last frames" not in e and e["last_frames"]
                   for e in lp["events"])
    finally:
        mock.send_signal(signal.SIGTERM)       # with faults, STOP does not end the mock
        mock.communicate(timeout=20)
    seen = json.load(open(tmp_path / "mock.json"))
    assert [e["name"] for e in seen["fault_events"]] == ["vanish"]
    assert seen["faults_injected"]["drop"] > 0 and seen["last_applied"] == 0.0


def test_a_link_that_holds_every_answer_late_is_stopped_with_stop_not_braking():
    """``configs/first_wall.yaml`` on a link that holds a fifth of the device's frames
    30 ms (``spike=0.2:30ms``): from its fifth STATE on every answer comes after its tick,
    and the device names one FORCE until its watchdog (docs/reliability.md, "A hold that
    never ends"). The lateness guard counts the hold the device is in and stops the run
    inside it, within the position bound; the device having taken none of the host's
    answers, no braking FORCE is sent (it would be as late), only the zero FORCE and STOP.
    Before 2026-11-29 the run went on until the handle reached the position bound
    (-0.1055 m), then sent 73 braking FORCEs the device ignored."""
    code, out, err = hapsim_main(["run", "configs/first_wall.yaml", "--duration", "0.3",
                                  "--faults", "spike=0.2:30ms"])
    assert code == 1, err[-1500:]
    assert ("no braking after the stop: the device applied none of the host's FORCEs "
            "(its last STATE named a FORCE more than the delay + 3 ticks old): STOP sent "
            "at once") in out, out[-1500:]
    code, out, err = hapsim_main(["run", "configs/first_wall.yaml", "--duration", "0.3",
                                  "--faults", "spike=0.2:30ms", "--json"])
    assert code == 1, err[-1500:]
    lp = json.loads(out)["loop"]
    assert "too late for the scene's loop" in lp["stop_reason"], lp["stop_reason"]
    assert lp["brake"]["ended"] == "ignored" and lp["brake"]["periods"] == 0, lp["brake"]
    assert lp["mock"]["saw_stop"] and lp["mock"]["last_host_message"] == "Stop"
    ctx = lp["safety_context"]
    assert abs(ctx["position_last_m"]) < lp["safety"]["position_limit"], ctx

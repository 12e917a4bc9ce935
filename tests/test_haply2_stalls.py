"""The 2DIY's real-time loop through host stalls (issue 29 item 2): a stall is a stall,
never a burst of catch-up writes nor by itself a re-synchronisation; with 1 byte in 200
lost each way the re-synchronisations are bounded by the faults, the joints never leave
the workspace, and a record with a stall is cut there on a board that keeps its own time
(its stretches measured: test_haply2_cuts).

The board is the emulated firmware V1.5 in process: on the wall clock (its own time: the
joints move over a host stall under the torque held, replies ready when the board's pass
made them), or in lockstep (one period per write), named so in the test's name. The host's
stalls are injected by sleeping inside a write."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hapsim.pipeline import haply2_host as host
from hapsim.pipeline import haply2_record as record
from hapsim.emulated.links import BoardLink
from hapsim.emulated.haply2_board import Haply2DIYBoard
from hapsim.emulated.driver_mock import ByteFaults
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.scene import load_scene_nd

WALL = Path(__file__).resolve().parent.parent / "configs" / "pantograph_wall.yaml"
#: The workspace the joints must stay in [rad] around the rest joints: the bound a 30 ms
#: host stall (the longest injected) at the board's torque clamp puts on this joint, 1/2
#: (0.123 N m / 2e-4 kg m^2) (0.03 s)^2 = 0.28 rad, times a margin of 1.8; the storm of
#: the issue turned a joint 1 to 12.5 rad.
WORKSPACE_RAD = 0.5


class StallingLink(BoardLink):
    """The emulated board behind ``write``/``in_waiting``/``read``, host bytes through
    ``rx``, replies through ``tx`` (:class:`hapsim.emulated.links.BoardLink`); the host
    stalls ``stalls[n]`` seconds inside its ``n``-th write of a record's loop (a sleep:
    the host process descheduled). ``times``: perf_counter() of each 10-byte write;
    ``truth``: the board's joints after each."""

    def __init__(self, board, stalls, rx=None, tx=None):
        super().__init__(board, rx, tx)
        self.stalls = dict(stalls)
        self.times = []

    def write(self, data):
        if len(data) == 10:
            self.times.append(time.perf_counter())
            s = self.stalls.get(len(self.times))
            if s:
                time.sleep(s)
        return super().write(data)


class WallLink:
    """The emulated board on the wall clock behind ``write``/``in_waiting``/``read``: each
    write fed at its time (``perf_counter`` since the link was made), its replies readable
    from the board's ``ready_at`` on; host bytes through ``rx``, replies through ``tx``;
    the host stalls ``stalls[n]`` seconds inside its ``n``-th 10-byte write."""

    def __init__(self, board, stalls, rx=None, tx=None):
        self.board, self.stalls = board, dict(stalls)
        self.rx = rx or (lambda b: b)
        self.tx = tx or (lambda b: b)
        self.t0 = time.perf_counter()
        self.queue, self.out = [], bytearray()
        self.times = []

    def _now(self):
        return time.perf_counter() - self.t0

    def write(self, data):
        if len(data) == 10:
            self.times.append(time.perf_counter())
            s = self.stalls.get(len(self.times))
            if s:
                time.sleep(s)
        rep = self.board.feed(self.rx(bytes(data)), self._now())
        if rep:
            self.queue.append((self.board.ready_at, self.tx(rep)))
        return len(data)

    def _release(self):
        now = self._now()
        while self.queue and self.queue[0][0] <= now:
            self.out += self.queue.pop(0)[1]

    @property
    def in_waiting(self):
        self._release()
        return len(self.out)

    def read(self, n):
        self._release()
        b = bytes(self.out[:n])
        del self.out[:n]
        return b


def _wall_record(seed, loss, N=300):
    sc = load_scene_nd(WALL)
    rng = np.random.default_rng(seed)
    at = rng.choice(np.arange(10, N - 10), size=int(rng.integers(3, 6)), replace=False)
    stalls = {int(a): float(rng.uniform(0.006, 0.030)) for a in at}
    board = Haply2DIYBoard(sc, "gen3", amplitude=1e-4, clock="wall")
    f = ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed})
    link = WallLink(board, stalls, f.rx, f.tx)
    rec = record.record_realtime(link, Haply2DIY("gen3"), sc, N)
    # the board run to the end of the record (its joints under the zero torque left)
    board.run_to(link._now())
    return sc, rec, link, f, stalls


@pytest.mark.parametrize("seed", [11])
def test_host_stalls_on_the_wall_clock_no_resync(seed):
    """The board on its own clock holds the torque over each 6-30 ms host stall and the
    joints move meanwhile: not one re-synchronisation (a late reply is a late sample),
    every stall counted, no burst after one (three consecutive writes span half a period),
    the board left at zero torque."""
    sc, rec, link, f, stalls = _wall_record(seed, 0.0)
    assert rec["resyncs"] == 0 and rec["bad_setups"] == 0, rec["decoder"]
    assert rec["stalled"].sum() >= len(stalls)
    w = np.asarray(link.times)[1:-1]
    assert np.min(w[2:] - w[:-2]) >= sc.period / 2
    assert link.board.settles_on() == 0.0


def test_wall_clock_beside_two_cpu_bound_processes_no_storm():
    """Beside two CPU-bound processes (the suite's own machine, loaded), the board on its
    own clock, host stalls, no byte lost: no storm of re-synchronisations (at most one per
    ten stalls counted), zero torque at the end."""
    from load import burners_for  # same directory: the other xdist workers count as busy
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(burners_for(2))]
    try:
        sc, rec, link, f, stalls = _wall_record(13, 0.0, N=200)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    # no storm: with no byte lost, a re-synchronisation can only follow a host stall
    # whose late reply the decoder took for garbage, and none feeds another (before: 5
    # desyncs in 200 ticks with the fixed 2-degree step check; now 0 or 1 measured; zero
    # is the goal, not met beside the hogs: docs/drivers.md)
    assert rec["resyncs"] <= max(1, rec["stalled"].sum() // 10), (rec["resyncs"],
                                                                  rec["decoder"])
    # (the joints' excursion is not asserted beside the hogs: their stalls are the
    # machine's, longer than the ones injected, and the board has no watchdog: 0.61 rad
    # measured once, the finding that stays open, docs/drivers.md)
    assert link.board.settles_on() == 0.0


def test_wall_clock_byte_loss_bounded_resyncs():
    """The board on its own clock, 1 byte in 200 lost each way, host stalls: the
    re-synchronisations no more than the bytes lost, the board left at zero torque.
    (The joints' excursion is not asserted here: a host byte lost shifts the board's
    parser, which may take a garbage torque, clamped to 0.123 N m, and hold it until the
    host sees the board out of step, SILENT_S at most; on this light joint, 2e-4 kg m^2,
    that is 12 rad/s, and the set-up re-anchors the angle the host reads. Measured 2 to
    18 rad of true excursion: docs/drivers.md, 'Real timing, every driver'.)"""
    from hapsim.drivers.haply2 import JOINT_PORTS
    sc, rec, link, f, stalls = _wall_record(7, 1 / 200, N=200)
    lost = f.counts["drop_rx"] + f.counts["drop_tx"]
    assert lost > 0 and rec["resyncs"] <= lost, (rec["resyncs"], f.counts)
    # zero on the joints' motor ports: a garbage set-up can leave a torque on port 3 or 4,
    # wired to nothing on a 2DIY (2.4e-38 N m seen there in CI; the lockstep test below)
    assert link.board.settles_on(JOINT_PORTS) == 0.0


def _record(seed, loss, N=300):
    sc = load_scene_nd(WALL)
    rng = np.random.default_rng(seed)
    # 3 to 5 host stalls of 6 to 30 ms at random writes of the loop
    at = rng.choice(np.arange(10, N - 10), size=int(rng.integers(3, 6)), replace=False)
    stalls = {int(a): float(rng.uniform(0.006, 0.030)) for a in at}
    board = Haply2DIYBoard(sc, "gen3", amplitude=1e-4, clock="lockstep")
    f = ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed})
    link = StallingLink(board, stalls, f.rx, f.tx)
    # the board runs in this process (no plant to load, record_realtime's ``running``):
    # the first arming's answers awaited REPLY_WAIT_S, not ARM_TIMEOUT. Seed 5 lost the
    # answer to its first set-up and waited the whole 10 s of a board process starting
    # (11.6 s of its 11.6 s wall, 1.8 s now); over seeds 0-13 (1 in 200 bytes lost, 150
    # rows) every claim of test_host_stalls_and_byte_loss_lockstep_bounded_resyncs still
    # held, the re-synchronisations' time at most 0.16 of its bound (seed 3)
    rec = record.record_realtime(link, Haply2DIY("gen3"), sc, N, lockstep_board=True,
                                 running=True)
    q0 = np.asarray(sc.device.joints, float)
    return sc, rec, link, f, q0, stalls


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_host_stalls_lockstep_no_burst_no_resync(seed):
    """No fault, only host stalls of 6-30 ms: not one re-synchronisation, every stall
    counted, no burst: any three consecutive writes of the loop span at least half a
    period (exact, from the loop's rule: tick k + 1 begins at most T/2 after its deadline
    or the clock goes on from it, write k comes before it, and write k + 2 not before its
    own deadline, a period after tick k + 1's), the joints within the workspace, the
    board left at zero torque."""
    sc, rec, link, f, q0, stalls = _record(seed, 0.0)
    T = sc.period
    assert rec["resyncs"] == 0 and rec["bad_setups"] == 0 and rec["decoder"]["desync"] == 0
    assert rec["stalled"].sum() >= len(stalls)
    w = np.asarray(link.times)[1:-1]            # the loop's (not the arming's, the end's)
    assert np.min(w[2:] - w[:-2]) >= T / 2, np.min(w[2:] - w[:-2]) / T
    assert np.abs(np.asarray(link.truth) - q0).max() <= WORKSPACE_RAD
    assert link.board.settles_on() == 0.0


@pytest.mark.parametrize("seed", [4, 5])
def test_host_stalls_and_byte_loss_lockstep_bounded_resyncs(seed):
    """1 byte in 200 lost each way and host stalls: each re-synchronisation answers a
    fault (no more of them than bytes lost, in either direction), each takes at most the
    loop's stated waits (ARM_TRIES set-ups, each waiting REARM_WAIT_S, QUIET_S and
    REPLY_WAIT_S), the joints within the workspace, the board left at zero torque."""
    sc, rec, link, f, q0, stalls = _record(seed, 1 / 200, N=150)
    lost = f.counts["drop_rx"] + f.counts["drop_tx"]
    assert lost > 0
    assert rec["resyncs"] <= lost, (rec["resyncs"], f.counts)
    per = record.ARM_TRIES * (record.REARM_WAIT_S + record.QUIET_S + record.REPLY_WAIT_S)
    assert rec["resync_s"] <= per * max(rec["resyncs"], 1)
    assert np.abs(np.asarray(link.truth) - q0).max() <= WORKSPACE_RAD
    # zero torque on the joints' motor ports (1 and 2). A garbage set-up the stream made
    # can give port 3 or 4 a motor address and a garbage write a torque there, which no
    # set-up of the 2DIY's (motors 1 and 2) clears (the firmware keeps a port's duty when
    # a set-up moves its address: hapsim.emulated.haply_firmware.CommandDecoder); nothing is wired
    # to those ports on a 2DIY (seed 4 with the 32-zero re-arming: -1.8e-32 on port 4)
    from hapsim.drivers.haply2 import JOINT_PORTS
    assert link.board.settles_on(JOINT_PORTS) == 0.0


def test_a_stalled_record_is_cut_at_the_stall_on_a_board_with_its_own_clock(monkeypatch):
    """A host stall in a record: on a board that keeps its own time the board held a
    torque over more than a period, so the record is cut there (rows s - 1 .. s + d + 1:
    the stall's held torque and the torques in flight after it,
    :func:`hapsim.pipeline.haply2_host.usable_rows`) and its two stretches, each a free
    response of the loop, are fitted jointly with the other records': "within", the
    stalls counted (before, a stall made the run "not measurable"). The records are made
    by the lockstep board with a stall flagged in each (the loop itself undisturbed: what
    is tested is the cut). The host's clock is simulated: on a loaded machine its own
    stalls cut the short records further, until too few rows were left to state the
    felt pair ("not measurable" in a loaded suite), which is not what is tested here."""
    import types
    from hapsim.lockstep import identification_plan
    clk = SimClock()
    monkeypatch.setattr(record, "time", types.SimpleNamespace(
        perf_counter=clk.now, monotonic=clk.now, sleep=clk.sleep))
    sc = load_scene_nd(WALL)
    N = 40
    real = host.record_realtime

    def stalled(*a, **k):
        rec = real(*a, **k)
        rec["stalled"][N // 2] = True
        return rec
    monkeypatch.setattr(host, "record_realtime", stalled)
    board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=1e-4, clock="lockstep")
    link = StallingLink(board, {})
    r = host.measure_felt_haply2_port(link, sc, "gen3", amplitude=1e-4,
                                      resolution=2.0 ** 22, samples=N,
                                      plan=identification_plan(sc, N), probe_wiring=False)
    d = int(sc.device.delay)
    # each stall cuts d + 3 rows: the one flagged in each of the five records, the host's
    # clock simulated (no stall of its own)
    assert r["stalls"] == [1] * 5
    for u in r["usable"]:
        assert u == N - (d + 3), r["usable"]
    assert r["within"] is True, (r["verdict"], r["reason"], r["deviation"])


# ------------------------------------------- the whole measurement on the board's own clock

class SimClock:
    """Simulated time for the host and the board alike: each reading of the clock moves it
    1 us on (the host's own work between two readings), a sleep by its length. The board
    keeps its own time (``clock="wall"``: the torques held over the real intervals between
    writes, replies ready when its pass made them); only the time is simulated, so the run
    is the same on any machine at any load."""

    def __init__(self):
        self.t = 0.0

    def now(self):
        self.t += 1e-6
        return self.t

    def sleep(self, d):
        self.t += max(float(d), 0.0)


class SimLink:
    """The board on its own clock behind ``write``/``in_waiting``/``read``, on a
    :class:`SimClock`: each write fed at its time, its replies readable from the board's
    ``ready_at``; host bytes through ``rx``, replies through ``tx``."""

    def __init__(self, board, clock, rx=None, tx=None):
        self.board, self.clock = board, clock
        self.rx = rx or (lambda b: b)
        self.tx = tx or (lambda b: b)
        self.queue, self.out = [], bytearray()

    def write(self, data):
        rep = self.board.feed(self.rx(bytes(data)), self.clock.t)
        if rep:
            self.queue.append((self.board.ready_at, self.tx(rep)))
        return len(data)

    def _release(self):
        while self.queue and self.queue[0][0] <= self.clock.t:
            self.out += self.queue.pop(0)[1]

    @property
    def in_waiting(self):
        self._release()
        return len(self.out)

    def read(self, n):
        self._release()
        b = bytes(self.out[:n])
        del self.out[:n]
        return b


def _sim_measure(monkeypatch, loss=0.0, seed=0, N=200):
    import types
    from hapsim.lockstep import identification_plan
    clk = SimClock()
    monkeypatch.setattr(record, "time", types.SimpleNamespace(
        perf_counter=clk.now, monotonic=clk.now, sleep=clk.sleep))
    sc = load_scene_nd(WALL)
    board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=1e-4, clock="wall")
    f = ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed})
    link = SimLink(board, clk, f.rx, f.tx)
    r = host.measure_felt_haply2_port(link, sc, "gen3", amplitude=1e-4,
                                      resolution=2.0 ** 22, samples=N,
                                      plan=identification_plan(sc, N), probe_wiring=False)
    return r, board, f


def test_own_clock_punctual_host_measures_within_simulated_time(monkeypatch):
    """The 2DIY's whole measurement (five records) closed on the board's own clock, the
    host punctual (simulated time): no stall, no estimated sample, no re-synchronisation,
    and the verdict is "within" (or "partly within", a damping not stated): measured =
    predicted within the stated uncertainty, with
    the board holding each torque over the real interval to the next write (its own
    delay of one period, as the scene states). The joints stay in the measurement's
    envelope and the board is left at zero torque."""
    r, board, _ = _sim_measure(monkeypatch)
    assert sum(r["stalls"]) == sum(r["estimated"]) == sum(r["resyncs"]) == 0
    # the wire's term over the error box (hapsim.analysis.wire_box) may leave a damping
    # unstated ("partly within"); the stiffness is stated, and nothing differs
    assert r["verdict"] in ("within", "partly within") and r["within"] is True, \
        (r["reason"], r["deviation"])
    assert all(s["quantity"] == "felt_damping" for s in r["statements"]
               if s["verdict"] == "not measurable")
    assert r["uncertainty"]["felt_stiffness"] is not None
    for k in ("felt_stiffness", "felt_damping"):
        if r["uncertainty"][k] is not None:
            assert r["deviation"][k] <= r["uncertainty"][k]
    assert board.excursion <= record.ENVELOPE_RAD
    assert board.settles_on() == 0.0


@pytest.mark.parametrize("seed", [1, 3, 8])
def test_own_clock_byte_loss_keeps_the_joints_in_the_workspace_simulated_time(
        monkeypatch, seed):
    """1 byte in 200 lost each way, the board on its own clock, the host punctual
    (simulated time): every re-synchronisation waits for the board's evidence at most
    REARM_REPLY_S and is sent again otherwise, so a garbage torque a shifted parser took is
    held no longer than the host's silence rule and one re-arming's bound: the joints'
    true excursion stays within the measurement's workspace (before these rules: up to
    16.8 rad, a corrupted re-arming waited 0.25 s with the clamp's torque held). The
    records are cut at each re-synchronisation and the run is never "differs" (a correct
    loop): "within" as far as the stretches state, or "not measurable" with its reason."""
    from tolerance import measured
    r, board, f = _sim_measure(monkeypatch, 1 / 200, seed)
    assert f.counts["drop_rx"] + f.counts["drop_tx"] > 0
    assert sum(r["resyncs"]) > 0 and r["verdict"] != "differs", (r["reason"],
                                                                 r["deviation"])
    assert r["within"] is True or r["reason"]
    # worst true excursion measured over seeds 1-10 of this run: 0.137 rad (seed 8); a
    # margin of 3 for another BLAS's round-off through the fit-free loop (the board's
    # plant and the host's arithmetic are deterministic here); both under WORKSPACE_RAD
    assert board.excursion <= min(measured(0.137, 3.0), host.WORKSPACE_RAD)


def test_wall_clock_closed_loop_beside_two_cpu_bound_processes():
    """The whole measurement on the real wall clock (the board in process, each write fed
    at its time), two CPU-bound processes beside it, no fault: not one
    re-synchronisation (a late reply is a late sample), the joints' true excursion within
    the workspace, the board left at zero torque, and a verdict that is never wrong: a
    run the host kept in time says "within"; one that left the envelope says "not
    measurable" and names that; one whose host stalled or zeroed a tick is cut there and
    measured on its stretches, never "differs" (on the board's own clock a departure
    beyond the stated uncertainty is "not measurable", named: the host's write timing is
    not in it) (no wall-clock timing is asserted: which of these depends on the
    machine)."""
    from hapsim.lockstep import identification_plan
    from load import burners_for  # same directory: the other xdist workers count as busy
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(burners_for(2))]
    try:
        sc = load_scene_nd(WALL)
        N = 120
        board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=1e-4, clock="wall")
        link = WallLink(board, {})
        r = host.measure_felt_haply2_port(link, sc, "gen3", amplitude=1e-4,
                                          resolution=2.0 ** 22, samples=N,
                                          plan=identification_plan(sc, N),
                                          probe_wiring=False)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    assert sum(r["resyncs"]) == 0, r["reason"]
    assert board.excursion <= host.WORKSPACE_RAD
    assert board.settles_on() == 0.0
    late = sum(r["stalls"]) + sum(r["held_zero"]) + sum(v >= 0 for v in r["left"])
    if any(v >= 0 for v in r["left"]):
        assert r["verdict"] == "not measurable" and "envelope" in r["reason"], r["reason"]
    elif late:
        assert r["verdict"] != "differs", r["verdict"]
        assert r["within"] is True or any(w in r["reason"] for w in (
            "own time", "too few", "depth", "clamp", "may move",
            "no felt matrices")), r["reason"]
    elif r["verdict"] == "not measurable":
        # kept in time by the counters above, and yet the readings' error box may move a
        # statement beyond the measurable (its term 3e4-1.4e5 relative on some records
        # beside two busy processes: 4 of 12 runs of this test on d6cb5c5, 1 of 6 on
        # fa4b2ee). Its cause, found: the fit took a noise pair for a rendered one where
        # its |z| outranked a pair of the loop (hapsim.analysis.wire_box, module notes),
        # now never (pencil.MODE_FLOOR). What stays is real: these counters do not count
        # the holds cut more than half a period off (write_holds.HOLD_CUT_PERIODS), and
        # stretches cut short may not determine a rendered pair within the errors (the
        # box's term then inf; at the records already: no felt matrices): said so, with
        # the box named, never "differs". Nor do they count the link's own latency,
        # which the host does not see: a departure beyond the stated uncertainty that a
        # latency varying by LINK_JITTER_S between writes could make is "not measurable"
        # on a board keeping its own time, named so (a fresh clone's CI at f7388078:
        # felt damping 0.325 off, no stall, no zeroed tick, no resync)
        assert ("may move" in r["reason"] and "box" in r["reason"]
                or "no felt matrices" in r["reason"]
                or "own time" in r["reason"] and "latency" in r["reason"]), r["reason"]
    else:
        assert r["verdict"] in ("within", "partly within") and r["within"] is True, \
            (r["reason"], r["deviation"])

"""The FireFader's two faders felt in real time (issue 30 item 3,
hapsim.pipeline.faders_run): the host's loop over one board carrying both faders, the
board's two-fader firmware loop (hapsim.emulated.firefader_board, fader B), the
measurement and its verdict.

- In lockstep, asked for by name (the board in-process, one period per host write): the
  real-time path's record, replayed through independent device models (each fader its
  own exact hold and sub-sample delay, hapsim.lockstep_ports.PortDevice, started at the hand's
  start and driven by the record's forces), gives the record's pot readings back count
  for count, and its forces are the links' law on the readings (the port matrices of
  hapsim.analysis.ports, not the host's code) rounded to the protocol's counts; over
  seeded random two-fader scenes.
- On the board's own clock (a child process behind a pty) beside two CPU-bound processes:
  the run ends by its duration or by the host's own lateness, leaves both faders at zero
  force, and makes a verdict on both faders.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from hapsim.drivers import firefader as ff
from hapsim.pipeline.faders_run import LockstepBoardLink
from hapsim.scene import Device, Link, Mass, ScenePorts
from test_wallclock import two_cpu_hogs  # noqa: F401  (the fixture, as that file's tests)


def random_faders(rng) -> ScenePorts:
    """A random two-fader scene at 250 Hz: each fader's own mass 0.03..0.08 kg and
    friction 0.05..0.2 N s/m, the FireFader's sub-sample delay 0.725, an anchor spring
    of 8..20 N/m per fader and a coupling of 10..35 N/m (dampers 0..0.15 N s/m): forces
    within the 0.38 N limit over the 4 mm excitation."""
    names = ("fader_a", "fader_b")
    masses = tuple(Mass(n, "port") for n in names) + (Mass("anchor", "ground"),)
    links = tuple(Link(f"spring_{n[-1]}", "spring_damper", n, "anchor",
                       float(rng.uniform(8.0, 20.0)), float(rng.uniform(0.0, 0.15)))
                  for n in names) + (
        Link("coupling", "spring_damper", *names, float(rng.uniform(10.0, 35.0)),
             float(rng.uniform(0.0, 0.15))),)
    devices = tuple((n, Device(mass=float(rng.uniform(0.03, 0.08)),
                               friction=float(rng.uniform(0.05, 0.2)), delay=0.725,
                               force_limit=0.38, protocol="firefader")) for n in names)
    return ScenePorts(rate_hz=250.0, masses=masses, links=links, devices=devices)


#: The board in-process on its lockstep clock (each write one tick): the package's own.
InProcessLink = LockstepBoardLink


@pytest.mark.parametrize("seed", range(4))
def test_the_records_replayed_through_each_faders_own_model_give_them_back(seed):
    """Lockstep by name: the host's real-time path (record_faders) over the two-fader
    board in-process. Replayed: each fader's readings are its own lockstep device model
    (PortDevice: exact hold, split at 0.725) started at the hand's start, driven by the
    forces the record says were sent (clamped at the device's limit as the board does),
    and read as the pot does (round to the count, 0.05 / 128 m); the forces sent are the
    links' law on the readings (K, B of analysis.ports.port_matrices) clamped and rounded
    to the protocol's counts. Both are integers of counts: equal, no tolerance (a true
    position within round-off of a count's edge could flip one count; measured: none in
    these cases)."""
    from hapsim.analysis.ports import port_matrices
    from hapsim.emulated.firefader_board import FireFaderDevice
    from hapsim.lockstep import excitation_starts
    from hapsim.lockstep_ports import PortDevice
    from hapsim.pipeline.faders_run import record_faders
    rng = np.random.default_rng(seed)
    sc = random_faders(rng)
    T, a, N = sc.period, 4e-3, 120
    drv = ff.FireFader()
    starts = excitation_starts(2, a, T)
    (_, da), (_, db) = sc.devices
    dev = FireFaderDevice(da, sc.rate_hz, None, clock="lockstep", device_b=db,
                          hand=[(x0[0], x0[1], v0[0], v0[1]) for x0, v0 in starts],
                          **drv.mock_hardware())
    run = record_faders(InProcessLink(dev), sc, N, len(starts),
                        force_scale=drv.force_scale, pace=False)
    assert run["stop"] == "end" and len(run["records"]) == len(starts)
    K, B = port_matrices(sc)
    lim = np.array([d.force_limit for _, d in sc.devices])
    q = ff.METRES_PER_COUNT
    for (x0, v0), rec in zip(starts, run["records"]):
        x, f = rec["position"], rec["force"]
        # the forces: the links' law on the readings, clamped, in counts
        xp = np.vstack([x[:1], x[:-1]])
        law = np.clip(-(x @ K.T) - ((x - xp) @ B.T) / T, -lim, lim)
        counts = np.array([[max(ff.force_counts(v, drv.full_scale), -ff.FORCE_MAX)
                            for v in row] for row in law])
        assert np.array_equal(np.round(f / drv.force_scale), counts)
        # the readings: each fader's own model, driven by those forces
        for i, (_, d) in enumerate(sc.devices):
            pd = PortDevice(d, sc.rate_hz, x0[i], v0[i])
            want = np.empty(N)
            for k in range(N):
                want[k] = min(max(round(pd.position / q), -ff.CENTRE),
                              ff.POSITION_MAX - ff.CENTRE)
                pd.tick(float(np.clip(f[k, i], -lim[i], lim[i])))
            assert np.array_equal(np.round(x[:, i] / q), want), (seed, i)
    # a rest that stays at rest, and each start moved the faders
    assert not np.any(run["records"][0]["position"])
    assert all(np.any(r["position"][1:] != r["position"][0]) for r in run["records"][1:])


@pytest.mark.parametrize("seed", range(6))
def test_the_decimated_second_order_fit_is_exact_on_the_lockstep_loop(seed):
    """The run's fit (every D-th sample, the rendered pairs only: order 2, the first
    decimated sample skipped) on the exact lockstep loop's free responses
    (hapsim.lockstep_ports.LockstepPorts, no quantiser) gives the predicted felt matrices to
    the linear loop's round-off allowance (LinearisationBound.roundoff, the lockstep
    measurement's own): the hold's and the delay's fast modes it leaves out are gone
    after one decimated sample, at 0.09^D of their start."""
    from hapsim.analysis.felt_matrices import felt_deviation
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.ports import check_ports, port_loop
    from hapsim.lockstep import excitation_starts
    from hapsim.lockstep_ports import LockstepPorts, ports_bound
    from hapsim.pipeline.faders_run import FIT_ORDER, _decimated, decimation
    sc = random_faders(np.random.default_rng(100 + seed))
    chk = check_ports(sc)
    T, N, a = sc.period, 300, 4e-3
    D = decimation(chk, T)
    assert D >= 4                             # 0.09^4 ~ 7e-5; the scenes' D: 9-15
    rest = LockstepPorts(sc).step(N)
    recs = [(LockstepPorts(sc, x0, v0).step(N) - rest)[::D]
            for x0, v0 in excitation_starts(2, a, T)[1:]]
    use = _decimated(np.ones(N, bool), D)
    fit = fit_felt_nd(recs, port_loop(sc)[0].mass, D * T, FIT_ORDER, usable=[use] * 4)
    dev = felt_deviation(fit, chk)
    assert max(dev.values()) <= ports_bound(sc, chk, a).roundoff, (D, dev)


def soft_faders(rng) -> ScenePorts:
    """A random soft two-fader scene (anchors 4..8 N/m, coupling 5..10 N/m, the shipped
    devices): the faders may move 9 mm under the 0.38 N limit."""
    names = ("fader_a", "fader_b")
    dev = Device(mass=0.05, friction=0.1, delay=0.725, force_limit=0.38,
                 protocol="firefader")
    return ScenePorts(
        rate_hz=250.0, masses=tuple(Mass(n, "port") for n in names)
        + (Mass("anchor", "ground"),),
        links=tuple(Link(f"s{n[-1]}", "spring_damper", n, "anchor",
                         float(rng.uniform(4.0, 8.0)), 0.05) for n in names)
        + (Link("c", "spring_damper", *names, float(rng.uniform(5.0, 10.0)), 0.05),),
        devices=tuple((n, dev) for n in names))


@pytest.mark.parametrize("case", ["shipped", 0, 1, 2])
def test_the_quantised_records_state_nothing_the_pots_cannot_bound(case):
    """The board in lockstep (by name: no host timing, the pots' and the forces' rounding
    alone). The wire's term is taken over the errors' box (hapsim.analysis.wire_box): at
    the records it is at least the first-order one and, at these 8-bit pots, above the
    measurable limit for every statement (measured: errors within the bounds moved a
    statement the first-order term made by up to 0.90 of it, and the box's sampled
    sensitivity was 1.06-1.95 times the records'; faders_run's notes), so nothing is
    stated and nothing "differs"; the reason names the box. What the run can state is
    predicted before it (faders_feasibility) and is what the records state."""
    from pathlib import Path

    import hapsim.lockstep as lockstep
    from hapsim.analysis.ports import check_ports
    from hapsim.emulated.firefader_board import FireFaderDevice
    from hapsim.lockstep import excitation_starts
    from hapsim.pipeline.faders_run import faders_feasibility, measure_faders, record_faders
    from hapsim.scene import load_scene_ports
    if case == "shipped":
        sc, a = load_scene_ports(Path(__file__).resolve().parents[1] / "configs"
                                 / "two_faders.yaml"), 4e-3
    else:
        sc, a = soft_faders(np.random.default_rng(200 + case)), 9e-3
    drv = ff.FireFader()
    chk = check_ports(sc)
    starts = excitation_starts(2, a, sc.period)
    (_, da), (_, db) = sc.devices
    dev = FireFaderDevice(da, sc.rate_hz, None, clock="lockstep", device_b=db,
                          hand=[(x0[0], x0[1], v0[0], v0[1]) for x0, v0 in starts],
                          **drv.mock_hardware())
    run = record_faders(InProcessLink(dev), sc, 300, len(starts),
                        force_scale=drv.force_scale, pace=False)
    assert not any(r["clamped"].any() for r in run["records"])   # the linear loop
    res = measure_faders(sc, run, a, samples=300, order=chk.states // 2, chk=chk,
                         force_scale=drv.force_scale)
    v, wire = res["verdict"], res["wire"]
    said = {s["name"]: s["verdict"] for s in v["statements"]}
    assert "differs" not in said.values(), v["reason"]
    assert wire["box"] and set(said.values()) == {"not measurable"}, said
    assert "over the errors' box" in v["reason"]
    # the box's term against the first-order one at the same records (the per-class
    # terms add alike): never below it
    orig = lockstep.wire_terms_nd
    lockstep.wire_terms_nd = lambda *p, **k: orig(*p, **{**k, "box": False})
    try:
        first = measure_faders(sc, run, a, samples=300, order=chk.states // 2, chk=chk,
                               force_scale=drv.force_scale)["wire"]
    finally:
        lockstep.wire_terms_nd = orig
    for q in ("felt_stiffness", "felt_damping"):
        assert wire[q] >= first[q]
        assert all(b >= f for b, f in zip(wire["directions"][q], first["directions"][q]))
    # faders_feasibility records the same lockstep board through its own link
    # (LockstepBoardLink) and measures its records as above: where they are this run's
    # to the bit (asserted), its measurement is the one made above (measure_faders is a
    # pure function of the records and the arguments), so it is not made twice (2.0 of
    # the test's 4.1 CPU-s); its verdict, statements and sentence are still its own
    import hapsim.pipeline.faders_run as faders_run
    made = faders_run.measure_faders
    seen = []

    def measured_once(scene, run2, amplitude, **kw):
        seen.append(_same(run2, run))
        if seen[-1] and amplitude == a and kw == dict(samples=300, order=chk.states // 2,
                                                        chk=chk, force_scale=drv.force_scale):
            return res
        return made(scene, run2, amplitude, **kw)
    faders_run.measure_faders = measured_once
    try:
        pre = faders_feasibility(sc, a, 300, chk)
    finally:
        faders_run.measure_faders = made
    assert seen == [True]              # the feasibility's records are the run's, bit for bit
    assert pre["stated"] == [] and pre["statement"].startswith("not measurable")
    assert pre["not_stated"] == [s["name"] for s in v["statements"]]


def _same(x, y) -> bool:
    """Two records (dicts, lists, arrays, numbers) equal to the bit, NaN equal to NaN."""
    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(
            _same(x[k], y[k]) for k in x)
    if isinstance(x, (list, tuple)):
        return isinstance(y, (list, tuple)) and len(x) == len(y) and all(
            _same(p, q) for p, q in zip(x, y))
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        x, y = np.asarray(x), np.asarray(y)
        return x.shape == y.shape and x.dtype == y.dtype and (
            x.tobytes() == y.tobytes())
    return x == y or (x != x and y != y)


def test_fader_b_is_the_firmwares_own_second_fader():
    """The board's fader B (the .ino's second motor, enable and pot): its byte of the
    packet drives it, its pot is in the record's second byte, read POT_S before pot A on
    the wall clock (its loop delay 1 - (adc_s - POT_S) / T), and the silence rule zeroes
    both faders' forces."""
    from hapsim.emulated.firefader_board import FireFaderDevice
    d = Device(mass=0.05, friction=0.1, delay=0.725, force_limit=0.38)
    dev = FireFaderDevice(d, 250.0, None, clock="lockstep", device_b=d)
    for _ in range(8):                        # the enables past their gate
        dev.feed(ff.encode_packet(0, 0))
    for _ in range(20):
        rec = dev.feed(ff.encode_packet(0, 100))
    r = ff.RecordDecoder().feed(rec)[-1]
    assert r[0] == ff.CENTRE and r[1] > ff.CENTRE + 5        # B pushed, A at rest
    assert dev.fader_b.held == 200 / 254 * 0.39              # twice the count, of 254
    dev.idle(0.2)
    assert dev.enable == dev.enable_b == 0 and dev.fader_b.settles_on() == 0.0
    w = FireFaderDevice(d, 250.0, None, device_b=d)
    T = 1 / 250
    assert 1 - w.adc_b_s / T == pytest.approx(1 - (w.ADC_S - w.POT_S) / T, rel=0, abs=0)


def test_two_faders_on_the_boards_own_clock_beside_two_cpu_hogs(two_cpu_hogs):  # noqa: F811
    """The embedded board on its own wall clock, behind a pty, two CPU-bound processes
    running: the run ends by its duration, or by the host's own lateness (beyond
    LATE_STOP_S, or a stall that carried a fader out of the workspace), and leaves both
    faders at zero force (the board's own report); a
    verdict is made on both faders (the matrices across them and each principal
    direction, or "not measurable" with its reason): "not measurable", as the prediction
    before the run said (docs/ports.md: the 8-bit pots' term over the errors' box)."""
    import hapsim
    from hapsim.pipeline.faders_run import CUT_PERIODS, LATE_STOP_S
    from pathlib import Path
    assert all(p.is_alive() for p in two_cpu_hogs)
    path = Path(__file__).resolve().parents[1] / "configs" / "two_faders.yaml"
    t = time.monotonic()
    rep = hapsim.run(str(path))
    took = time.monotonic() - t
    rt = rep.extra["realtime"]
    assert rt["held_at_end"] == [0.0, 0.0], rt
    # the host's watchdog beside the board (hapsim.drivers.host_watchdog): each zero write
    # it made (a host silence of its bound) was answered and its record dropped
    wd = rt["watchdog"]
    assert wd["running"] and wd["zeroed"] == wd["fired"], wd
    assert rt["stop"] == "end" or rt["stop"].startswith(("host late", "safety:")), rt
    if rt["stop"].startswith("host late"):
        # a write past the bound, or a zero write in a stall that the board merged with
        # the host's next packet (one record for two: whose is lost)
        assert rt["latest"] > LATE_STOP_S or (
            rt["stop"].startswith("host late: the watchdog zeroed the forces")
            and wd["zeroed"] >= 1), rt
    if rt["stop"].startswith("safety:"):
        # the workspace, after a stall of the host: the force held over it (or, past the
        # silence rule, none) carried the fader out; seen once beside another session's
        # SCHED_FIFO process (fader A 42.2 mm out after a 163 ms stall)
        assert "workspace" in rt["stop"] and rt["latest"] > CUT_PERIODS / 250.0, rt
    # the scene's own faders: a verdict is made, never "differs" (a wrong verdict); the
    # 8-bit pots' rounding, over the errors' box, leaves every quantity unstated, and the
    # run said so before it started (in real time the host's lateness only adds)
    assert rep.verdict == "not measurable" and rep.reason
    assert rep.extra["stated_before_run"].startswith("not measurable, predicted before")
    assert rep.dof == 2 and rep.extra["ports"] == ["fader_a", "fader_b"]
    if rt["stop"] == "end":
        # both faders: the two 2 x 2 matrices and the two principal directions, each
        # stated or named as not stated
        names = {s["name"] for s in rep.statements} | set(rep.not_stated)
        assert {"felt stiffness", "felt damping"} <= names
        assert sum(s["direction"] is not None for s in rep.statements) in (0, 4)
        assert len(rt["usable"]) == 5
    assert math.isfinite(took)


class _ZeroingWatchdog:
    """The host's watchdog as record_faders sees it, its zero writes made where asked:
    just before the host's write number ``at`` (a stall of the whole bound ends there),
    the zero packet written to the port and reported by that host write, as
    :meth:`hapsim.drivers.torque_watchdog.TorqueWatchdog.write` reports it."""

    def __init__(self, at):
        self.at, self.n, self.fired = set(at), 0, 0

    def arm(self, on=True):
        pass

    def write(self, ser, data, holding):
        self.n += 1
        times = ()
        if self.n in self.at:
            ser.write(ff.encode_packet(0, 0))
            self.fired += 1
            times = (time.monotonic_ns(),)
        ser.write(data)
        return times


def _lockstep_faders(seed):
    """A random two-fader scene and its board in lockstep (named), with the hand's starts:
    ``(rng, scene, driver, starts, device)``."""
    from hapsim.emulated.firefader_board import FireFaderDevice
    from hapsim.lockstep import excitation_starts
    rng = np.random.default_rng(seed)
    sc = random_faders(rng)
    drv = ff.FireFader()
    starts = excitation_starts(2, 4e-3, sc.period)
    (_, da), (_, db) = sc.devices
    dev = FireFaderDevice(da, sc.rate_hz, None, clock="lockstep", device_b=db,
                          hand=[(x0[0], x0[1], v0[0], v0[1]) for x0, v0 in starts],
                          **drv.mock_hardware())
    return rng, sc, drv, starts, dev


@pytest.mark.parametrize("seed", [0, 1])
def test_a_watchdog_zero_write_answered_with_the_hosts_next_is_read_as_its_own(seed):
    """Lockstep by name: the board answers each command at once, so when the host's
    watchdog made a zero write in a stall, the host's next read finds two records, the
    zero write's and its own write's (as a host descheduled between its write and its
    read finds them on the board's own clock). Each is the answer to one command: the
    run takes them in order and ends by its duration, every zero write's record dropped
    (it stopped with "no record within 0.5 s (the board lost)" when a read kept the last
    record of those waiting: a fresh-clone suite's two-fader run did so after a 190 ms
    stall of its host)."""
    from hapsim.pipeline.faders_run import record_faders
    rng, sc, drv, starts, dev = _lockstep_faders(seed)
    wd = _ZeroingWatchdog(rng.choice(np.arange(2, 200), size=6, replace=False))
    run = record_faders(InProcessLink(dev), sc, 60, len(starts),
                        force_scale=drv.force_scale, pace=False, watchdog=wd)
    assert run["stop"] == "end" and len(run["records"]) == len(starts), run["stop"]
    assert wd.fired == 6 and run["watchdog_zeroed"] == 6


class _MergingWatchdog(_ZeroingWatchdog):
    """As :class:`_ZeroingWatchdog`, the zero packet and the host's in one write: the
    board finds both waiting for its pass and merges them (one record)."""

    def write(self, ser, data, holding):
        self.n += 1
        if self.n in self.at:
            ser.write(ff.encode_packet(0, 0) + data)
            self.fired += 1
            return (time.monotonic_ns(),)
        ser.write(data)
        return ()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_zero_write_the_board_merged_with_the_hosts_stops_the_run_by_its_cause(seed):
    """Lockstep by name: the watchdog's zero packet and the host's next wait together for
    the board's pass, and the ``.ino`` runs one pass for both (the last counts), so one
    record answers two commands. The records say nothing of whose they are: the run stops,
    said as the host's lateness with the count of records, and keeps what it measured.
    It waited 0.5 s for a record that never came and stopped with "no record within
    0.5 s (the board lost)" (a fresh-clone CI's two-fader run over the mock's port after
    a 180 ms stall of its host)."""
    from hapsim.pipeline.faders_run import record_faders
    rng, sc, drv, starts, dev = _lockstep_faders(seed)
    at = int(rng.integers(100, 150))
    wd = _MergingWatchdog([at])
    t = time.monotonic()
    run = record_faders(InProcessLink(dev), sc, 60, len(starts),
                        force_scale=drv.force_scale, pace=False, watchdog=wd)
    assert wd.fired == 1 and dev.merged >= 1
    assert run["stop"].startswith("host late: the watchdog zeroed the forces"), run["stop"]
    assert "answered 1 of the 2 packets" in run["stop"], run["stop"]
    assert time.monotonic() - t < 60.0 and run["records"], run

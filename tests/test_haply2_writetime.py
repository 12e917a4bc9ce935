"""The host's write timing in the 2DIY's stated uncertainty (issue 29): on a board that
keeps its own time each torque acts from when the board takes its write to when it takes
the next, not one period. The record is then, exactly, the loop of exact periods with the
device's state changed at each sample by the motion over the hold's excess
(:func:`hapsim.pipeline.haply2_host.hold_bounds`), which the wire's term carries through
the loop (:func:`hapsim.lockstep.state_responses`).

Checked here against an independent simulation of the loop with holds of random lengths
(the device advanced exactly over each, ``scipy.linalg.expm``), and through the whole
measurement on the emulated board on a simulated clock (the same run on any machine)."""

from __future__ import annotations

import dataclasses
import functools
import types

import numpy as np
import pytest
from scipy.linalg import expm

from hapsim.analysis.pencil import fit_felt_nd
from hapsim.emulated.haply2_board import Haply2DIYBoard
from hapsim.engine import Engine
from hapsim.kinematics import device
from hapsim.lockstep import (LockstepND, excitation_starts, identification_plan,
                             wire_terms_nd)
from hapsim.pipeline import haply2_host as host
from hapsim.pipeline import haply2_record as record
from hapsim.scene import load_scene_nd
from test_haply2_stalls import WALL, SimLink
from tolerance import measured

#: The hand's start [m]: the records move 2.18 a (0.44 mm, inside the wall's 0.5 mm),
#: about what the board's coast through its set-up gave 1e-4 m before the hand let go at
#: the record's first write (3.3 a); 1e-4 m now leaves the felt damping unstated
A = 2e-4


def _hold_map(M, B, h):
    """The device's exact map over a hold of ``h`` [s]: ``[x, v]`` and a force held ->
    ``[x, v]`` (``M dv/dt = u - B v``), from the matrix exponential of the augmented
    system (Van Loan)."""
    n = M.shape[0]
    Mi = np.linalg.inv(M)
    A = np.zeros((3 * n, 3 * n))
    A[:n, n:2 * n] = np.eye(n)
    A[n:2 * n, n:2 * n] = -Mi @ B
    A[n:2 * n, 2 * n:] = Mi
    E = expm(A * h)
    return E[:2 * n, :2 * n], E[:2 * n, 2 * n:]


def _jittered(scene, x0, v0, holds):
    """The loop (the scene's engine, delay 1) with the device held over ``holds[i]``
    between samples ``i`` and ``i + 1``, advanced exactly: the positions, the forces, and
    the state change each hold's excess made (against a hold of one period)."""
    n, T = scene.dimension, scene.period
    M, B = scene.device.mass, scene.device.friction
    eng = Engine(scene)
    rest = scene.device.position.copy()
    state = np.concatenate([x0, v0])
    eng.xp[:, eng.port] = rest + x0 - v0 * T
    eng.x[:, eng.port] = rest + x0
    P0, G0 = _hold_map(M, B, T)
    N = len(holds)
    pos, force, w = np.zeros((N, n)), np.zeros((N, n)), np.zeros((N, 2 * n))
    u = np.zeros(n)
    for i in range(N):
        pos[i] = state[:n]
        eng.set_port_position(rest + state[:n])
        eng.step()
        F = eng.port_force.copy()
        force[i] = F
        if i + 1 < N:
            P, G = _hold_map(M, B, holds[i + 1])
            nxt = P @ state + G @ u
            w[i + 1] = nxt - (P0 @ state + G0 @ u)
            state = nxt
        u = F
    return pos, force, w


def test_term_is_zero_with_exact_periods():
    """Writes exactly a period apart (a host on time; a lockstep board's holds are periods
    by construction and get no term at all: ``test_haply2_realtime``): every hold's bound
    is 0, whatever the motion, the torques and the writes' durations, and the wire's term
    with these zero state errors is the one without them, bit for bit. (At 1024 Hz the
    period is a power of two: the write times are exact in binary64.)"""
    sc = load_scene_nd(WALL)
    s1024 = dataclasses.replace(sc, rate_hz=1024.0)
    rng = np.random.default_rng(4)
    N = 60
    J = device("pantograph", sc.device.geometry).jacobian(sc.device.joints)
    b = np.arange(N) * s1024.period
    rec = {"write_s": np.stack([b, b + rng.uniform(0, 3e-4, N)], axis=1),
           "position": rng.normal(0, 1e-4, (N, 2)), "readings": rng.normal(0, 1e-4, (N, 2)),
           "torque": rng.uniform(-0.05, 0.05, (N, 2))}
    h = host.hold_bounds(rec, s1024, J, [1e-6, 1e-6])
    assert not np.any(h["delta"]) and not np.any(h["position"]) and not np.any(h["velocity"])
    # nothing to correct either: no state change estimated, no remainder, the record
    # left as it is (hold_motion runs no loop for zero changes)
    c = host.hold_corrections(rec, s1024, J, [1e-6, 1e-6])
    assert not np.any(c["state"]) and not np.any(c["corrected"])
    assert not np.any(c["position"]) and not np.any(c["velocity"])
    assert np.all(rec["position"] - host.hold_motion(s1024, c["state"]) == rec["position"])
    T = sc.period
    chk, p, _ = identification_plan(sc, N)
    rest = LockstepND(sc).step(N, record=True)
    diffs = [LockstepND(sc, x0=x0, v0=v0).step(N, record=True) - rest
             for x0, v0 in excitation_starts(2, 1e-4, T)[1:]]
    errs = [("reading", J, np.array([1e-7, 1e-7]))]
    zero = [np.zeros((N, 2))] * 5
    a = wire_terms_nd(sc, diffs, chk, p, errs)
    z = wire_terms_nd(sc, diffs, chk, p, errs + [("position", np.eye(2), zero),
                                                 ("velocity", np.eye(2), zero)])
    assert a == z


@functools.cache
def _random_hold_records(big=0):
    """The five records of the independent loop whose holds last ``T + delta_k``
    (``|delta_k|`` up to 40 us, uniform, seed 29; with ``big``, that many holds of each
    record up to 500 us off, as a loaded host's late writes), 150 samples each: per record the
    positions, the forces, the state changes each hold's excess made (``_jittered``), the
    same start's record at exact periods, and the host's record (write times, readings,
    torques ``tau = J^T F``)."""
    sc = load_scene_nd(WALL)
    T = sc.period
    chk, p, N = identification_plan(sc, 150)
    J = device("pantograph", sc.device.geometry).jacobian(sc.device.joints)
    rng = np.random.default_rng(29)
    out = []
    for x0, v0 in excitation_starts(2, 1e-4, T):
        holds = T + rng.uniform(-4e-5, 4e-5, N)
        if big:
            holds[rng.choice(np.arange(2, N), big, replace=False)] = \
                T + rng.uniform(-5e-4, 5e-4, big)
        pos, force, w = _jittered(sc, np.asarray(x0, float), np.asarray(v0, float), holds)
        s = np.concatenate([[0.0], np.cumsum(holds[1:])])
        rec = {"write_s": np.stack([s, s], axis=1), "position": pos, "readings": pos,
               "torque": force @ J}
        out.append(types.SimpleNamespace(
            x0=x0, v0=v0, holds=holds, s=s, pos=pos, w=w, rec=rec,
            nominal=LockstepND(sc, x0=x0, v0=v0).step(N, record=True)))
    return sc, chk, p, N, J, out


def _moved(fit, exact, chk, q):
    """How far a fitted felt matrix moved from the exact records' fit, over the largest
    predicted entry (the deviation's scale)."""
    P = np.asarray(getattr(chk.render, q), float)
    return float(np.max(np.abs(np.asarray(fit[q]) - np.asarray(exact[q])))
                 / np.max(np.abs(P)))


def test_holds_off_a_period_are_state_changes_within_their_bounds_and_the_term():
    """An independent loop whose holds last ``T + delta_k`` (``|delta_k|`` up to 40 us,
    random) is, to round-off, the loop of exact periods with the state changed by
    ``w_k`` at each sample (``LockstepND``'s ``state_error``); each ``|w_k|`` is within
    ``hold_bounds``'s bound computed from the write times and the record alone; and the
    felt matrices fitted from the jittered records move from the exact ones by no more
    than the wire's term those bounds give (first order, Hoelder's worst case)."""
    sc, chk, p, N, J, runs = _random_hold_records()
    T = sc.period
    pos_b, vel_b = [], []
    for r in runs:
        # the same loop in lockstep with the state changes: the same record
        same = LockstepND(sc, x0=r.x0, v0=r.v0).step(N, record=True, state_error=r.w)
        # round-off of the two simulations' sums over 150 samples of positions ~1e-4 m:
        # measured worst 2.0e-19 m (this machine's OpenBLAS); a margin of 5000 for another
        # BLAS's order of sums, and still 1e-11 of the amplitude
        assert np.max(np.abs(same - r.pos)) <= measured(2.0e-19, 5000)
        hb = host.hold_bounds(r.rec, sc, J, [0.0, 0.0])
        # (measured: the largest |w_k| 0.96 of its bound for the position, 0.99 for the
        # velocity: the bounds are reached along the mass's lightest direction)
        assert np.all(np.abs(r.w[:, :2]) <= hb["position"])
        assert np.all(np.abs(r.w[:, 2:]) <= hb["velocity"])
        # the holds back from their sums: the round-off of the differences of times up
        # to 0.15 s, a few units in the last place of the sum
        assert np.allclose(hb["delta"][1:], np.abs(r.holds[1:] - T), rtol=0,
                           atol=4 * np.spacing(r.s[-1]))
        pos_b.append(hb["position"])
        vel_b.append(hb["velocity"])
    M = sc.device.mass
    recs = [r.pos for r in runs]
    diffs = [r - recs[0] for r in recs[1:]]
    fit = fit_felt_nd(diffs, M, T, p)
    exact = fit_felt_nd([r.nominal - runs[0].nominal for r in runs[1:]], M, T, p)
    term = wire_terms_nd(sc, diffs, chk, p, [("position", np.eye(2), pos_b),
                                             ("velocity", np.eye(2), vel_b)])
    for q in ("felt_stiffness", "felt_damping"):
        moved = _moved(fit, exact, chk, q)
        # measured: the fit moved 0.078 (stiffness) and 0.12 (damping) of the term
        assert 0 < moved <= term[q], (q, moved, term[q])


@pytest.mark.parametrize("big", [0, 12])
def test_the_signed_holds_corrected_leave_a_remainder_within_its_bound_and_term(big):
    """The same independent loop, corrected as the host does (``hold_corrections``: each
    hold's state change estimated with its sign from the write times, the readings and
    the torques; ``hold_motion``: its motion through the loop removed): each estimate is
    off the true change ``w_k`` by no more than the remainder's bound, that bound is a
    small part of the worst case's, and the corrected records' fit moves from the
    exact-period fit by no more than the wire's term of the remainder -- and by less than
    the uncorrected fit moved. Also with 12 holds a record up to 500 us off (up to the
    cut, :data:`~hapsim.pipeline.haply2_host.HOLD_CUT_PERIODS`: a loaded host's late
    writes, measured 100-900 us)."""
    sc, chk, p, N, J, runs = _random_hold_records(big)
    T = sc.period
    M = sc.device.mass
    corr, pos_b, vel_b = [], [], []
    for r in runs:
        # (the first hold's force 0, as the arming's zero write's in record_realtime)
        c = host.hold_corrections(r.rec, sc, J, [0.0, 0.0], first_torque=(0.0, 0.0))
        hb = host.hold_bounds(r.rec, sc, J, [0.0, 0.0])
        # every hold corrected (row 0 is the record's start: no hold)
        assert np.all(c["corrected"][1:]) and not c["corrected"][0]
        # without the first hold's torque that hold is not corrected: its worst case kept
        c1 = host.hold_corrections(r.rec, sc, J, [0.0, 0.0])
        assert not c1["corrected"][1] and c1["position"][1, 0] == hb["position"][1, 0]
        assert np.all(c1["state"][2:] == c["state"][2:])
        # measured: the largest |w_k - w_hat_k| 0.72 of its bound (position and velocity;
        # with the 500 us holds too)
        assert np.all(np.abs(r.w[:, :2] - c["state"][:, :2]) <= c["position"])
        assert np.all(np.abs(r.w[:, 2:] - c["state"][:, 2:]) <= c["velocity"])
        # measured: the remainder's bound 4e-5 to 1.1e-4 of the worst case's (median,
        # position); asserted below 1e-2 of it, the margin ~100
        ok = c["corrected"]
        assert np.median(c["position"][ok] / hb["position"][ok]) < 1e-2
        corr.append(r.pos - host.hold_motion(sc, c["state"]))
        pos_b.append(c["position"])
        vel_b.append(c["velocity"])
    exact = fit_felt_nd([r.nominal - runs[0].nominal for r in runs[1:]], M, T, p)
    raw = fit_felt_nd([r.pos - runs[0].pos for r in runs[1:]], M, T, p)
    diffs = [r - corr[0] for r in corr[1:]]
    fit = fit_felt_nd(diffs, M, T, p)
    term = wire_terms_nd(sc, diffs, chk, p, [("position", np.eye(2), pos_b),
                                             ("velocity", np.eye(2), vel_b)])
    for q in ("felt_stiffness", "felt_damping"):
        moved = _moved(fit, exact, chk, q)
        # measured: 0.18 (stiffness) and 0.025 (damping) of the remainder's term, which
        # is 8.8e-5 and 1.2e-4 of the worst case's; uncorrected the fit moved 4900 and
        # 41000 times as far (with the 500 us holds: 0.33 and 0.088 of the term; 1100
        # and 3900 times as far)
        assert moved <= term[q], (q, moved, term[q])
        assert moved < _moved(raw, exact, chk, q), q


class _JitterClock:
    """Simulated time (as ``test_haply2_stalls.SimClock``) whose readings move it 1 us
    plus a random 0-``spread`` [s]: the host's own work between two readings varies, so
    its writes go out off the period by what its clock shows; with ``late = (p, s)``
    a reading also moves it a random 0-``s`` [s] with probability ``p`` (the host
    descheduled)."""

    def __init__(self, seed, spread, late=(0.0, 0.0)):
        self.t = 0.0
        self.rng = np.random.default_rng(seed)
        self.spread = spread
        self.late = late

    def now(self):
        self.t += 1e-6 + self.rng.uniform(0.0, self.spread)
        if self.late[0] and self.rng.uniform() < self.late[0]:
            self.t += self.rng.uniform(0.0, self.late[1])     # the host descheduled
        return self.t

    def sleep(self, d):
        self.t += max(float(d), 0.0)


def _measure(monkeypatch, *, inertia=1.0, unseen=0.0, seed=1, N=200, spread=3e-6,
             late=(0.0, 0.0), amplitude=A):
    """The whole measurement on the emulated board on its own clock (simulated time), the
    host's clock jittered (:class:`_JitterClock`, 0-``spread`` [s] a reading, 3 us unless
    told, and with probability ``late[0]`` a reading ``late[1]`` later), each write taken by
    the board a random 0-``unseen`` [s] after the host began it (a latency the host does
    not see), the board's joint inertia ``inertia`` times the scene's."""
    clk = _JitterClock(seed, spread, late)
    monkeypatch.setattr(record, "time", types.SimpleNamespace(
        perf_counter=clk.now, monotonic=clk.now, sleep=clk.sleep))
    sc = load_scene_nd(WALL)
    plant = dataclasses.replace(sc, device=dataclasses.replace(
        sc.device, joint_inertia=sc.device.joint_inertia * inertia))
    board = Haply2DIYBoard(plant, "gen3", cpr=2.0 ** 22, amplitude=amplitude, clock="wall")
    link = SimLink(board, clk)
    rng = np.random.default_rng(seed + 1)
    write = link.write

    def late(data):
        if len(data) == 10:
            clk.t += rng.uniform(0.0, unseen)
        return write(data)
    link.write = late
    return host.measure_felt_haply2_port(link, sc, "gen3", amplitude=amplitude,
                                         resolution=2.0 ** 22, samples=N,
                                         plan=identification_plan(sc, N),
                                         probe_wiring=False)


def test_a_correct_loop_with_the_hosts_jitter_is_within_simulated_time(monkeypatch):
    """The host's writes off the period by its clock's jitter (seen, in the term) and taken
    up to 40 us later still (unseen, less than the firmware's pass): a correct loop is
    "within", its write-timing term counted, every record whole (the first hold a period
    too: before, tick 0's write went out when the arming's reply came, and the same run
    was 0.3-0.5 % off in the felt stiffness, seeds 1-3)."""
    r = _measure(monkeypatch, unseen=4e-5)
    # measured over seeds 1-3: the largest deviation over its uncertainty 0.27; with the
    # holds corrected (hold_corrections: the write-timing term now a remainder, the
    # unseen latency not in it) 0.53
    assert r["verdict"] == "within", (r["reason"], r["deviation"], r["uncertainty"])
    assert 0 < r["wire"]["hold_s"] < 0.1 * 1e-3
    assert r["usable"] == [200] * 5
    for k in ("felt_stiffness", "felt_damping"):
        assert r["deviation"][k] <= r["uncertainty"][k]


def test_a_board_with_30_percent_more_inertia_differs_on_its_own_clock_simulated_time(
        monkeypatch):
    """The same host jitter against a board whose joints carry 30 % more inertia than the
    scene says: never "within"; "differs" (the felt stiffness 17 % off) when beyond the
    stated uncertainty even with the board's take of each write varying by a firmware
    pass more than the host's write times show (``LINK_JITTER_S``), else "not
    measurable" with the departure named (so since the wire's term is taken over the
    error box: with that allowance it is beyond the measurable limit)."""
    h = _measure(monkeypatch, inertia=1.3)
    # measured over seeds 1-3 (a = 1e-4 m): 0.175 off against 0.130-0.131 with the pass's
    # allowance (0.174 at a = 2e-4 m);
    # with the holds corrected against 0.095-0.098. Since the wire's term is taken over
    # the error box (hapsim.analysis.wire_box, its margin 2) the stiffness's term with the
    # pass's allowance is 0.28 (0.095 at first order at the records), beyond the
    # measurable limit: "not measurable", the departure kept in the reason; without the
    # allowance it is 0.023 and the run "differs" before that check
    assert h["verdict"] in ("differs", "not measurable"), (h["reason"], h["deviation"])
    if h["verdict"] == "differs":
        assert h["deviation"]["felt_stiffness"] > h["link_uncertainty"]["felt_stiffness"]
    else:
        assert h["deviation"]["felt_stiffness"] > 0.1       # 30 % more inertia: 0.174
        dk = f"felt_stiffness {h['deviation']['felt_stiffness']:.3g}"
        assert "link's latency" in h["reason"] and dk in h["reason"], h["reason"]


def test_late_writes_corrected_within_and_30_percent_inertia_differs_simulated_time(
        monkeypatch):
    """A loaded host: its clock jittered ten times as much (0-20 us a reading) and now and
    then descheduled for up to 400 us (a write that late, the next hold short by as much;
    below the cut, :data:`~hapsim.pipeline.haply2_host.HOLD_CUT_PERIODS`). With the holds'
    known departures corrected (``hold_corrections``) a correct loop is "within", every
    stiffness stated and no row cut (a damping direction may not be stated since the wire's
    term is taken over the error box); a board with 30 % more inertia is never "within"
    ("differs" beyond the uncertainty with a firmware pass of unseen latency too, or "not
    measurable" where that allowance's term is beyond the limit). Before the correction
    (each hold's worst case, holds over 100 us cut) the same correct runs were "partly
    within" (seeds 1-3: the damping not stated, 5-10 rows a record cut) and the heavier
    board "not measurable" in 2 of 3."""
    r = _measure(monkeypatch, spread=2e-5, late=(3e-4, 4e-4))
    # measured over seeds 1-3: holds up to 200-270 us off; the largest deviation over its
    # uncertainty 0.12 (stiffness) and 0.05 (damping). Since the wire's term is taken over
    # the error box (hapsim.analysis.wire_box) a damping direction may not be stated:
    # "partly within", the stiffness stated and within
    assert r["verdict"] in ("within", "partly within"), (r["reason"], r["deviation"])
    assert all(s["quantity"] == "felt_damping" for s in r["statements"]
               if s["verdict"] == "not measurable")
    assert r["wire"]["hold_s"] > 1e-4
    assert r["usable"] == [200] * 5
    for k in ("felt_stiffness", "felt_damping"):
        if r["uncertainty"][k] is not None:
            assert r["deviation"][k] <= r["uncertainty"][k]
    assert r["uncertainty"]["felt_stiffness"] is not None
    h = _measure(monkeypatch, spread=2e-5, late=(3e-4, 4e-4), inertia=1.3)
    # measured over seeds 1-3: 0.175 off against 0.098-0.100 with the pass's allowance
    # (first order); over the error box that allowance leaves the stiffness unstated, as
    # in the test above: never "within"
    assert h["verdict"] in ("differs", "not measurable"), (h["reason"], h["deviation"])
    if h["verdict"] == "differs":
        assert h["deviation"]["felt_stiffness"] > h["link_uncertainty"]["felt_stiffness"]

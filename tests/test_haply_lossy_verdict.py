"""A Haply M3 re-synchronised on a lossy link: the frame's error is bounded, and the
verdict does not depend on how many times it happened (issue 29;
:func:`hapsim.pipeline.runner.timing_verdict`).

One host byte lost makes firmware V1.5 read a write's torque bytes as commands: a byte 0
is a reset, a byte 1 a set-up out of garbage (its single reads of bytes not arrived give
255: four encoders, whose parameters swallow the next writes); either forgets the
board's set-up, the writes are then answered by the id alone (``lone``), and the host
re-synchronises the board at its estimate of the angle. That is a real loss of place,
about 1.1 a run of 1.5 s at 1 byte in 200 each way (simulated, 40 seeds: 35 ``lone``). A
re-synchronisation moves the board's frame by the estimate's error, which the transport
bounds (``frame_bound``); the host closes its loop in its own frame, the record is cut
at each re-synchronisation (``seq`` skips) and each stretch is fitted from its own
initial state, so the error does not enter the fit. The count rule before (more than two:
"not measurable") withdrew sound verdicts.

On the simulated clock (the transport's ``time`` is the test's, the board
:class:`hapsim.emulated.haply_board.HaplyDevice` on it, a seeded link losing bytes each
way, ``tests/test_haply_silence.py``'s port), the host's loop closed with the engine of
``configs/haply.yaml`` and measured as ``hapsim run`` measures it
(:func:`hapsim.pipeline.runner.identify_run`).
"""

from __future__ import annotations

import collections
import dataclasses
import math
import struct
import types

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.drivers import get_driver
from hapsim.drivers import transport as tp
from hapsim.emulated.haply_board import HaplyDevice
from hapsim.engine import Engine
from hapsim.host.telemetry import FLAG_ESTIMATED
from test_haply_silence import SimClock, StarvedBoardPort

N_TICKS = 1500           # 1.5 s at 1 kHz, as tools/driver_timing.py's runs


@pytest.fixture(scope="module")
def prep():
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    return prepare_run(load_scene("configs/haply.yaml"),
                       RunOptions(driver="haply", rt_priority=0, handle_signals=False,
                                  duration=N_TICKS * 1e-3))


def sim_board(monkeypatch, prep, heavier=1.0):
    """The simulated clock (the transport's ``time``), the scene, its device, the M3
    driver armed at the scene's start and the emulated board on that clock, its joint
    ``heavier`` times the scene's inertia: ``(clock, scene, device, driver, board)``."""
    clock = SimClock()
    monkeypatch.setattr(tp, "time", clock)
    sc, dev = prep.scene, prep.scene.device
    drv = get_driver("haply", offset_deg=math.degrees(sc.excitation.x0))
    drv.loop_delay, drv.own_clock = int(dev.delay), True
    board = HaplyDevice(dataclasses.replace(dev, mass=dev.mass * heavier), sc.rate_hz,
                        sc.excitation, clock="wall", resolution=drv.resolution)
    return clock, sc, dev, drv, board


def host_loop(tr, drv, sc, clock, on_states=None):
    """``N_TICKS`` ticks of the host loop (:mod:`hapsim.host.host_clock`) over the armed
    transport ``tr`` on the simulated ``clock``, the engine of scene ``sc`` closing it;
    ``on_states`` is given each tick's STATEs. Returns the telemetry columns (one row per
    new record or estimated sample, as the loop logs them)."""
    from hapsim.host.host_clock import ESTIMATED_MAX
    dev = sc.device
    T = sc.period
    t0 = clock.t = math.ceil(clock.t / T) * T + T
    eng, lim = Engine(sc), float(dev.force_limit)
    rows = collections.defaultdict(list)
    used, run_est = -1, 0
    st = types.SimpleNamespace(seq=0, time_us=0, status=0, force_seq=0)
    for k in range(N_TICKS):
        clock.t = max(clock.t, t0 + k * T)
        states = [m for m in tr.receive(0.0) if isinstance(m, fp.State)]
        if on_states is not None:
            on_states(states)
        # the host loop's tick (hapsim.host.host_clock): a new record, else an estimated
        # sample (up to ESTIMATED_MAX in a row), else the last force held
        if states and states[-1].seq != used:
            m = states[-1]
            x, used, run_est, flag, t_us = m.position[0], m.seq, 0, 0, m.time_us
        elif tr.overdue() and run_est < ESTIMATED_MAX:
            x = tr.estimate(st, used + 1, 1)
            if x != x:
                tr.hold()
                continue
            run_est, used, flag, t_us = run_est + 1, st.seq, FLAG_ESTIMATED, st.time_us
        else:
            tr.hold()
            continue
        f = min(max(eng.port_step(x), -lim), lim)
        tr.send(fp.Force(used, (f,)))
        for q, v in (("time", t_us * 1e-6), ("position", x),
                     ("force", drv.applied_force(f)), ("seq", used), ("flags", flag)):
            rows[q].append(v)
    n = len(rows["seq"])
    cols = {q: np.asarray(rows[q], float) for q in ("time", "position", "force")}
    cols.update(seq=np.asarray(rows["seq"], np.int64),
                flags=np.asarray(rows["flags"], np.uint8), late=np.zeros(n, np.uint8),
                force_seq=np.asarray(rows["seq"], np.int64) - int(dev.delay),
                status=np.zeros(n, np.uint16))
    return cols


def _lossy_run(monkeypatch, prep, seed, p, heavier=1.0):
    """One run over a link losing each byte with probability ``p`` each way (seeded), the
    board's joint ``heavier`` times the scene's inertia. Returns the transport, the
    measurement and, per record taken, ``(host reading, true angle in the arming's frame,
    frame_bound then)`` [rad]."""
    from hapsim.pipeline.runner import identify_run
    clock, sc, dev, drv, board = sim_board(monkeypatch, prep, heavier)
    truth = []                       # (the angle sent, rounded to binary32; the truth)
    angle = board.angle_deg

    def angle_deg(port=0):
        a = angle(port)
        if port == 0 and board._base0 is not None:
            truth.append((math.radians(struct.unpack("<f", struct.pack("<f", a))[0]),
                          (board._counts() - board._base0) * 2.0 * math.pi / board.cpr))
        return a
    board.angle_deg = angle_deg
    tr = tp.DriverTransport(drv, "loop://", inertia=dev.mass)
    tr._ser.close()
    tr._ser = StarvedBoardPort(clock, board, [], (),
                               {"drop_rx": p, "drop_tx": p, "seed": 5000 + seed})
    tr.send(fp.Config(1000.0, 5000, 10.0))
    records = []
    cols = host_loop(tr, drv, sc, clock, lambda states: records.extend(
        (m.position[0], tr.stats["frame_bound"]) for m in states))
    n = cols["seq"].size
    tel = types.SimpleNamespace(wrapped=False, n=n, head=n, columns=lambda *a: cols)
    m = identify_run(prep, tel, None, driver=drv)
    # each record is a reply the board made, in order: matched to its truth
    out, j = [], 0
    for x, bound in records:
        while j < len(truth) and truth[j][0] != x:
            j += 1
        assert j < len(truth), "a record no reply of the board's made"
        out.append((x, truth[j][1], bound))
        j += 1
    return tr, m, out


def test_the_frame_moves_within_its_bound(monkeypatch, prep):
    """At 1 byte in 100 lost each way (seeds 0-3: 7 re-synchronisations in all): every
    record's reading is within the summed ``frame_bound`` of the re-synchronisations
    before it of the joint's true angle in the arming's frame, but for the wire's binary32
    rounding of the angle in degrees (half an ulp, 2^-24 relative, and the radians'
    conversion: 2^-23 relative). Measured (seeds 0-15 at 1 in 200): the largest error 3 %
    to 8 % of the bound."""
    resyncs = 0
    for seed in range(4):
        tr, m, recs = _lossy_run(monkeypatch, prep, seed, 1 / 100)
        resyncs += tr.stats["resyncs"]
        for x, true, bound in recs:
            assert abs(x - true) <= bound + 2.0 ** -23 * abs(true), (seed, x, true, bound)
    assert resyncs >= 4                  # the class happened (7, deterministic)


#: Seeds of 1 byte in 200 lost each way whose runs were re-synchronised more than the
#: count the verdict was withdrawn past before (2): found by running seeds 0-79 of this
#: link (matching joint: 5 of them, 3 to 6 re-synchronisations, all within; 0-59 of the
#: joint 30 % heavier: 5 of them, 3 to 5, none within). The matching ones found again on
#: the board with the firmware's 256 torque levels (its joint's path, and so its losses'
#: effect, another): seeds 0-59, 4 of them (5, 18, 38, 52), 3 or 4, all within.
MANY_MATCHING = (5, 18, 52)
MANY_HEAVIER = (6, 7, 38)


@pytest.mark.parametrize("seed", MANY_MATCHING)
def test_a_matching_joint_is_within_however_often_resynchronised(monkeypatch, prep, seed):
    """The matching joint, re-synchronised 3 to 6 times: within (the fit over the stretches
    between the re-synchronisations), and the run's rule keeps it (the frame's bound is
    far inside the workspace, the run's position bound)."""
    from hapsim.pipeline.runner import timing_verdict
    tr, m, recs = _lossy_run(monkeypatch, prep, seed, 0.005)
    assert tr.stats["resyncs"] > 2, tr.stats["resync_reasons"]
    assert m.get("within") is True, (m.get("verdict"), m.get("error"))
    reading = max(abs(x) for x, _, _ in recs)
    timing_verdict(m, types.SimpleNamespace(samples=N_TICKS, overruns=0), tr.stats,
                   workspace=(reading, 4.0))
    assert m["within"] is True, m["verdict"]
    # the same run in a workspace the frame's bound may leave: withdrawn, with the reason
    timing_verdict(m, types.SimpleNamespace(samples=N_TICKS, overruns=0), tr.stats,
                   workspace=(reading, reading + 0.5 * tr.stats["frame_bound"]))
    assert m["within"] is False and "beyond the workspace" in m["verdict"]


@pytest.mark.parametrize("seed", MANY_HEAVIER)
def test_a_heavier_joint_is_never_within(monkeypatch, prep, seed):
    """A joint 30 % heavier than the scene says, re-synchronised 4 or 5 times: "differs"
    or not measurable, never within."""
    tr, m, _ = _lossy_run(monkeypatch, prep, seed, 0.005, heavier=1.3)
    assert tr.stats["resyncs"] > 2, tr.stats["resync_reasons"]
    assert m.get("within") is not True, (m.get("verdict"), m.get("k"), prep.pred["k"])

"""The Haply M3's late replies kept as readings (issue 29;
:mod:`hapsim.drivers.late_replies`, :meth:`hapsim.drivers.haply.HaplyM3.unknown_force_rows`).

Under load a reply often misses its tick: the host loop steps the tick with an estimated
sample and the reply comes with the next tick's. Firmware V1.5 answers every write it
parses, in order, so a reply read together with every reply after it (none damaged)
answers the estimated tick's own command: the write was parsed in step, its torque is the
one sent. Such rows are kept (before, every estimated row was cut with its neighbours,
and loaded runs were left "not measurable: too few cycles").

On the simulated clock (``tests/test_haply_silence.py``'s port and clock, the board
:class:`hapsim.emulated.haply_board.HaplyDevice` on the wall clock of the simulation), the
board's reader starved in many short seeded windows (0.3 to 3 ms: its replies miss the
host's tick) and, in half the cases, a link losing 1 byte in 200 each way, the host's
loop closed with the engine of ``configs/haply.yaml`` and measured as ``hapsim run``
measures it (:func:`hapsim.pipeline.runner.identify_run`). What must hold, per seed:

- every late reply recorded against a command is the reply the board made to that very
  write (matched by the write's torque, its binary32 bytes; ambiguous torques skipped):
  the board's angle at that tick, bit for bit after the wire's binary32 and the radians;
- the rows kept are never fewer than before, and more in all;
- no wrong verdict: the matching joint never "differs"; a joint 30 % heavier never
  "within" (it "differs" wherever the record is measured).
"""

from __future__ import annotations

import collections
import math
import struct
import types

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.drivers import transport as tp
from hapsim.host.telemetry import FLAG_ESTIMATED
from test_haply_lossy_verdict import N_TICKS, host_loop, sim_board
from test_haply_silence import StarvedBoardPort

SEEDS = range(6)


@pytest.fixture(scope="module")
def prep():
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    return prepare_run(load_scene("configs/haply.yaml"),
                       RunOptions(driver="haply", rt_priority=0, handle_signals=False,
                                  duration=N_TICKS * 1e-3))


def _windows(rng):
    """30 to 80 short starvations of the board's reader, 0.3 to 3 ms each, woken 0 to
    0.5 ms after (a loaded board process: its replies miss the host's tick and come with
    the next), spread over the run after its first 50 ms."""
    out, t = [], 0.05
    for _ in range(int(rng.integers(30, 81))):
        t += float(rng.uniform(0.002, 0.03))
        d, w = float(rng.uniform(3e-4, 3e-3)), float(rng.uniform(0.0, 5e-4))
        if t + d + w > N_TICKS * 1e-3 - 0.02:
            break
        out.append((t, t + d, w))
        t += d + w
    return out


def _late_run(monkeypatch, prep, seed, p, heavier=1.0):
    """One run: the starved board (:func:`_windows`), bytes lost with probability ``p``
    each way (seeded), the board's joint ``heavier`` times the scene's inertia. Returns
    the transport, the driver, the telemetry columns, the measurement, the torque bytes
    sent per command (``seq -> bytes``) and the board's replies per write it parsed
    (``(torque bytes parsed, angle [deg])``, in order)."""
    from hapsim.pipeline.runner import identify_run
    clock, sc, dev, drv, board = sim_board(monkeypatch, prep, heavier)
    # the board's truth: each write it parsed for the joint's id, its torque's bytes and
    # the angle its reply read (the firmware's read_encoder_value, before the wire)
    replies, last = [], [None]
    angle, commands = board.angle_deg, board.decoder.commands

    def angle_deg(port=0):
        a = angle(port)
        last[0] = a
        return a

    def parsed(data):
        for c in commands(data):
            last[0] = None
            yield c                       # (the board applies it and reads its angle)
            if c[0] == "write" and c[1] == drv.id and c[2].get(0) is not None:
                replies.append((struct.pack("<f", c[2][0]), last[0]))
    board.angle_deg, board.decoder.commands = angle_deg, parsed
    rng = np.random.default_rng(2950 + seed)
    tr = tp.DriverTransport(drv, "loop://", inertia=dev.mass)
    tr._ser.close()
    tr._ser = StarvedBoardPort(clock, board, _windows(rng), (),
                               {"drop_rx": p, "drop_tx": p, "seed": 2950 + seed} if p
                               else None)
    sent = {}
    command = tr._command

    def command_logged(data, force=0.0):
        command(data, force)
        sent[tr._cmd] = bytes(data)
    tr._command = command_logged
    tr.send(fp.Config(1000.0, 5000, 10.0))
    cols = host_loop(tr, drv, sc, clock)
    n = cols["seq"].size
    tel = types.SimpleNamespace(wrapped=False, n=n, head=n, columns=lambda *a: cols)
    m = identify_run(prep, tel, None, driver=drv)
    return tr, drv, cols, m, sent, replies


def _kept(drv, cols, late):
    """Rows the account leaves in (not unknown), with the late replies or without."""
    keep = drv.late_answers
    drv.late_answers = keep if late else None
    try:
        cut = drv.unknown_force_rows(cols)
    finally:
        drv.late_answers = keep
    return int(cols["seq"].size if cut is None else np.count_nonzero(~cut))


@pytest.mark.parametrize("p", [0.0, 0.005])
def test_late_replies_are_the_boards_readings_and_more_rows_are_kept(monkeypatch, prep,
                                                                       p):
    """Seeds 0-5 of the starved board, with and without loss: each late reply recorded
    is the board's own reply to that write (exact), and the kept rows rise."""
    checked = gained = 0
    for seed in SEEDS:
        tr, drv, cols, m, sent, replies = _late_run(monkeypatch, prep, seed, p)
        est = (cols["flags"] & FLAG_ESTIMATED) != 0
        assert est.any()                      # the class happened: replies missed ticks
        by_torque = collections.Counter(b for b, _ in replies)
        sent_torque = collections.Counter(d[2:6] for d in sent.values() if len(d) == 6)
        for s, x in tr.late_answers.items():
            assert est[cols["seq"] == s].all()          # an estimated tick's command
            b = sent[s][2:6]
            if by_torque[b] != 1 or sent_torque[b] != 1:
                continue                      # a torque written twice: not matched
            a = next(a for bb, a in replies if bb == b)
            assert x == math.radians(struct.unpack("<f", struct.pack("<f", a))[0]), (
                seed, s, x, a)
            checked += 1
        old, new = _kept(drv, cols, False), _kept(drv, cols, True)
        assert new >= old, (seed, old, new)
        gained += new - old
        assert m.get("verdict", "").find("differs") < 0, (seed, m.get("verdict"))
    assert checked >= 50, checked            # the class was tested (many late replies)
    assert gained > 0


@pytest.mark.parametrize("p", [0.0, 0.005])
@pytest.mark.parametrize("seed", range(3))
def test_a_heavier_joint_is_never_within(monkeypatch, prep, seed, p):
    """A joint 30 % heavier than the scene says, the board starved, the link lossy or
    not: the rows kept from late replies do not make it "within"; without loss every
    record is measured and "differs" (seeds 0-7 measured: 8 of 8; with loss 1 of 8
    "differs", the others "not measurable")."""
    tr, drv, cols, m, sent, replies = _late_run(monkeypatch, prep, seed, p, heavier=1.3)
    assert tr.late_answers                   # late replies were kept
    assert m.get("within") is not True, (m.get("verdict"), m.get("k"), prep.pred["k"])
    if p == 0.0:
        assert "differs" in m.get("verdict", ""), m.get("verdict")

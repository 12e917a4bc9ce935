"""The 2DIY's wiring checked before any torque loop (issues 20 and 23): on the emulated
board (firmware V1.5's separate direction bytes per motor and encoder), every wiring of
the two joints' motors and encoders, each as Haply wires it or reversed."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from hapsim.emulated.haply2_board import BoardLink, Haply2DIYBoard
from hapsim.drivers.haply2 import GENERATIONS, Haply2DIY
from hapsim.drivers.haply2_probe import find_directions
from hapsim.errors import IdentificationError
from hapsim.scene import load_scene_nd

WALL = Path(__file__).resolve().parent.parent / "configs" / "pantograph_wall.yaml"
_SCENE = []


def _scene():
    if not _SCENE:
        _SCENE.append(load_scene_nd(WALL))
    return _SCENE[0]


def _probe(board, drv):
    q0 = [math.degrees(v) for v in _scene().device.joints]
    return find_directions(drv, BoardLink(board.feed), q0, force_limit=0.05, envelope=0.1,
                           pace=False, timeout=0.0)


def _turns_true(board, drv, j):
    """With ``drv``'s set-up, a positive torque on joint ``j``: (how far its reading
    moved, how far the joint itself turned) [rad], from the same start."""
    q0 = [math.degrees(v) for v in _scene().device.joints]
    link = BoardLink(board.feed)
    link.write(drv.arm_bytes(q0))
    dec = drv.decoder()
    link.read(0.0)
    r0, t0 = drv.joints_of(dec.feed(board.feed(drv.write_bytes((0.0, 0.0))))[-1])[j], \
        board.plant.joints()[j]
    tau = (0.03, 0.0) if j == 0 else (0.0, 0.03)
    for _ in range(25):
        rep = dec.feed(board.feed(drv.write_bytes(tau)))
    board.feed(drv.write_bytes((0.0, 0.0)))
    return drv.joints_of(rep[-1])[j] - r0, board.plant.joints()[j] - t0


# (m1, e1, m2, e2): every wiring on gen3; on gen2 (other direction bytes) as Haply wires
# it, one motor reversed, one encoder reversed, and both of one joint reversed
WIRINGS = [("gen3", w) for w in itertools.product((1, -1), repeat=4)] + [
    ("gen2", w) for w in ((1, 1, 1, 1), (-1, 1, 1, 1), (1, 1, 1, -1), (-1, -1, 1, 1))]


@pytest.mark.parametrize("gen,w", WIRINGS)
def test_every_wiring_is_found_and_corrected_or_refused(gen, w):
    """Over the wirings (each joint's motor and encoder as Haply wires them or
    reversed): a joint with exactly one of them reversed is refused, naming exactly those
    joints and the two corrections; the correction that matches the board then passes
    the probe, and a positive torque turns the joint the way its angle counts up *and*
    the reading follows the joint (the loop is right). A joint with both reversed passes
    (no pulse shows it) and its reading is mirrored: the stated limit. The board is left
    at zero torque after every probe, refused or not."""
    sc = _scene()
    g = GENERATIONS[gen]
    m1, e1, m2, e2 = w
    wiring = ((m1, e1), (m2, e2))
    bad = [j for j, (m, e) in enumerate(wiring) if m * e < 0]
    board = Haply2DIYBoard(sc, gen, wiring=wiring, amplitude=1e-4, clock="lockstep")
    drv = Haply2DIY(gen)
    if bad:
        with pytest.raises(IdentificationError) as ei:
            _probe(board, drv)
        msg = str(ei.value)
        assert board.settles_on() == 0.0
        for j in range(2):
            assert (f"joint {j + 1}" in msg.split("turned")[0]) == (j in bad), msg
        mfix = tuple(1 - b if k in bad else b for k, b in enumerate(g.motor_direction))
        efix = tuple(1 - b if k in bad else b
                     for k, b in enumerate(g.encoder_direction))
        assert f"motor_direction={mfix}" in msg and f"encoder_direction={efix}" in msg
        # the correction that matches the board: the motor byte where the motor is
        # reversed, the encoder byte where the encoder is
        mfix = tuple(1 - b if wiring[k][0] < 0 and k in bad else b
                     for k, b in enumerate(g.motor_direction))
        efix = tuple(1 - b if wiring[k][1] < 0 and k in bad else b
                     for k, b in enumerate(g.encoder_direction))
        drv = Haply2DIY(gen, motor_direction=mfix, encoder_direction=efix)
        board = Haply2DIYBoard(sc, gen, wiring=wiring, amplitude=1e-4, clock="lockstep")
    p = _probe(board, drv)
    assert p.relative == (1, 1)
    assert all(t[0] > 0 > t[1] and max(map(abs, t)) <= 0.05 for t in p.torque)
    assert all(c[0] > 0 > c[1] for c in p.counts)
    assert board.settles_on() == 0.0
    for j in range(2):
        read, turned = _turns_true(Haply2DIYBoard(sc, gen, wiring=wiring,
                                                  amplitude=1e-4, clock="lockstep"), drv, j)
        assert read > 2 * 2 * math.pi / drv.resolution
        both = wiring[j][0] < 0 and wiring[j][1] < 0
        assert np.sign(turned) == (-1 if both else 1), (wiring, j, read, turned)


def test_a_reversed_motor_is_refused_before_the_real_time_loop_over_a_pty():
    """``measure_felt_haply2_port`` on the board in a child process whose joint 2 motor
    is wired backwards: the wiring probe refuses it before any record (no torque loop
    ran: the board took the probe's writes only) and leaves it at zero torque; given the
    motor byte the refusal names, the same board passes the probe."""
    from hapsim.pipeline.haply2_embedded import Embedded2DIY
    from hapsim.pipeline.haply2_host import measure_felt_haply2_port
    from hapsim.lockstep import identification_plan
    sc = _scene()
    N = 40
    plan = identification_plan(sc, N)
    child = Embedded2DIY(str(WALL), "gen3", amplitude=1e-4, wiring=((1, 1), (-1, 1)))
    try:
        with pytest.raises(IdentificationError, match=r"joint 2 turned its angle down.*"
                                                      r"motor_direction=\(0, 1\)"):
            measure_felt_haply2_port(child.port, sc, "gen3", amplitude=1e-4, samples=N,
                                     plan=plan)
        child.release_slave()
        rep = child.report(5.0)
    finally:
        child.close()
    assert rep is not None and rep["held_at_end"] == 0.0
    assert rep["decoder"]["setups"] == 2                 # the probe's arming and stop
    b = Haply2DIYBoard(sc, "gen3", wiring=((1, 1), (-1, 1)), amplitude=1e-4, clock="lockstep")
    assert _probe(b, Haply2DIY("gen3", motor_direction=(0, 1))).relative == (1, 1)


class _LateLink:
    """The emulated board behind a link whose replies come late on script: each reply
    held back ``lag`` writes with probability ``p`` (seeded; what follows waits too, the
    board answers in order), and the first reply not before ``start_s`` [s] of the host's
    clock (a board process still starting). ``silent``: no reply ever."""

    def __init__(self, board, p=0.0, lag=0, seed=0, start_s=0.0, silent=False):
        import time
        self.board, self.p, self.lag, self.silent = board, p, lag, silent
        self.rng = np.random.default_rng(seed)
        self.start = time.monotonic() + start_s
        self.writes = self.late = 0
        self.queue, self.out = [], b""

    def write(self, data):
        self.writes += 1
        late = self.rng.random() < self.p
        self.late += late
        self.queue.append((self.writes + (self.lag if late else 0), self.board.feed(data)))

    def read(self, timeout):
        import time
        if self.silent or time.monotonic() < self.start:
            return b""
        while self.queue and self.queue[0][0] <= self.writes:
            self.out += self.queue.pop(0)[1]
        out, self.out = self.out, b""
        return out


@pytest.mark.parametrize("seed", [0, 1])
def test_late_replies_are_read_late_not_taken_for_a_silent_board(seed):
    """A loaded host (or board process): a reply in 25 comes two writes late, more
    than 20 over the probe but never 20 writes in a row without one. The probe reads
    them late (the board answers every write, in order) and finds the wiring, as on a
    prompt link; it used to refuse with "more than 20 missing replies"."""
    q0 = [math.degrees(v) for v in _scene().device.joints]
    link = _LateLink(Haply2DIYBoard(_scene(), "gen3", clock="lockstep"), p=0.04, lag=2, seed=seed)
    r = find_directions(Haply2DIY("gen3"), link, q0, force_limit=0.05, envelope=0.1,
                        pace=False, timeout=1e-4)
    assert link.late > 20
    assert r.relative == (1, 1)


def test_a_board_still_starting_is_waited_for_and_a_silent_one_refused():
    """The first write's reply is waited for ``first_timeout`` (a board process still
    loading when the port opened: the probe is the first to talk to it); a board that
    never answers is refused after 21 writes in a row without a reply, naming the rule."""
    from hapsim.errors import DeviceError
    q0 = [math.degrees(v) for v in _scene().device.joints]
    link = _LateLink(Haply2DIYBoard(_scene(), "gen3", clock="lockstep"), start_s=0.2)
    r = find_directions(Haply2DIY("gen3"), link, q0, force_limit=0.05, envelope=0.1,
                        pace=False, timeout=0.0, first_timeout=5.0)
    assert r.relative == (1, 1)
    link = _LateLink(Haply2DIYBoard(_scene(), "gen3", clock="lockstep"), silent=True)
    with pytest.raises(DeviceError, match="more than 20 writes in a row"):
        find_directions(Haply2DIY("gen3"), link, q0, force_limit=0.05, envelope=0.1,
                        pace=False, timeout=0.0)
    assert link.writes == 21 + 1                  # and the stop's zero torque

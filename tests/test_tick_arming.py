"""The arming's placement of the Hapkit sketch's tick boundary survives a burst of late
replies in one sweep of its probes.

The writes to a ticking board are timed once, at the first arming
(:meth:`hapsim.drivers.tick_align.TickAligned.tick_phase`), and never re-timed. Beside two
CPU-bound processes and two other real-time test modules, one run in 36 placed the
boundary 0.39-0.41 of a tick off (its stop's 8 placements agreeing on it; its arming's
sweep had 14 of 16 probes answered and fitted cleanly with a flat part of 744 us where
the sketch's is 434): 283 of its 478 commands came within a tenth of a tick of the
boundary, where the board takes a command at one tick or the next by the host's jitter.
The sweeps of those runs show why: the replies to a few probes in a row come 0.2-0.45 of a
tick late together (the host or the board descheduled), a shape the fit can take for a
shifted jump. Now two sweeps must agree (:data:`hapsim.drivers.tick_align.ARM_AGREE`),
the later taken.

In process, on a simulated clock shared by the host and the board (no real time,
:class:`test_hapkit_serial_tick.SimClock`): the sketch's loop on a tick of a seeded phase
and link transit; one of the arming's first three sweeps has a burst of 3-6 consecutive
replies 0.2-0.45 of a tick late, seeded. The arming must place the boundary within the
agreement's bound in every seed, or refuse (no alignment: the writes unaligned, which the
run reports; a wrong alignment it does not).
"""

from __future__ import annotations

import numpy as np
import pytest

from test_hapkit_serial_tick import BYTE_NS, TICK_NS, TickingPort, _transport  # same dir

from hapsim.drivers import tick_align


class LateBurstPort(TickingPort):
    """The sketch's tick (:class:`TickingPort`, ``sketch=True``) whose replies to the
    writes numbered in ``late`` (1, 2, ... as written) come ``late[n]`` [ns] later: the
    host's read of them, or the board's write, delayed by the machine's load."""

    def __init__(self, phase_ns: int, transit_ns: int, late: dict) -> None:
        super().__init__(phase_ns, transit_ns, sketch=True)
        self.late = dict(late)

    def write(self, data: bytes) -> int:
        n = super().write(data)
        d = self.late.get(self.writes, 0)
        if d:
            ready, reply = self.pending.pop()
            self.pending.append((ready + int(d), reply))
        return n


def _burst(seed: int) -> tuple:
    """A seeded board (phase, transit [ns]) and a burst of late replies within one of the
    arming's first three sweeps (writes 2-17, 18-33, 34-49: one wake-up write, then 16
    probes each; a refused sweep moves the later ones, which only spreads the burst)."""
    rng = np.random.default_rng([seed, 77])
    phase = int(rng.integers(0, TICK_NS))
    transit = int(rng.integers(0, 2_000_000))
    sweep = int(rng.integers(0, 3))
    first = 2 + 16 * sweep + int(rng.integers(0, 12))
    late = int(rng.uniform(0.2, 0.45) * TICK_NS)
    return phase, transit, {w: late for w in range(first, first + int(rng.integers(3, 7)))}


@pytest.mark.parametrize("seeds", [range(0, 40)], ids=["40 seeds"])
def test_a_burst_of_late_replies_in_one_sweep_moves_no_alignment(monkeypatch, seeds):
    """Over 40 seeds (0.15 CPU-s), each a board and a burst in one sweep (module notes):
    the arming aligns the writes on a boundary within ``ARM_AGREE + 1/8`` of a tick of the
    truth, or refuses; and it aligns in at least 36 of 40. The bound, derived: the
    placement taken agrees with another within :data:`~hapsim.drivers.tick_align.ARM_AGREE`,
    so a burst's placement taken is at most that from a clean one, beside the clean one's
    own error (an eighth: the single placement's bound,
    ``test_the_probe_finds_the_boundary_and_the_writes_come_mid_tick``); 0.275 of a tick,
    where the writes put half a tick after it stay 0.225 from the boundary. Measured over
    1,000 seeds: 0.158 at worst (margin 1.7), all aligned. Before the agreement (one
    sweep): 1 of these 40 off by more (0.42) and 6 refused; 29 of 1,000 off by more, 0.50
    at worst."""
    aligned = 0
    bound = (tick_align.ARM_AGREE + 1 / 8) * TICK_NS
    for seed in seeds:
        phase, transit, late = _burst(seed)
        port = LateBurstPort(phase, transit, late)
        tr = _transport(monkeypatch, port)
        found = tr.tick_phase()
        if found is None:
            continue
        aligned += 1
        truth = (port.phase - port.transit - BYTE_NS) % TICK_NS
        err = (tr._write_at - truth + TICK_NS // 2) % TICK_NS - TICK_NS // 2
        assert abs(err) <= bound, (seed, err / TICK_NS, found, sorted(late))
        assert found["placements"] >= 2
    # (three sweeps of which two clean ones agree unless the burst spreads over two)
    assert aligned >= 36, aligned


def test_placements_agree_only_within_the_band():
    """:func:`~hapsim.drivers.tick_align.agreeing_placement`: a placement within
    :data:`~hapsim.drivers.tick_align.ARM_AGREE` of a tick of an earlier one (folded:
    whole ticks apart count as none) is taken as it is; further from all of them, none."""
    tk = TICK_NS
    q = int(tick_align.ARM_AGREE * tk) - 1          # (1 ns inside: no float's edge)
    new = (1_000_000 + 7 * tk + q, 30)
    assert tick_align.agreeing_placement([(1_000_000, 10)], new, tk) == new
    assert tick_align.agreeing_placement([(0, 0)], (q + 3, 1), tk) is None
    assert tick_align.agreeing_placement([(0, 0)], (-3 * tk - q, 1), tk) == (-3 * tk - q, 1)
    assert tick_align.agreeing_placement([], (0, 0), tk) is None
    # two earlier that disagree (0 and 0.45 of a tick): the one near agrees
    assert tick_align.agreeing_placement([(0, 0), (int(0.45 * tk), 1)], (tk // 2, 2),
                                         tk) == (tk // 2, 2)

"""identify's excitation counts a stall of its own host (issue 29: a device keeps its own
time; the host does not always run).

A device on its own clock holds the last force it received while the host is away. The
excitation reverses its push when the device's *stop ahead* (where it would stop if the
force reversed now) nears the envelope; a host preempted just then leaves the push on for
the whole stall, and the answers to the STATEs that queued meanwhile reach the device late,
in a burst. Before, the stop ahead counted the device's delay and its inertia but not the
stall: beside a process at the loop's own real-time priority a 0.237 kg device ended
0.0016 to 0.009 mm beyond its 10 mm envelope (safety stop, exit 1).

The records here come from a simulation written in this file: the exact zero-order-hold
step of ``m x'' + b0 x' = u`` from the matrix exponential (``scipy.linalg.expm``), a device
ticking at 1 kHz on its own clock that applies the answer to tick ``j`` from tick
``j + d``, or from the tick after it arrives when it arrives later, and a host that answers
every STATE but stalls now and then: the STATEs of a stall are answered in a burst at its
end. The host's clock, as :class:`~hapsim.pipeline.excitation.ExcitationEngine` reads it,
is the simulation's.
"""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from hapsim.pipeline.excitation import (HOST_STALL_PRIOR_S, ExcitationEngine,
                                          excitation_plan)

T = 1e-3
FORCE_LIMIT, ENVELOPE, N = 2.0, 0.01, 4000


def _stalls(rng, n: int, first: float) -> dict[int, int]:
    """Host stalls: start tick -> length [ticks]. One of ``first`` [s] during the quiet
    start (the device at rest), then one every 50-400 ticks, each no longer than the
    longest before it or :data:`HOST_STALL_PRIOR_S`."""
    out = {40: int(round(first / T))}
    longest = max(first, HOST_STALL_PRIOR_S)
    k = 200
    while k < n - 50:
        out[k] = int(rng.integers(1, int(round(longest / T)) + 1))
        k += out[k] + int(rng.integers(50, 400))
    return out


def run_stalled(m: float, b0: float, d: int, stalls: dict[int, int], seed: int,
                clocked: bool = True, applied: np.ndarray | None = None) -> np.ndarray:
    """True positions [m] of a device (mass ``m`` [kg], viscous friction ``b0`` [N s/m],
    delay ``d`` [ticks]) excited by the engine through a host that stalls (module notes);
    ``clocked``: the engine reads the host's clock (a real-time run), else none (lockstep);
    ``applied`` (shape (N,)), when given, receives the force the device held over each
    tick [N] (``tools/identify_noisy_stalls.py`` fits the records with it)."""
    plan = excitation_plan(N, 1.0 / T, FORCE_LIMIT, ENVELOPE, max_delay=20, seed=seed)
    now = [0.0]
    plan.clock = (lambda: now[0]) if clocked else None
    eng = ExcitationEngine(plan)
    eng.set_port_position(0.0)
    E = expm(np.array([[0.0, 1.0, 0.0], [0.0, -b0 / m, 1.0 / m], [0.0, 0.0, 0.0]]) * T)
    x = v = 0.0
    held, held_j = 0.0, -1
    arrivals: list[tuple[int, int, float]] = []     # (tick it acts from, tick answered, force)
    queue: list[tuple[int, float]] = []             # STATEs waiting for a stalled host
    busy_until = -1
    xs = np.empty(N)
    for k in range(N):
        for a in [a for a in arrivals if a[0] <= k]:
            if a[1] > held_j:
                held, held_j = a[2], a[1]
            arrivals.remove(a)
        xs[k] = x
        if k in stalls:
            busy_until = k + stalls[k]
        queue.append((k, x))
        if k >= busy_until:
            # the host answers what queued, now (its clock: this tick's, plus its work)
            for i, (j, y) in enumerate(queue):
                now[0] = k * T + 2e-4 + 1e-6 * i
                f = float(np.clip(eng.port_step(y), -FORCE_LIMIT, FORCE_LIMIT))
                arrivals.append((max(j + d, k + 1) if d else k + 1, j, f))
            queue.clear()
        if applied is not None:
            applied[k] = held
        xn, vn, _ = E @ np.array([x, v, held])
        x, v = float(xn), float(vn)
    return xs


#: Longest first stall [s]: twice a framed device's default watchdog (50 ms), beyond which
#: the device itself zeroes the force it holds (not modelled here: a stricter test).
FIRST_STALL_MAX_S = 0.1


def _case(seed: int):
    rng = np.random.default_rng(7000 + seed)
    m = math.exp(rng.uniform(math.log(0.02), math.log(2.0)))
    b0, d = float(rng.uniform(0.0, 5.0)), int(rng.integers(0, 11))
    return m, b0, d, _stalls(rng, N, float(rng.uniform(0.0, FIRST_STALL_MAX_S)))


@pytest.mark.parametrize("seed", range(40))
def test_stalls_no_longer_than_one_seen_never_take_the_device_out(seed):
    """Property over random devices (m 0.02-2 kg log-uniform, b0 0-5 N s/m, d 0-10) and
    random host stalls: one of 0-100 ms while the device is at rest, then stalls no longer
    than the longest seen (or the prior, :data:`HOST_STALL_PRIOR_S`) at random moments:
    the device never leaves the envelope (the loop's safety stop). Measured over seeds
    0-119: at most 6.0 mm of the 10; over 120-399, 8.8 mm (the excitation before
    2026-11-28: 5.8 and 10.8 mm, 4 of 280 beyond 8 mm -- docs/identify.md)."""
    m, b0, d, st = _case(seed)
    xs = run_stalled(m, b0, d, st, seed)
    assert np.max(np.abs(xs)) < ENVELOPE, (m, b0, d, np.max(np.abs(xs)))


@pytest.mark.parametrize("seed", [126, 219, 345])
def test_an_engine_blind_to_the_stalls_takes_these_devices_out(seed):
    """The property above is not vacuous: the same loops with the engine reading no
    clock (the stop ahead before it counted the stall) leave the envelope (15.1, 14.5 and
    11.6 mm, the three farthest of seeds 120-499; with the clock 1.5-4.1 mm).
    The excitation of 2026-11-28 raises its level only once the device has felt the full
    push of the present one: blind to the clock, 2 of seeds 0-119 leave the envelope
    (before: 7)."""
    m, b0, d, st = _case(seed)
    xs = run_stalled(m, b0, d, st, seed, clocked=False)
    assert np.max(np.abs(xs)) > ENVELOPE


def test_an_engine_rebuilt_after_a_loss_keeps_the_longest_stall():
    """The loop rebuilds its engine after a loss as ``type(engine)(engine.scene)``
    (:mod:`hapsim.host.recovery`), often right after a long stall: the new engine counts
    the stall the old one saw, not the prior."""
    plan = excitation_plan(N, 1.0 / T, FORCE_LIMIT, ENVELOPE, max_delay=20, seed=1)
    now = [0.0]
    plan.clock = lambda: now[0]
    eng = ExcitationEngine(plan)
    eng.set_port_position(0.0)
    for k in range(50):
        now[0] = k * T + (0.04 if k >= 30 else 0.0)      # a 40 ms stall before tick 30
        eng.port_step(0.0)
    # the engine's own arithmetic (the clock between two answers, less a period)
    assert eng.host_stall == (30 * T + 0.04) - 29 * T - T
    assert eng.host_stall > HOST_STALL_PRIOR_S
    again = type(eng)(eng.scene)
    assert again.host_stall == eng.host_stall

"""The braking after a safety stop (:meth:`hapsim.host.recovery.Recovery._brake`).

Zero force alone leaves a moving handle to its friction, which carries it ``v m / b``
further; the host instead brakes it with ``f = -B v``, ``B = g m / T``, then sends zero.
Checked over random devices on the virtual clock (the device keeps its own time: a
real-time mock behind :class:`~hapsim.emulated.links.SimTransport`), the stop a velocity
limit crossed in a free response, so that the device is moving at the stop:

- the travel after the stop (to where the handle comes to rest, the coast after the last
  zero force in closed form, ``x + v m / b``) is within the braking's own bound, and a
  small part of what friction alone gives on the same loop without braking;
- the delayed difference equation ``v(k+1) = v(k) - g v(k-d)`` of the module notes is
  stable at ``g`` for every delay up to 5 (its roots, against the closed-form bound
  ``2 sin(pi / (2 (2 d + 1)))``);
- no braking after a non-finite reading, and a run without a stop does not brake.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.emulated.links import SimTransport
from hapsim.emulated.mock import MockDevice
from hapsim.engine import Engine
from hapsim.host.loop import HostLoop, LoopConfig
from hapsim.host.recovery import BRAKE_GAIN, BRAKE_MAX_S, brake_damping
from hapsim.host.telemetry import Telemetry
from hapsim.scene import parse_scene
from tolerance import roots_tol  # same directory (pytest prepend import mode)

LIMIT = 10.0


def _scene(m, b, d, rate, K, x0):
    return parse_scene(f"""
rate_hz: {rate}
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K}, damping: 0.0}}
device: {{mass: {m}, friction: {b}, delay: {d}, hold: zoh, force_limit: {LIMIT}}}
excitation: {{x0: {x0}}}
""")


class _Spy(HostLoop):
    """Notes the device's true state when the braking starts (the stop's moment)."""

    at_stop = None

    def _brake(self):
        ph = self.transport.mock.physics
        self.at_stop = (ph.x, ph.v)
        return super()._brake()


def _run(scene, rate, d, vlim, braking, mock_cls=MockDevice):
    m = scene.device.mass
    mock = mock_cls(scene.device, scene.excitation, native_rate_hz=rate, lockstep=False)
    tr = SimTransport(mock)
    tr.sent = []
    cfg = LoopConfig(rate_hz=rate, n_samples=int(rate), delay=d, force_limit=LIMIT,
                     velocity_limit=vlim, watchdog_us=200_000,
                     brake_damping=brake_damping(m, rate) if braking else 0.0,
                     brake_rest=1e-4)
    loop = _Spy(Engine(scene), tr, cfg, Telemetry(int(rate)))
    res = loop.run()
    return res, loop.at_stop, mock.physics, tr.sent


def _l1_impulse(g: float, d: int, n: int = 20_000) -> float:
    """Sum of |v(k)| of ``v(k+1) = v(k) - g v(k-d)`` from a unit velocity (its l1 norm)."""
    v = [0.0] * d + [1.0]
    for _ in range(n):
        v.append(v[-1] - g * v[-1 - d])
    return float(np.sum(np.abs(v)))


def _cases(n, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        m = float(rng.uniform(0.02, 1.0))
        b = float(rng.uniform(0.05, 1.0))
        d = int(rng.integers(1, 4))
        rate = float(rng.choice([250.0, 500.0, 1000.0]))
        # a soft spring (well inside the stability region: K T^2 / m <= 0.03 / (d + 1))
        K = float(rng.uniform(0.005, 0.03)) * m * rate ** 2 / (d + 1)
        x0 = 0.01
        vlim = float(rng.uniform(0.3, 0.8)) * math.sqrt(K / m) * x0
        yield m, b, d, rate, K, x0, vlim


@pytest.mark.parametrize("case", list(_cases(12, 7)), ids=lambda c: f"d{c[2]}-{c[3]:.0f}Hz")
def test_the_handle_stops_within_the_brakes_bound_not_the_frictions_coast(case):
    m, b, d, rate, K, x0, vlim = case
    T = 1.0 / rate
    sc = _scene(m, b, d, rate, K, x0)
    res, (xs, vs), ph, sent = _run(sc, rate, d, vlim, True)
    assert res.safety_stop and res.stop_reason.startswith("safety: velocity"), res.stop_reason
    bk = res.brake
    assert bk["damping"] == BRAKE_GAIN * m * rate     # the same two products
    assert bk["ended"] in ("rest", "time") and bk["seconds"] <= BRAKE_MAX_S + 3 * T
    assert bk["late"] == 0             # the virtual clock: the host is never late
    # the last force is zero, then STOP (whatever the braking sent before)
    forces = [msg for msg in sent if type(msg) in (fp.Force, fp.Stop)]
    assert type(forces[-1]) is fp.Stop and forces[-2].force == (0.0,)
    # every braking force opposes the motion's estimate and stays within the limit
    assert all(abs(f.force[0]) <= LIMIT for f in forces[:-1])
    travel = abs(ph.x + ph.v * m / b - xs)          # to rest: the last coast, closed form
    # The braking's bound (module notes of hapsim.host.recovery): the speed at the stop
    # plus what the spring's forces still in flight add over d + 1 periods, carried for
    # those periods and then over the l1 norm of the braking's difference equation.
    vp = abs(vs) + (d + 1) * T * K * abs(xs) / m
    bound = T * vp * ((d + 1) + _l1_impulse(BRAKE_GAIN, d + 1))
    # Measured: the largest travel / bound over 30 random loops of this kind was 1.77 (the
    # host's velocity is a backward difference read a period late, which the bound's
    # d + 1 does not count); 2.5 leaves a margin of 1.4.
    assert travel <= 2.5 * bound, (travel, bound)
    # friction alone (the same loop, no braking) coasts v m / b: at least 5 times further
    res0, (xs0, vs0), ph0, _ = _run(sc, rate, d, vlim, False)
    assert res0.brake == {} and res0.stop_reason == res.stop_reason
    free = abs(ph0.x + ph0.v * m / b - xs0)
    if m / b >= 20.0 * T * (d + 1 + 1.0 / BRAKE_GAIN):
        assert travel * 5.0 <= free, (travel, free)


def _braking_poly(g: float, d: int) -> np.ndarray:
    """Coefficients of ``z^(d+1) - z^d + g`` (highest power first)."""
    poly = np.zeros(d + 2)
    poly[0] = 1.0
    poly[1] -= 1.0
    poly[-1] += g
    return poly


@pytest.mark.parametrize("d", range(0, 6))
def test_the_braking_gain_is_stable_up_to_five_periods_of_delay(d):
    # roots of z^(d+1) - z^d + g = 0 inside the unit circle below the closed-form bound
    # 2 sin(pi / (2 (2 d + 1))) (Levin & May 1976), on it at the bound
    bound = 2.0 * math.sin(math.pi / (2 * (2 * d + 1)))
    assert BRAKE_GAIN < bound
    rho = float(np.max(np.abs(np.roots(_braking_poly(BRAKE_GAIN, d)))))
    rho_b = float(np.max(np.abs(np.roots(_braking_poly(bound, d)))))
    assert rho < 1.0 - 1e-2, rho                  # 1 - rho >= 0.04 at d = 5
    # numpy.roots: eigenvalues of the companion matrix, their round-off bounded by
    # tolerance.roots_tol (Edelman & Murakami 1995)
    assert abs(rho_b - 1.0) <= roots_tol(_braking_poly(bound, d)), rho_b


def test_no_braking_without_a_motion_stop():
    from test_loop_clocks import NanMock
    sc = _scene(0.1, 0.5, 1, 1000.0, 100.0, 0.005)
    res, _, _, sent = _run(sc, 1000.0, 1, math.inf, True, mock_cls=NanMock)
    assert res.stop_reason.startswith("safety: non-finite") and res.brake == {}
    res, _, _, _ = _run(sc, 1000.0, 1, math.inf, True)
    assert res.stop_reason == "duration" and not res.safety_stop and res.brake == {}


def test_a_board_on_its_own_clock_is_braked_at_the_runs_end():
    """A driver's board that keeps its own time (``driver.own_clock``: hardware, or an
    emulated board on the wall clock) is braked at the end of a run that ran its
    duration, as after a motion stop: the handle's travel after the run (to its rest,
    ``x + v m / b`` in closed form after the last zero force) within the braking's
    bound, ``|v| T (d + 1 + 1/g)`` and the rest speed's coast; the same run on a board
    without its own clock (a lockstep mock, its time the commands') is not braked, and
    its handle coasts ``|v| m / b``. Random devices on the virtual clock, the run's end
    mid-swing. Before, the end of a run sent zero force at once: against the independent
    board models of ``tools/independent_boards`` the Haply M3's joint went 1-2 rad past
    its last reading and the Hapkit's paddle to its end stops."""
    import types
    rng = np.random.default_rng(31)
    for _ in range(6):
        m = float(rng.uniform(0.02, 0.2))
        b = float(rng.uniform(0.05, 0.3))
        rate, d = 250.0, 1
        K = float(rng.uniform(0.01, 0.03)) * m * rate ** 2 / (d + 1)
        sc = _scene(m, b, d, rate, K, 0.01)
        n = int(rng.integers(int(0.3 * rate), int(0.6 * rate)))
        travel = {}
        for own in (True, False):
            mock = MockDevice(sc.device, sc.excitation, native_rate_hz=rate, lockstep=False)
            tr = SimTransport(mock)
            tr.driver = types.SimpleNamespace(own_clock=own)
            cfg = LoopConfig(rate_hz=rate, n_samples=n, delay=d, force_limit=LIMIT,
                             watchdog_us=200_000, brake_damping=brake_damping(m, rate),
                             brake_rest=1e-4)
            loop = _Spy(Engine(sc), tr, cfg, Telemetry(n))
            res = loop.run()
            assert res.stop_reason == "duration" and not res.safety_stop
            x_end, v_end = loop.at_stop
            ph = mock.physics
            travel[own] = (abs(ph.x + ph.v * m / b - x_end), abs(v_end))
            assert (res.brake and res.brake["ended"] == "rest") if own else res.brake == {}
        (braked, v), (free, v0) = travel[True], travel[False]
        # the same end; x + v m / b is an invariant of the free motion (the mock's exact
        # ZOH, closed form): equal to round-off, a few ulps a step over < 100 steps
        # (derived: 1e-9 relative is 1e5 ulps)
        assert v == v0 and free == pytest.approx(v * m / b, rel=1e-9)
        assert braked <= v / rate * (d + 1 + 1 / BRAKE_GAIN) + 1e-4 * m / b, (braked, v)
        assert braked < 0.5 * free, (braked, free)


def test_the_braking_damping_of_a_device():
    assert brake_damping(0.1, 250.0) == BRAKE_GAIN * 0.1 * 250.0
    for bad in (0.0, -1.0, math.nan, math.inf):
        assert brake_damping(bad, 250.0) == 0.0
        assert brake_damping(0.1, bad) == 0.0


@pytest.mark.parametrize("brake", [True, False])
def test_the_scenes_safety_brake_key_turns_it_on_and_off(brake):
    """``safety: {brake: false}`` leaves a stop's zero force at once; the default brakes.
    A run of an unstable scene on the virtual clock (the real-time mock), until its
    force-limit stop: ``loop.brake`` and ``loop.safety.brake_damping`` say which."""
    from hapsim.pipeline.runner import run_scene
    sc = parse_scene(f"""
rate_hz: 250
masses:
  - {{name: handle, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: spring, kind: spring_damper, between: [handle, wall], stiffness: 150.0, damping: 0.0}}
device: {{mass: 0.1, friction: 0.3, delay: 1, hold: zoh, force_limit: 2.0}}
excitation: {{x0: 0.01}}
safety: {{brake: {str(brake).lower()}}}
""")
    rep = run_scene(sc, allow_unstable=True, transport="sim",
                    handle_signals=False)
    loop = rep["loop"]
    assert loop["safety_stop"], loop["stop_reason"]
    if brake:
        assert loop["safety"]["brake_damping"] == BRAKE_GAIN * 0.1 * 250.0
        assert loop["brake"] and loop["brake"]["periods"] > 0
    else:
        assert loop["safety"]["brake_damping"] == 0.0 and loop["brake"] is None

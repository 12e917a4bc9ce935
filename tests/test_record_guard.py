"""The safety of an n-D record over a port (:mod:`hapsim.pipeline.record_guard`): the 1-D
host loop's position bound, lateness guard and braking at ``n`` axes (issue 30: every
capability in every dimension). Device models keep their own clock (the n-axis mock on
:class:`~hapsim.emulated.links.SimTransport`'s virtual clock, faults seeded): a host
late for the device is late, never waited for."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import firmware_protocol as fp
from from_file import load_module  # same directory
from hapsim.analysis.late_growth import late_growth
from hapsim.analysis.scene_check import closed_loop_nd
from hapsim.braking import BRAKE_MAX_S, brake_text
from hapsim.pipeline.record_guard import RecordGuard
from hapsim.scene import parse_scene, parse_scene_nd
from seeds import seeds
from tolerance import measured

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ROOT = Path(__file__).resolve().parent.parent


#: tools/late_guard.py as a module: the n-D cases' scenes, links and runs
lg = load_module(ROOT / "tools" / "late_guard.py")
A, _text, _measure, _stopped_at = lg.ND_A, lg.nd_text, lg.nd_measure, lg.stopped_at


def _ended_with_zero_then_stop(sent, n):
    """The last FORCE the host sent is zero, and STOP came after it."""
    i = max(j for j, s in enumerate(sent) if type(s) is fp.Force)
    return sent[i].force == (0.0,) * n and any(type(s) is fp.Stop for s in sent[i:])


# (seed 40: a delay at which one of a double pole's halves is lost to round-off, which
# raised before the poles were offered again; 1 of seeds 0-59)
@pytest.mark.parametrize("seed", [*range(8), 40])
def test_a_symmetric_planar_loops_growth_tables_are_its_1d_twins(seed):
    """A 2-D cartesian device of one mass and friction on each axis and one spring-damper
    to a point is the 1-D loop twice: the lateness guard's tables made from the n-D
    closed loop's eigenvalues (:func:`hapsim.analysis.scene_check.closed_loop_nd`) are
    the 1-D scene's, made from its THS map (:func:`hapsim.analysis.prediction.
    predicted_poles`, another model of the same loop), each mode twice: its double poles,
    split by round-off, are followed as two modes."""
    rng = np.random.default_rng(40 + seed)
    m, b0, K, B = (rng.uniform(0.05, 0.3), rng.uniform(0.1, 1.5), rng.uniform(200, 4000),
                   rng.uniform(0.0, 4.0))
    d = int(rng.integers(1, 3))
    two = parse_scene_nd(_text(2, [m, m], [b0, b0], K, B, d), "<2-D>")
    one = parse_scene(f"rate_hz: 1000\nmasses:\n  - {{name: hand, kind: port}}\n"
                      f"  - {{name: c, kind: ground, x0: 0.0}}\nlinks:\n"
                      f"  - {{name: s, kind: spring_damper, between: [hand, c], "
                      f"stiffness: {K!r}, damping: {B!r}}}\ndevice: {{mass: {m!r}, "
                      f"friction: {b0!r}, delay: {d}, hold: zoh}}\n", "<1-D>")
    g2, g1 = late_growth(two, 0.02), late_growth(one, 0.02)
    assert (g2.stable_to, g2.step, g2.delay) == (g1.stable_to, g1.step, g1.delay)
    t1, t2 = g1.array(), g2.array()
    assert t2.shape[0] == min(2 * t1.shape[0], 4)
    # measured 2.3e-9 over 300 such scenes (seeds 40-339; the same on OpenBLAS's
    # Sandybridge kernels; the tables sum ln|z| over up to 21 delays, and the poles near
    # the delay line's z = 0 are clustered, where a root's round-off grows), margin 100:
    # 2.3e-7, six decades below the stop's ln 2
    tol = measured(2.3e-9, 100)
    for row in t2:
        assert np.min(np.max(np.abs(t1 - row), axis=1)) < tol
    assert np.max(np.abs(t2[0] - t1[0])) < tol            # the mode that grows most


@pytest.mark.parametrize("seed", seeds(range(1, 9), kept=[3, 5]))
def test_on_a_late_link_the_guard_stops_what_runs_away_and_never_what_decays(seed):
    """Random 2-D and 3-D loops stable on time, each measured on a late link (seeded
    frames held 3-12 ms) without the lateness guard and with it (the position bound,
    20 a, on both):

    - where the records decay without the guard (every record's last 60 rows below half
      its first 60), the guard never stops the measurement;
    - where a record runs to the position bound without the guard, the guard stops the
      measurement no later (the two runs are the same, frame for frame, until the first
      stop), and sooner in all of a seed's cases but one at most;
    - every stop ends with the zero FORCE and STOP, the braking given up at once to a
      device applying none of the host's FORCEs (on such a link, every stop here);
    - and the same loops on a link that holds nothing are never stopped.

    (``python tools/late_guard.py --family n-D --seeds 11 12 13 14 15 --cases 16``, 80
    such cases: 23 ran away,
    22 stopped sooner by the guard; 16 decayed, none stopped; of the 41 others the guard
    stopped 9, and the record it stopped grew without the guard in 7 of them, 1.5-12
    times; the other two, 0.65 and 0.82, were of loops that grew in other records.)"""
    rng = np.random.default_rng(seed)
    seen = {"ran away": 0, "decayed": 0, "other": 0}
    sooner = 0
    for _ in range(8):
        sc, faults, fseed = lg.nd_case(rng)
        (off, _), (on, tr) = (_measure(sc, faults, fseed, False),
                              _measure(sc, faults, fseed, True))
        assert off["stop"] == "end" or off["stop"].startswith("safety: position")
        kind = lg.nd_kind(off)
        if kind == "ran away":
            assert on["stop"].startswith("safety"), (faults, on["stop"])
            assert _stopped_at(on) <= _stopped_at(off), (faults, on["rows"], off["rows"])
            sooner += lg.late_stop(on) and _stopped_at(on) < _stopped_at(off)
        elif kind == "decayed":
            assert on["stop"] == "end", (faults, on["stop"])
        seen[kind] += 1
        if on["stop"].startswith("safety"):
            assert on["safety"]["stop"] == on["stop"]
            assert _ended_with_zero_then_stop(tr.sent, sc.dimension), tr.sent[-4:]
        clean, _ = _measure(sc, None, 0, True)
        assert clean["stop"] == "end" and clean["safety"]["stop"] is None
    # (a slow growth is left to the bound, as in 1-D: a soft spring, 649 N/m, whose
    # records crept out over four records on a link holding 28 % of the frames 11 ms,
    # seed 6, the one such case of seeds 1-8; 1 of the 23 in the 80 cases below)
    assert sooner >= seen["ran away"] - 1, (sooner, seen)
    # each seed takes one of the two claims at least (the kept ones, 3 and 5, both)
    assert seen["ran away"] + seen["decayed"] >= 1, seen
    if seed in (3, 5):
        assert seen["ran away"] >= 1 and seen["decayed"] >= 1, seen


@pytest.mark.parametrize("n", [2, 3])
def test_an_unstable_loop_is_stopped_at_its_bound_and_braked_to_rest(n):
    """A loop unstable on time (measured with ``--allow-unstable``) on a link that holds
    nothing runs to the position bound, ``max(0.1 m, 20 a)``, which stops it; the host
    then brakes the handle, ``F = -B v`` with ``B = g M / T`` (hapsim.braking), to rest
    (three speeds below the rest speed) within :data:`hapsim.braking.BRAKE_MAX_S`,
    where zero force would have left it on its friction alone. With ``safety: {brake:
    false}`` the zero FORCE follows at once."""
    m, b0 = [0.1, 0.15, 0.12][:n], [0.3, 0.5, 0.4][:n]
    sc = parse_scene_nd(_text(n, m, b0, 20000.0, 5.0, 1), "<unstable>")
    assert max(abs(np.linalg.eigvals(closed_loop_nd(sc)[0]))) > 1.0
    res, tr = _measure(sc, None, 0, True)
    assert res["stop"].startswith("safety: position") and res["incomplete"]
    br = res["safety"]["brake"]
    guard = RecordGuard(sc, A, None, 1e9)
    assert br["ended"] == "rest" and br["seconds"] <= BRAKE_MAX_S
    assert np.max(np.abs(br["v_start"])) > 100 * guard.rest_speed
    assert np.max(np.abs(br["v_end"])) < guard.rest_speed
    np.testing.assert_array_equal(br["damping"], 0.25 * np.diag(m) * 1000.0)
    forces = [s for s in tr.sent if type(s) is fp.Force]
    assert len(forces) >= br["periods"] and _ended_with_zero_then_stop(tr.sent, n)
    free = parse_scene_nd(_text(n, m, b0, 20000.0, 5.0, 1, brake=False), "<no brake>")
    res, tr = _measure(free, None, 0, True)
    assert res["stop"] == "safety: " + res["safety"]["stop"][len("safety: "):]
    assert res["safety"]["brake"] is None and res["safety"]["brake_damping"] is None
    assert _ended_with_zero_then_stop(tr.sent, n)


@pytest.mark.xdist_group("realtime")
def test_hapsim_run_reports_a_safety_stop_of_a_2d_run_and_exits_1():
    """``hapsim run`` of a 2-D scene over the embedded mock (real time) on a link that
    holds a third of the device's frames 4 ms: the guard stops the run, the text says why
    and what the host did after, ``--json`` carries it (``stop``, ``safety``), and the
    exit code is 1 (a safety stop, as in 1-D)."""
    from inproc import hapsim_main
    args = ["run", str(CONFIGS / "pantograph_wall.yaml"), "--amplitude", str(A),
            "--faults", "spike=0.3:4ms", "--fault-seed", "1"]
    code, out, err = hapsim_main(args)
    assert code == 1, (out, err)
    assert "stopped: safety: the host's FORCEs came too late" in out, out
    assert "verdict: not measurable" in out, out
    # what the host did after: one braking line, whichever the device's last STATE
    # allowed (most often none: the device had applied none of the late FORCEs; on a
    # loaded machine the stop can come where it had, and the braking runs, once in a
    # fresh clone's CI)
    assert len(re.findall(_BRAKE_LINE, out)) == 1, out
    code, out, err = hapsim_main(args + ["--json"])
    assert code == 1, (out, err)
    rep = json.loads(out)
    assert rep["stop"].startswith("safety: ") and rep["verdict"] == "not measurable"
    sf = rep["safety"]
    assert sf["stop"] == rep["stop"] and sf["position_limit"] == 0.1
    br = sf["brake"]
    assert sf["late_guard"]["modes"] >= 1 and br["ended"] in ("ignored", "rest", "time"), br
    assert br["periods"] > 0 or br["ended"] == "ignored", br   # (none run: none applied)
    assert re.fullmatch(_BRAKE_LINE, brake_text(br)), brake_text(br)


#: The report's line of what the host did after a safety stop
#: (:func:`hapsim.braking.brake_text`): no braking, or a braking and how it ended.
_BRAKE_LINE = (r"(no braking after the stop: the device applied none of the host's FORCEs"
               r"[^\n]*|braked after the stop: damping [^\n]* ended: (rest|time|ignored)"
               r"[^\n]*)")


def test_a_port_that_fails_under_the_braking_ends_the_measurement_on_its_stop(monkeypatch):
    """The port fails as the braking begins (a cable pulled): the braking ends ("port"),
    the measurement ends at once on its safety stop, reported, with no wait for the port
    to come back (a lost port is otherwise waited for, ``reconnect_time``)."""
    from hapsim.emulated.links import SimTransport
    from hapsim.emulated.mock import MockDeviceND
    from hapsim.errors import DeviceError
    from hapsim.pipeline import record_guard
    from hapsim.pipeline.felt_port import measure_felt_port

    class Pulled:
        """A transport whose port is gone once ``gone`` is set."""

        def __init__(self, inner):
            self.inner, self.gone, self.reopens = inner, False, 0

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def send(self, msg):
            if self.gone:
                raise DeviceError("write failed: the port vanished")
            self.inner.send(msg)

        def receive(self, timeout=0.0):
            if self.gone:
                raise DeviceError("read failed: the port vanished")
            return self.inner.receive(timeout)

        def reopen(self):
            self.reopens += 1
            raise DeviceError("no such port")

    brake = record_guard.RecordGuard._brake

    def pulled_at_the_brake(self, transport, *args):
        transport.gone = True
        return brake(self, transport, *args)
    monkeypatch.setattr(record_guard.RecordGuard, "_brake", pulled_at_the_brake)
    sc = parse_scene_nd(_text(2, [0.1, 0.15], [0.3, 0.5], 20000.0, 5.0, 1), "<unstable>")
    tr = Pulled(SimTransport(MockDeviceND(sc, lockstep=False, amplitude=A)))
    t0 = tr.clock()
    res = measure_felt_port(tr, sc, amplitude=A, reconnect_time=10.0)
    assert res["stop"].startswith("safety: position") and res["incomplete"]
    assert res["safety"]["brake"]["ended"] == "port" and tr.reopens == 0
    assert tr.clock() - t0 < 2.0                # no 10 s wait for the port

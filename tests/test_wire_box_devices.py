"""The Falcon's and the Hapkit pantograph firmware's felt statements over the wire's error
box (issue 29; :mod:`hapsim.analysis.wire_box`): refits of records moved by errors inside
the bounds each device states never move a stated component by more than its stated term;
a matching device is never "differs", one with 30 % more inertia still is where the
statement is made; and the first-order term at the records alone, which both verdicts
stated before, was exceeded on each device's shipped spring field at its own counts. At
the finer counts the refit tests draw, the search stays within the first-order term
(measured over seeds 0-7 of the Falcon's family, 100 samples, and eight of the
pantograph's, 150: at most 0.76 and 0.82 of it), and within 0.22 and 0.35 of the box's
stated term (the box stating 89 of the 177 components the first-order term stated on
the Falcon's, 48 of 58 on the pantograph's).

The records are the loop's own free responses on the simulated lockstep clock (named:
:class:`hapsim.lockstep.LockstepND`), the errors fed back through the loop by it (an
independent path from the superposition :func:`hapsim.analysis.wire_box.moved_records`
uses); what is stated is the box's term of each device's bounds: the Falcon's (half an
encoder count per leg reading, half a motor command per torque; the Falcon's verdict
stated it until its rounding term, :mod:`hapsim.analysis.wire_rounding`, and the 2DIY's
verdict still takes the box for its errors that are no rounding) and
:func:`hapsim.emulated.pantograph_board.wire_term` (half a sensor count plus a binary32
ulp per joint reading, half a PWM step plus the torque's binary32 rounding). The devices'
counts are drawn finer than their own where a statement is to be made: at their own
counts (the Falcon's 6.35e-4 rad, the Hapkit's 10-bit sensor and 8-bit PWM) the box
states nothing on these loops (tests/test_falcon_spring.py, tests/test_pantograph_firmware.py).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
from hapsim.analysis.pencil import felt_sensitivity_nd, filtered_sensitivity_nd, fit_felt_nd
from hapsim.kinematics import device
from hapsim.lockstep import (LockstepND, error_responses, excitation_starts,
                             identification_plan, wire_terms_nd)
from hapsim.scene import parse_scene_nd
from tests.test_wire_box import _loop as _pantograph_loop, _statements

ROOT = Path(__file__).resolve().parent.parent
SPRING = (ROOT / "configs" / "falcon_spring.yaml").read_text()
HAPKIT_H = (ROOT / "firmware_protocol" / "firmware" / "hapkit"
            / "hapkit_geometry.h").read_text()
#: The Falcon's largest hand start on configs/falcon_spring.yaml [m]
#: (:func:`hapsim.emulated.falcon_felt.felt_feasibility`'s ``amplitude_m``, 3.77 mm:
#: tests/test_falcon_spring.py recomputes it).
SPRING_START = 3.77e-3


def _hapkit(name: str) -> float:
    return float(re.search(rf"#define {name} ([0-9.]+)", HAPKIT_H).group(1))


#: The pantograph firmware's HELLO scales (firmware_protocol/firmware/pantograph/
#: pantograph.c, PG_RAD_PER_COUNT and 1 / PG_STEPS_PER_NM): joint angle per sensor count
#: [rad] and joint torque per PWM step [N m].
HAPKIT_RAD_PER_COUNT = (_hapkit("HK_SENSOR_PERIOD_RAD") / _hapkit("HK_SENSOR_SPAN_COUNTS")
                        * _hapkit("HK_CAPSTAN_RADIUS_M") / _hapkit("HK_SECTOR_RADIUS_M"))
HAPKIT_TORQUE_STEP = (_hapkit("HK_MOTOR_TORQUE_MAX_NM") * _hapkit("HK_SECTOR_RADIUS_M")
                      / _hapkit("HK_CAPSTAN_RADIUS_M") / _hapkit("HK_PWM_STEPS"))


def _falcon_loop(seed, inertia=1.0):
    """configs/falcon_spring.yaml with its legs' inertia and friction and the field's
    stiffness and damping drawn from ``seed`` (the inertia times ``inertia`` more: a
    device unlike the drawn scene); the stiffness kept under 0.9 of the shipped one,
    half the limit along the lightest mass axis (its comments), so every draw is stable."""
    rng = np.random.default_rng(seed)
    ji = 1.5e-4 * rng.uniform(0.7, 2.0, 3) * inertia
    jf = 1e-3 * rng.uniform(0.2, 5.0, 3)
    k, b = 1000 * rng.uniform(0.3, 0.9), 3.0 * rng.uniform(0.3, 1.5)
    text = (SPRING.replace("joint_inertia: [1.5e-4, 1.5e-4, 1.5e-4]",
                           "joint_inertia: [%r, %r, %r]" % tuple(map(float, ji)))
            .replace("joint_friction: [1.0e-3, 1.0e-3, 1.0e-3]",
                     "joint_friction: [%r, %r, %r]" % tuple(map(float, jf)))
            .replace("stiffness: 1000, damping: 3",
                     f"stiffness: {float(k)!r}, damping: {float(b)!r}"))
    return parse_scene_nd(text), rng


def _records(sc, a, N, reading=None, force=None):
    """The ``2n + 1`` records (rest first), each with its reading and force errors at the
    handle, (N, n) [m] and [N], fed back through the loop."""
    return [LockstepND(sc, x0=x0, v0=v0).step(
        N, record=True, reading_error=None if reading is None else reading[j],
        force_error=None if force is None else force[j])
        for j, (x0, v0) in enumerate(excitation_starts(sc.dimension, a, sc.period))]


def _stated(wire, n):
    """The stated term of each statement of :func:`_statements`, relative."""
    d = wire["directions"]
    return np.array([wire["felt_stiffness"]] * n * n + [wire["felt_damping"]] * n * n
                    + d["felt_stiffness"] + d["felt_damping"])


def _scales(chk, E):
    """What each statement's term is relative to: the predicted matrix's largest entry,
    ``|e_i^T X_pred e_i|`` along a direction."""
    P = np.stack([chk.render.felt_stiffness, chk.render.felt_damping])
    n = P.shape[1]
    big = np.repeat(np.max(np.abs(P), axis=(1, 2)), n * n)
    return np.concatenate([big, np.abs(np.einsum("ai,bi,qab->qi", E, E, P)).ravel()])


class _Box:
    """One loop's error box: the joint readings' bounds ``dq`` through ``J``, the joint
    torques' ``dt`` through ``J^-T``, and the search for the errors that move a
    statement most (each statement's worst signs for the fit linearised at given records,
    the first-order map's maximisers, :func:`hapsim.analysis.wire_box.box_worst_case`'s
    points)."""

    def __init__(self, sc, a, N, p, J, dq, dt):
        self.sc, self.a, self.N, self.p, self.J = sc, a, N, p, J
        self.Jt = np.linalg.inv(J).T
        self.dq, self.dt = dq, dt
        Hr, Hf = error_responses(sc, N)
        self.H = (Hr @ J, Hf @ self.Jt)
        self.E = None

    def move(self, u):
        """The records with joint reading errors ``u[0]`` and torque errors ``u[1]``
        (per record (N, n) [rad], [N m])."""
        return _records(self.sc, self.a, self.N, [x @ self.J.T for x in u[0]],
                        [x @ self.Jt.T for x in u[1]])

    def worst_signs(self, X, statements):
        """Per statement, the errors at the box's corner where its first-order change
        about the records ``X`` is largest."""
        n, N = self.sc.dimension, self.N
        sens = felt_sensitivity_nd([r - X[0] for r in X[1:]], self.sc.device.mass,
                                   self.sc.period, self.p)
        sens = [-sum(sens)] + list(sens)                   # the rest record's first
        comb = [np.concatenate([s.reshape(2 * n * n, N, n), np.einsum(
            "ai,bi,qabtc->qitc", self.E, self.E, s).reshape(2 * n, N, n)]) for s in sens]
        fr, ff = (filtered_sensitivity_nd(comb, H) for H in self.H)
        return {o: ([self.dq * np.sign(S[o]) for S in fr],
                    [self.dt * np.sign(S[o]) for S in ff]) for o in statements}

    def trials(self, X0, s0, statements, rng, relinearise=1):
        """Errors inside the box: each statement's worst signs at ``X0`` both ways, then
        re-linearised ``relinearise`` times at the records they moved (the sign that moved
        it farther kept); uniform draws and the box's corners. Yields records."""
        n, N, R = self.sc.dimension, self.N, 2 * self.sc.dimension + 1
        for o, u in self.worst_signs(X0, statements).items():
            for sg in (1.0, -1.0):
                u1 = ([sg * x for x in u[0]], [sg * x for x in u[1]])
                X = self.move(u1)
                yield X
                for _ in range(relinearise):
                    s = _statements(X, self.sc, self.p, self.E)
                    if s is None:
                        break
                    v = self.worst_signs(X, [o])[o]
                    if (s[o] - s0[o]) < 0:
                        v = ([-x for x in v[0]], [-x for x in v[1]])
                    X = self.move(v)
                    yield X
        for _ in range(2):
            yield self.move((list(rng.uniform(-self.dq, self.dq, (R, N, n))),
                             list(rng.uniform(-self.dt, self.dt, (R, N, n)))))
            yield self.move((list(self.dq * rng.choice([-1.0, 1.0], (R, N, n))),
                             list(self.dt * rng.choice([-1.0, 1.0], (R, N, n)))))


def _falcon_counts(monkeypatch, finer):
    """The Falcon's encoder ``finer`` times finer than its own, for the verdict's error
    bounds (:func:`hapsim.emulated.falcon_felt.falcon_felt_verdict` reads the count when
    called). Returns ``(dq, dt)``: half a count [rad] and half a motor command [N m]."""
    import hapsim.drivers.falcon as falcon
    monkeypatch.setattr(falcon, "DEG_PER_TICK", falcon.DEG_PER_TICK / finer)
    return math.radians(falcon.DEG_PER_TICK) / 2.0, falcon.TORQUE_PER_COUNT / 2.0


def _falcon_wire(sc, X, plan, a):
    """The worst case over the errors' box of the Falcon's counts (half a count per leg
    reading, half a motor command per torque) for records ``X``, and its verdict: the
    term the Falcon's verdict stated before its rounding term
    (:mod:`hapsim.analysis.wire_rounding`), which the 2DIY's verdict still takes for the
    errors that are no rounding (:func:`hapsim.lockstep.wire_terms_nd` with
    ``box=True``)."""
    from hapsim.analysis.felt_matrices import felt_deviation, felt_directions, felt_verdict
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    chk, order, N = plan
    J = device("delta", sc.device.geometry).jacobian(np.asarray(sc.device.joints, float))
    diffs = [x - X[0] for x in X[1:]]
    errors = [("reading", J, np.full(3, math.radians(DEG_PER_TICK) / 2.0)),
              ("force", np.linalg.inv(J).T, np.full(3, TORQUE_PER_COUNT / 2.0))]
    wire = wire_terms_nd(sc, diffs, chk, order, errors, box=True)
    fit = fit_felt_nd(diffs, sc.device.mass, sc.period, order)
    v = felt_verdict(felt_deviation(fit, chk),
                     linearisation_bound(sc, a, chk.render.rendered_poles), wire,
                     directions=felt_directions(fit, chk))
    return {**v, "wire": wire}


def _pantograph_wire(sc, X, plan, c, s):
    """The pantograph firmware's stated wire term for records ``X`` at ``c`` rad per
    count and ``s`` N m per PWM step (the largest torque taken as 0.5 N m, the firmware
    test's bound on its live loop: its binary32 rounding is 3e-8 N m of it)."""
    from hapsim.emulated.pantograph_board import wire_term
    res = {"responses": X, "predicted": plan[0], "order": plan[1], "torque_max": 0.5}
    return wire_term(sc, res, c, s)


def _check_refits(box, X0, s0, stated, first, scale, rng):
    """The largest refit change of each statement over the box's trials, against what is
    stated: returns (worst, worst over the first-order term)."""
    ok = stated <= MEASURABLE_WIRE
    assert ok.any(), stated                   # the draw makes a statement (module notes)
    worst = np.zeros(stated.size)
    for X in box.trials(X0, s0, np.flatnonzero(ok), rng):
        s = _statements(X, box.sc, box.p, box.E)
        worst = np.maximum(worst, np.inf if s is None else np.abs(s - s0) / scale)
    assert np.all(worst[ok] <= stated[ok]), (worst[ok], stated[ok])
    return worst, worst[ok] / first[ok]


@pytest.mark.parametrize("seed", [1, 4])
def test_falcon_refits_within_the_counts_stay_within_what_is_stated(seed, monkeypatch):
    """Random spring fields on the Falcon (legs' inertia and friction, the field's
    stiffness and damping drawn), its encoder 8 to 32 times finer (drawn; at its own
    count the box states nothing here), a hand start of 1 to 3.4 mm: the records moved
    by errors inside the bounds the verdict states (half a count per leg, half a motor
    command per torque: each stated statement's worst signs at the records and
    re-linearised once at the records they moved, uniform draws, the box's corners),
    refitted: no stated component moved by more than its stated term."""
    sc, rng = _falcon_loop(seed)
    dq, dt = _falcon_counts(monkeypatch, 2.0 ** rng.uniform(3, 5))
    a, N = float(rng.uniform(1e-3, 3.4e-3)), 100
    plan = identification_plan(sc, N)
    chk, p, _ = plan
    J = device("delta", sc.device.geometry).jacobian(np.asarray(sc.device.joints, float))
    box = _Box(sc, a, N, p, J, dq, dt)
    box.E = np.asarray(chk.render.directions, float)
    X0 = _records(sc, a, N)
    v = _falcon_wire(sc, X0, plan, a)
    stated, first = _stated(v["wire"], 3), _stated(v["wire"]["first_order"], 3)
    assert np.all(stated >= first)           # the box holds the records' own point
    _check_refits(box, X0, _statements(X0, sc, p, box.E), stated, first,
                  _scales(chk, box.E), rng)


@pytest.mark.parametrize("seed", [0, 1])
def test_pantograph_firmware_refits_stay_within_what_is_stated(seed):
    """Random pantograph walls (tests/test_wire_box.py's family: joint inertia and
    friction, the wall's and the press spring's stiffness and damping, the delay drawn),
    the firmware's sensor and PWM 16 to 64 times finer (drawn; at their own the term is
    above the limit), a hand start of 0.1 to 0.3 mm: the records moved by errors inside
    :func:`hapsim.emulated.pantograph_board.wire_term`'s bounds, refitted: no stated
    component moved by more than its stated term."""
    sc, rng = _pantograph_loop(100 + seed)
    finer = 2.0 ** rng.uniform(4, 6)
    c, s = HAPKIT_RAD_PER_COUNT / finer, HAPKIT_TORQUE_STEP / finer
    a, N = float(rng.uniform(1e-4, 3e-4)), 150
    plan = identification_plan(sc, N)
    chk, p, _ = plan
    q0 = np.asarray(sc.device.joints, float)
    J = device("pantograph", sc.device.geometry).jacobian(q0)
    ulp = np.spacing(np.abs(q0).astype(np.float32)).astype(float)
    box = _Box(sc, a, N, p, J, c / 2 + ulp, s / 2 + 2.0 ** -24 * 0.5)
    box.E = np.asarray(chk.render.directions, float)
    X0 = _records(sc, a, N)
    wire = _pantograph_wire(sc, X0, plan, c, s)
    stated, first = _stated(wire, 2), _stated(wire["first_order"], 2)
    assert np.all(stated >= first)
    _check_refits(box, X0, _statements(X0, sc, p, box.E), stated, first,
                  _scales(chk, box.E), rng)


def _past_first_order(sc, a, kind, dq, dt, o, relinearise):
    """Statement ``o`` on ``sc``'s exact records from starts at ``a`` [m], errors within
    ``dq`` per joint reading [rad] and ``dt`` per joint torque [N m]: its first-order
    term at the records (relative) and the largest change the box's search found (its
    worst signs, re-linearised ``relinearise`` times)."""
    chk, p, N = identification_plan(sc)
    n = sc.dimension
    J = device(kind, sc.device.geometry).jacobian(np.asarray(sc.device.joints, float))
    box = _Box(sc, a, N, p, J, dq, dt)
    E = box.E = np.asarray(chk.render.directions, float)
    X0 = _records(sc, a, N)
    s0 = _statements(X0, sc, p, E)
    first = _stated(wire_terms_nd(sc, [r - X0[0] for r in X0[1:]], chk, p,
                                  [("reading", J, np.broadcast_to(dq, (n,))),
                                   ("force", box.Jt, np.full(n, dt))]), n)
    moved = 0.0
    for X in box.trials(X0, s0, [o], np.random.default_rng(0), relinearise=relinearise):
        s = _statements(X, sc, p, E)
        moved = max(moved, math.inf if s is None else abs(s[o] - s0[o]) / _scales(chk, E)[o])
    return first[o], moved, E


def test_the_first_order_term_was_exceeded_on_the_falcons_spring():
    """Why the Falcon's verdict left the first-order term: on configs/falcon_spring.yaml
    at its largest start (3.77 mm) and the Falcon's own counts, the first-order term at
    the exact records states the felt stiffness along the heaviest principal direction
    (0.101, under the limit of 0.25); errors inside the counts' bounds, its worst signs
    re-linearised twice at the records they moved, move it by 0.22 (measured: 2.2 times
    the term; four re-linearisations of the stiffness entries reach 2.7 times, and one
    entry's fit collapses, 1,800 times). The box's term there (tests/test_falcon_spring.py)
    is beyond the limit: nothing is stated."""
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    first, moved, _ = _past_first_order(parse_scene_nd(SPRING), SPRING_START, "delta",
                                        math.radians(DEG_PER_TICK) / 2.0,
                                        TORQUE_PER_COUNT / 2.0, 18, 2)  # k along e_0
    assert first <= MEASURABLE_WIRE                   # first order stated it
    # measured 2.2 times the term; 1.5 leaves the records' round-off (1e-16 relative)
    # and any BLAS's refit far inside the 0.7 above it
    assert moved > 1.5 * first, (moved, first)


def test_the_first_order_term_was_exceeded_on_the_pantographs_spring():
    """Likewise the pantograph firmware's: on configs/pantograph_spring.yaml at 5 mm (the
    loop in lockstep, the firmware's own sensor count and PWM step) the first-order term
    at the records states the felt damping along x (0.18); errors within half a count
    and half a step, its worst signs re-linearised once at the records they moved, move
    it by 0.24 (measured: 1.34 times the term; three re-linearisations reach 1.9 times).
    Over the box nothing is stated there (tests/test_pantograph_spring.py)."""
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(ROOT / "configs" / "pantograph_spring.yaml")
    q0 = np.asarray(sc.device.joints, float)
    ulp = np.spacing(np.abs(q0).astype(np.float32)).astype(float)
    first, moved, E = _past_first_order(sc, 5e-3, "pantograph",
                                        HAPKIT_RAD_PER_COUNT / 2 + ulp,
                                        HAPKIT_TORQUE_STEP / 2 + 2.0 ** -24 * 0.5,
                                        11, 1)                  # b along e_1
    assert abs(E[0, 1]) > 0.99                        # e_1 is x
    assert first <= MEASURABLE_WIRE                   # first order stated it
    # measured 1.34 times the term; 1.2 leaves the records' round-off (1e-16 relative)
    # and any BLAS's refit far inside the 0.14 above it
    assert moved > 1.2 * first, (moved, first)


@pytest.mark.parametrize("family", ["falcon", "pantograph"])
def test_a_matching_device_is_never_differs_and_more_inertia_still_is(family, monkeypatch):
    """The readings rounded to whole counts (each joint's motion at the operating point's
    Jacobian, fed back through the loop), the torques off by up to half a step (uniform,
    seeded), the counts finer than the device's own (32 times the Falcon's, 64 times the
    Hapkit's): the scene's own device is never "differs" over the box's term; the device
    with 30 % more joint inertia "differs" in the felt stiffness, where it is stated."""
    from hapsim.analysis.felt_matrices import felt_deviation, felt_directions, felt_verdict
    from hapsim.analysis.linearisation import linearisation_bound
    rng = np.random.default_rng(29)
    if family == "falcon":
        sc, _ = _falcon_loop(7)
        plant, _ = _falcon_loop(7, inertia=1.3)
        dq, dt = _falcon_counts(monkeypatch, 32.0)
        a, N, kind = 3e-3, 100, "delta"
    else:
        sc, _ = _pantograph_loop(0)
        plant, _ = _pantograph_loop(0, inertia=1.3)
        c, s = HAPKIT_RAD_PER_COUNT / 64.0, HAPKIT_TORQUE_STEP / 64.0
        dq, dt = c / 2.0, s / 2.0
        a, N, kind = 2e-4, 150, "pantograph"
    plan = identification_plan(sc, N)
    chk = plan[0]
    J = device(kind, sc.device.geometry).jacobian(np.asarray(sc.device.joints, float))
    Ji = np.linalg.inv(J)
    n = sc.dimension
    bound = linearisation_bound(sc, a, chk.render.rendered_poles)
    verdicts = []
    for loop in (sc, plant):
        exact = _records(loop, a, N)
        step = 2.0 * dq
        reading = []
        for r in exact:
            q = r @ Ji.T
            reading.append((np.round(q / step) * step - q) @ J.T)
        force = [rng.uniform(-dt, dt, (N, n)) @ Ji for _ in exact]
        recs = _records(loop, a, N, reading, force)
        if family == "falcon":
            verdicts.append(_falcon_wire(sc, recs, plan, a))
            continue
        wire = _pantograph_wire(sc, recs, plan, c, s)
        fit = fit_felt_nd([r - recs[0] for r in recs[1:]], sc.device.mass, sc.period,
                          plan[1])
        verdicts.append(felt_verdict(felt_deviation(fit, chk), bound, wire,
                                     directions=felt_directions(fit, chk)))
    match, more = verdicts
    assert match["verdict"] != "differs", match["reason"]
    assert all(st["verdict"] != "differs" for st in match["statements"])
    stiff = [st for st in more["statements"]
             if "stiffness" in st["name"] and st["verdict"] != "not measurable"]
    assert stiff, more["reason"]                      # the statement is made
    assert more["verdict"] == "differs", more["reason"]
    assert any(st["verdict"] == "differs" for st in stiff)


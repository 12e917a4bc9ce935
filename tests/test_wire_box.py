"""The n-D felt fit's stated wire term beyond first order (:mod:`hapsim.analysis.wire_box`):
refits of records moved by errors inside the stated bounds stay within what is stated,
over seeded random loops that really differ (the scene's text changed, so its Cartesian
mass and friction are recomputed); a correct device is never "differs", one with 30 %
more inertia still is.

The records are the loop's own free responses in lockstep (:class:`hapsim.lockstep.LockstepND`,
the 2DIY's wall scene, ``configs/pantograph_wall.yaml``); the errors enter them through
the loop as :class:`LockstepND` feeds a reading error back (an independent path from the
superposition :func:`hapsim.analysis.wire_box.moved_records` uses)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis.felt_matrices import (MEASURABLE_WIRE, felt_deviation,
                                           felt_directions, felt_verdict)
from hapsim.analysis.linearisation import linearisation_bound
from hapsim.analysis.pencil import felt_sensitivity_nd, filtered_sensitivity_nd, fit_felt_nd
from hapsim.kinematics import device
from hapsim.lockstep import (LockstepND, error_responses, excitation_starts,
                             identification_plan, wire_terms_nd)
from hapsim.scene import parse_scene_nd

WALL = (Path(__file__).resolve().parent.parent / "configs" / "pantograph_wall.yaml").read_text()


def _loop(seed, inertia=1.0):
    """The wall scene with its joint inertia and friction, the wall's and the press
    spring's stiffness and damping and the delay drawn from ``seed`` (the joint inertia
    times ``inertia`` more: a device unlike the drawn scene)."""
    rng = np.random.default_rng(seed)
    ji = 2e-4 * rng.uniform(0.5, 2.0, 2) * inertia
    jf = 1e-3 * rng.uniform(0.2, 5.0, 2)
    kw, bw = 1000 * rng.uniform(0.3, 3.0), 2.0 * rng.uniform(0.2, 3.0)
    kp, bp = 200 * rng.uniform(0.3, 3.0), 0.5 * rng.uniform(0.2, 3.0)
    text = (WALL.replace("joint_inertia: [2.0e-4, 2.0e-4]",
                         f"joint_inertia: [{float(ji[0])!r}, {float(ji[1])!r}]")
            .replace("joint_friction: [1.0e-3, 1.0e-3]",
                     f"joint_friction: [{float(jf[0])!r}, {float(jf[1])!r}]")
            .replace("stiffness: 1000, damping: 2.0", f"stiffness: {float(kw)!r}, damping: {float(bw)!r}")
            .replace("stiffness: 200, damping: 0.5", f"stiffness: {float(kp)!r}, damping: {float(bp)!r}")
            .replace("delay: 1}", f"delay: {int(rng.integers(1, 3))}}}"))
    return parse_scene_nd(text), rng


def _records(sc, a, N, errors=None):
    """The ``2n + 1`` records (rest first) with a reading error (N, n) [m] each."""
    return [LockstepND(sc, x0=x0, v0=v0).step(
        N, record=True, reading_error=None if errors is None else errors[j])
        for j, (x0, v0) in enumerate(excitation_starts(2, a, sc.period))]


def _statements(recs, sc, p, E):
    """The felt entries, then ``e_i^T X e_i``: what is stated (None: no felt matrices)."""
    f = fit_felt_nd([r - recs[0] for r in recs[1:]], sc.device.mass, sc.period, p)
    if f["felt_stiffness"] is None:
        return None
    X = np.stack([f["felt_stiffness"], f["felt_damping"]])
    return np.concatenate([X.ravel(), np.einsum("ai,bi,qab->qi", E, E, X).ravel()])


def _stated(wire):
    """The stated term of each statement of :func:`_statements`, relative."""
    d = wire["directions"]
    return np.array([wire["felt_stiffness"]] * 4 + [wire["felt_damping"]] * 4
                    + d["felt_stiffness"] + d["felt_damping"])


def _scales(chk, E):
    """What each statement's term is relative to: the predicted matrix's largest entry,
    ``|e_i^T X_pred e_i|`` along a direction."""
    P = np.stack([chk.render.felt_stiffness, chk.render.felt_damping])
    big = np.repeat(np.max(np.abs(P), axis=(1, 2)), 4)
    return np.concatenate([big, np.abs(np.einsum("ai,bi,qab->qi", E, E, P)).ravel()])


@pytest.mark.parametrize("seed", range(3))
def test_refits_within_the_bounds_stay_within_what_is_stated(seed):
    """Random loops, excitations and encoders (2^20 to 2^22 counts per revolution, half a
    count per joint reading): the records moved by errors inside the bounds (each
    statement's worst signs at the records, both ways; random errors, uniform and at the
    box's corners), fed back through the loop, refitted: every stated component moved by
    no more than its stated term; a component whose term is beyond the measurable limit
    is not stated. Measured over seeds 0-9 of this family (docs/dimensions.md, 'The
    wire's term beyond first order'): the first-order term at the records was exceeded
    up to 3.0 times by a component it stated (seed 5: a=1e-4 m, N=300, 2^20), the
    sampled box without its margin up to 1.27 times (seed 9, likewise), the box with its
    margin (hapsim.analysis.wire_box.BOX_MARGIN) at most 0.40 of it."""
    sc, rng = _loop(seed)
    a = float(rng.uniform(3e-5, 1e-4))
    cpr = 2.0 ** int(rng.integers(20, 23))
    N = 150
    chk, p, _ = identification_plan(sc, N)
    E = np.asarray(chk.render.directions, float)
    J = device("pantograph", sc.device.geometry).jacobian(np.asarray(sc.device.joints))
    delta = math.pi / cpr                                   # half a count [rad]
    X0 = _records(sc, a, N)
    s0 = _statements(X0, sc, p, E)
    wire = wire_terms_nd(sc, [r - X0[0] for r in X0[1:]], chk, p,
                         [("reading", J, np.full(2, delta))], box=True)
    stated = _stated(wire)
    first = _stated(wire["first_order"])
    # the box states at least the first-order term at the records (it is one of its points)
    assert np.all(stated >= first)
    scale = _scales(chk, E)
    # each statement's worst signs at the records: the first-order map's maximisers
    sens = felt_sensitivity_nd([r - X0[0] for r in X0[1:]], sc.device.mass, sc.period, p)
    sens = [-sum(sens)] + list(sens)                       # the rest record's first
    comb = [np.concatenate([s.reshape(8, N, 2),
                            np.einsum("ai,bi,qabtc->qitc", E, E, s).reshape(4, N, 2)])
            for s in sens]
    fil = filtered_sensitivity_nd(comb, error_responses(sc, N)[0] @ J)
    trials = [[sg * delta * np.sign(S[o]) for S in fil] for o in range(12) for sg in (1, -1)]
    trials += [list(rng.uniform(-delta, delta, (5, N, 2))) for _ in range(2)]
    trials += [list(delta * rng.choice([-1.0, 1.0], (5, N, 2))) for _ in range(2)]
    worst = np.zeros(12)
    for u in trials:
        s = _statements(_records(sc, a, N, [ui @ J.T for ui in u]), sc, p, E)
        worst = np.maximum(worst, np.inf if s is None else np.abs(s - s0) / scale)
    ok = stated <= MEASURABLE_WIRE
    assert np.all(worst[ok] <= stated[ok]), (worst / stated, stated)


@pytest.mark.parametrize("seed", [0, 5])
def test_a_correct_device_is_never_differs_and_more_inertia_still_is(seed):
    """The readings rounded to whole counts (2^20 per revolution, each joint's motion at
    the operating point's Jacobian, fed back through the loop): the scene's own device is never
    "differs"; the device with 30 % more joint inertia than the scene states "differs"
    wherever the first-order term said it (the felt stiffness, ~15 % off against a
    stated term of a few per cent)."""
    sc, _ = _loop(seed)
    plant, _ = _loop(seed, inertia=1.3)
    a, N, cpr = 1e-4, 150, 2.0 ** 20
    chk, p, _ = identification_plan(sc, N)
    J = device("pantograph", sc.device.geometry).jacobian(np.asarray(sc.device.joints))
    Ji = np.linalg.inv(J)
    step = 2 * math.pi / cpr
    bound = linearisation_bound(sc, a, chk.render.rendered_poles)
    verdicts = []
    for loop in (sc, plant):
        exact = _records(loop, a, N)
        # each joint's motion J^-1 x rounded to whole counts, back at the handle: an
        # error of half a count at most per joint, as the stated bounds
        errs = []
        for r in exact:
            dq = r @ Ji.T
            errs.append((np.round(dq / step) * step - dq) @ J.T)
        recs = _records(loop, a, N, errs)
        diffs = [r - recs[0] for r in recs[1:]]
        fit = fit_felt_nd(diffs, sc.device.mass, sc.period, p)
        wire = wire_terms_nd(sc, diffs, chk, p, [("reading", J, np.full(2, step / 2))],
                             box=True)
        dev, dirs = felt_deviation(fit, chk), felt_directions(fit, chk)
        verdicts.append((felt_verdict(dev, bound, wire, directions=dirs),
                         felt_verdict(dev, bound, dict(wire["first_order"]),
                                      directions=dirs)))
    (match, _), (more, more_first) = verdicts
    assert match["verdict"] != "differs", match["reason"]
    assert all(s["verdict"] != "differs" for s in match["statements"])
    assert more["verdict"] == "differs", more["reason"]
    was = {s["name"] for s in more_first["statements"] if s["verdict"] == "differs"}
    now = {s["name"] for s in more["statements"] if s["verdict"] == "differs"}
    assert "felt stiffness" in now and was <= now | set(more["not_stated"]), (was, now)


def test_the_first_order_term_at_the_records_alone_was_exceeded():
    """The helper's report, at its cause (the loop of seed 5, a = 1e-4 m, N = 300, 2^20
    counts per revolution): the felt damping matrix's first-order term at the records is
    0.204, inside the measurable limit, so it was stated; the errors of the worst signs
    for one entry, re-linearised once at the records they moved (still inside the
    bounds), move another entry by 1.24 times that term (measured: 0.253 relative; three
    re-linearisations reach 2.8 times). The box's term, the first-order worst case also
    taken at each statement's worst errors, is beyond the limit: the felt damping is not
    stated."""
    sc, _ = _loop(5)
    a, N, cpr = 1e-4, 300, 2.0 ** 20
    chk, p, _ = identification_plan(sc, N)
    E = np.asarray(chk.render.directions, float)
    J = device("pantograph", sc.device.geometry).jacobian(np.asarray(sc.device.joints))
    delta = math.pi / cpr
    H = error_responses(sc, N)[0] @ J
    X0 = _records(sc, a, N)
    s0 = _statements(X0, sc, p, E)
    wire = wire_terms_nd(sc, [r - X0[0] for r in X0[1:]], chk, p,
                         [("reading", J, np.full(2, delta))], box=True)
    first, stated = _stated(wire["first_order"]), _stated(wire)

    def worst_signs(X, o):
        sens = felt_sensitivity_nd([r - X[0] for r in X[1:]], sc.device.mass, sc.period, p)
        comb = [np.concatenate([s.reshape(8, N, 2), np.einsum(
            "ai,bi,qabtc->qitc", E, E, s).reshape(4, N, 2)]) for s in [-sum(sens)] + sens]
        return [delta * np.sign(S[o]) for S in filtered_sensitivity_nd(comb, H)]
    X1 = _records(sc, a, N, [u @ J.T for u in worst_signs(X0, 6)])
    s1 = _statements(X1, sc, p, E)
    u = worst_signs(X1, 6)
    if s1[6] < s0[6]:
        u = [-v for v in u]
    moved = np.abs(_statements(_records(sc, a, N, [v @ J.T for v in u]), sc, p, E) - s0)
    moved /= _scales(chk, E)
    assert first[7] <= MEASURABLE_WIRE                      # first order stated it
    # measured 1.24 times the first-order term; 1.1 leaves the margin of the refits'
    # round-off (the records' 1e-16 relative, far under the 0.14 above 1.1)
    assert moved[7] > 1.1 * first[7], (moved[7], first[7])
    assert stated[7] > MEASURABLE_WIRE                      # the box does not state it


def test_a_pair_the_records_do_not_determine_is_never_taken_for_a_rendered_one():
    """Issue 29, the box term's explosion (3e4-1.4e5 relative on the 2DIY's records kept
    in time): a vector prediction of order p has n p poles, and those of the loop's fast
    modes, dead within a few samples, are set by the readings' errors alone. Errors
    inside the bounds can move such a noise pair anywhere, outside the unit circle too;
    taken for a rendered pair by ``|z|`` alone, it made the felt matrices at that point of
    the box those of no mode of the loop. Over seeded random loops of this family with
    short records (25 rows, a = 2e-5 m, half a count at 2^20 to 2^22 counts per
    revolution, so the noise pairs are loosely held) and each felt entry's worst errors
    of either sign (the box's own points, fed back through the loop): every pair the fit
    renders with the records' floor (:data:`hapsim.analysis.pencil.MODE_FLOOR` times the
    differences' bound at the handle) is nearest to a rendered pole of the loop (no
    tolerance: the nearest of all the loop's poles), at the records and at every point;
    without the floor (``|z|`` alone, the old selection) a noise pair was taken at 7 of
    these 160 points (seeds 7 and 8). The floor leaves the loop's own pairs: at the
    records both are rendered, and at most points too (the noise pairs' sizes at these
    points at most 0.6 times the bound, the loop's at least 9.2 times: the floor's 3.5
    between them)."""
    from hapsim.analysis.pencil import MODE_FLOOR
    N, a = 25, 2e-5
    old_wrong = full = points = 0
    for seed in range(10):
        sc, rng = _loop(seed)
        delta = math.pi / 2.0 ** int(rng.integers(20, 23))       # half a count [rad]
        chk, p, _ = identification_plan(sc, N)
        J = device("pantograph", sc.device.geometry).jacobian(np.asarray(sc.device.joints))
        pred = np.asarray(chk.render.poles)
        rendered = set(np.flatnonzero(np.isin(pred, chk.render.rendered_poles)).tolist())
        # a difference of two records: twice one record's bound at the handle
        floor = MODE_FLOOR * 2 * float(np.linalg.norm(np.abs(J) @ np.full(2, delta)))

        def loop_modes(fit):
            return all(int(np.argmin(np.abs(pred - z))) in rendered
                       for z in fit["rendered_poles"])
        X0 = _records(sc, a, N)
        d0 = [r - X0[0] for r in X0[1:]]
        f0 = fit_felt_nd(d0, sc.device.mass, sc.period, p, floor=floor)
        assert f0["rendered_poles"].size == 2 and loop_modes(f0), (seed, f0["poles"])
        sens = felt_sensitivity_nd(d0, sc.device.mass, sc.period, p)
        sens = [-sum(sens)] + list(sens)                   # the rest record's first
        fil = filtered_sensitivity_nd([s.reshape(8, N, 2) for s in sens],
                                      error_responses(sc, N)[0] @ J)
        for o in range(8):
            for sg in (1, -1):
                X = _records(sc, a, N, [sg * delta * np.sign(S[o]) @ J.T for S in fil])
                d = [r - X[0] for r in X[1:]]
                f = fit_felt_nd(d, sc.device.mass, sc.period, p, floor=floor)
                assert loop_modes(f), (seed, o, sg, f["rendered_poles"], f["poles"])
                full += f["rendered_poles"].size == 2
                old_wrong += not loop_modes(fit_felt_nd(d, sc.device.mass, sc.period, p))
                points += 1
    # the class is there without the floor (measured 7 of 160), and the floor leaves the
    # loop's pairs rendered at most points (measured 153 of 160: at the other 7 the fit
    # holds no second pair of the loop, the one |z| alone replaced by a noise pair)
    assert old_wrong > 0 and full > points // 2, (old_wrong, full, points)


def test_filtered_sensitivity_is_each_inputs_convolution_to_the_bit():
    """pencil.filtered_sensitivity_nd (one transform of each coordinate's sensitivity for
    every input) equals its definition composed of fftconv.fftconvolve, one convolution
    per (coordinate, input), added over the coordinates in turn, bit for bit: over
    seeded random shapes (1-3 coordinates and inputs, records of 1-300 rows against
    responses of 1-400, values over 16 decades), the same transforms of the same arrays."""
    from hapsim.analysis.fftconv import fftconvolve

    def by_definition(sensitivity, H):
        out = []
        for s in sensitivity:
            S = s.reshape(-1, s.shape[-2], s.shape[-1])
            N, L = S.shape[1], min(S.shape[1], H.shape[0])
            Su = np.zeros((S.shape[0], N, H.shape[2]))
            for c in range(S.shape[2]):
                for j in range(H.shape[2]):
                    Su[:, :, j] += fftconvolve(S[:, ::-1, c], H[None, :L, c, j],
                                               axes=1)[:, :N][:, ::-1]
            out.append(Su)
        return out
    rng = np.random.default_rng(31)
    for _ in range(60):
        n, m = (int(v) for v in rng.integers(1, 4, 2))
        N, L = int(rng.integers(1, 300)), int(rng.integers(1, 400))
        sens = [rng.normal(size=(2, n, n, N, n)) * 10.0 ** rng.uniform(-8, 8)
                for _ in range(int(rng.integers(1, 4)))]
        H = rng.normal(size=(L, n, m)) * 10.0 ** rng.uniform(-8, 3)
        got, ref = filtered_sensitivity_nd(sens, H), by_definition(sens, H)
        assert len(got) == len(ref)
        for g, r in zip(got, ref):
            assert g.shape == r.shape and g.tobytes() == r.tobytes()


@pytest.mark.parametrize("seed", range(4))
def test_the_prediction_rows_gathered_at_once_are_the_rows_one_by_one(seed):
    """``pencil._regression`` gathers each record's lagged rows in one indexing (the
    suite's time: it was a Python loop per row); the rows, the right-hand sides and the
    reference are those of the row-by-row construction, to the bit, with and without the
    offset and with usable masks."""
    from hapsim.analysis import pencil
    rng = np.random.default_rng(seed)
    for t in range(10):
        n, p = 1 + t % 3, 2 + t % 4
        recs = [rng.normal(size=(int(rng.integers(p + 1, 60)), n)) * 10 ** rng.uniform(-6, 2)
                for _ in range(int(rng.integers(1, 4)))]
        usable = None if t % 2 else [rng.random(len(r)) > 0.1 for r in recs]
        for off in (False, True):
            R, Y, eqs, ref = pencil._regression(recs, p, usable, off)
            rows = [np.concatenate([(r[k - p:k][::-1] - ref).ravel(), [1.0] if off else []])
                    for r, ks in zip(recs, eqs) for k in ks]
            rhs = [r[k] - ref for r, ks in zip(recs, eqs) for k in ks]
            assert np.array_equal(np.asarray(R), np.array(rows).reshape(np.shape(R)))
            assert np.array_equal(np.asarray(Y), np.array(rhs).reshape(np.shape(Y)))

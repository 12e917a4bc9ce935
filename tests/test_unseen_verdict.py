"""A "differs" of a board on its own tick stands only where the predicted loop, broken
where the board's unseen holds may have struck, does not explain the record to its noise
(issue 29; :mod:`hapsim.analysis.unseen_verdict`, :mod:`hapsim.pipeline.unseen_review`).

The class: the Hapkit sketch takes a command a tick or more late, unseen by the host,
once or for a run of commands (its grid shifted until it catches up), anywhere in the
record: at a turning point (a small force step), late, next to another one. The hold
search (:mod:`hapsim.analysis.unseen_holds`) models a single late command, so a run of
late commands, or holds packed together, can leave the fit of free poles off by more than
its tiny stated interval (2.6e-8 relative on an emulated record).

Measured on the generator below (:func:`_holds`, seeds 0-199, matching paddles, the
offline board on a simulated clock): main (55b5101, the search and the shift rule) said
"differs" of 12 of them (seeds 8, 24, 42, 71, 83, 112, 129, 139, 143, 150, 167, 181) and
"not measurable" of 3; this change none "differs", 200 within. Seeds 0-39 with 30 % more
mass, 0.3 N s/m or 0.03 N of Coulomb friction the scene does not state: 40, 40 and 38
"differs" before and after (the other 2 Coulomb paddles stop within 1.3 cycles: "not
identified" with that reason, before and after). Those figures are of a board that applies
the float at its read (:data:`IDEAL`); the property test below runs the sketch's board (its
256 levels, its render latency, which the run searches within its bounds). Those seeds
were drawn at 250 and 200 Hz on a 1 ms tick; on the sketch's own 0.992 ms tick, at the
rates of 4 and 5 of its ticks, seeds 0-59 without the review said "differs" of 8 and 42
(the review: within, 7 and 8 breaks), within of the other 58.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import tempfile

import numpy as np
import pytest

from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
from seeds import seeds
from test_unseen_holds import _measure, _random_case

pytestmark = pytest.mark.xdist_group("test_unseen_verdict")

#: Two of the matching paddles of :func:`_holds` that the fit without the review says
#: "differs" of (module notes).
MAIN_DIFFERS = (8, 42)
#: The property test's seeds: a window holding one of those two.
SEEDS = tuple(range(6, 26, 2))
#: Those the suite runs (tests/seeds.py): the one main said "differs" of, and each wrong
#: device (:func:`_wrong`, by the seed's remainder of 3) twice.
KEPT = (6, 8, 10, 12, 16, 20)


def _holds(seed: int, prep, n: int) -> dict:
    """1 to 10 events of late commands the host does not see, ``{command: ticks late}``:
    each a single late command or a run of 2 to 25 (the board's grid shifted that long),
    0.6 to 2.5 ticks late, placed anywhere, at a turning point of the handle (a small
    force step and path error), in the last 40 % of the record, or within 6 rows of one
    already placed."""
    rng = np.random.default_rng(10_000 + seed)
    base, _, _ = hapkit_serial_offline_loop(prep.scene, n, **IDEAL)
    v = np.abs(np.gradient(base["position"]))
    turn = np.flatnonzero(v < 0.15 * v.max())
    turn = turn[(turn >= 5) & (turn < n - 5)]
    late: dict = {}
    for _ in range(int(rng.integers(1, 11))):
        kind = int(rng.integers(4))
        if kind == 0 or (kind == 3 and not late):
            j = int(rng.integers(5, n - 5))
        elif kind == 1:
            j = int(rng.choice(turn))
        elif kind == 2:
            j = int(rng.integers(int(0.6 * n), n - 5))
        else:
            j = int(rng.choice(sorted(late))) + int(rng.integers(-6, 7))
        length = 1 if rng.random() < 0.5 else int(rng.integers(2, 26))
        lat = float(rng.uniform(0.6, 2.5))
        for r in range(max(j, 5), min(j + length, n - 5)):
            late[r] = lat
    return late


def _wrong(prep, seed: int):
    """The board's true device: 30 % more mass, 0.3 N s/m or 0.03 N of Coulomb friction
    more than the scene states (by seed)."""
    dev = prep.scene.device
    return (dataclasses.replace(dev, mass=1.3 * dev.mass),
            dataclasses.replace(dev, friction=dev.friction + 0.3),
            dataclasses.replace(dev, coulomb=0.03))[seed % 3]


#: The board of the module notes' measurements: a sketch that applies the float at its
#: read (named), the loop the scene's whole delay; the default board is the sketch's (its
#: 256 levels, its render 0.45 ms after the read: the run searches that latency,
#: hapsim.pipeline.render_latency.latency_search).
IDEAL = {"levels": 0, "render_s": 0.0}


@functools.lru_cache(maxsize=None)
def _outcome(seed: int, ideal: bool = False):
    """The verdicts of the matching paddle and of the wrong one, same holds; on the
    sketch's board, or (``ideal``) on :data:`IDEAL`'s, predicted with the scene's delay."""
    with tempfile.TemporaryDirectory() as tmp:   # (cached: no tmp_path; nothing left)
        prep, n, _ = _random_case(seed, pathlib.Path(tmp))
        kw = {}
        if ideal:
            from hapsim.analysis.prediction import predict
            prep = dataclasses.replace(prep, model_scene=None, pred=predict(prep.scene))
            kw = IDEAL
        late = _holds(seed, prep, n)
        cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, read_late=late, **kw)
        assert board.tick_arrivals["off_period"] >= 1                 # the class happened
        match = _measure(prep, cols, drv)
        cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, read_late=late,
                                                  device=_wrong(prep, seed), **kw)
        return match, _measure(prep, cols, drv)


def _says(m) -> str:
    v = str(m.get("verdict") or "")
    return ("differs" if v.startswith("measured differs") else
            "within" if v.startswith("measured = predicted") else "not measurable")


@pytest.mark.parametrize("seed", seeds(SEEDS, KEPT))
def test_no_matching_paddle_differs_and_a_wrong_one_does(seed):
    """The matching paddle is within (or not measurable with its reason), never
    "differs"; the wrong one "differs", or says why it is not measurable."""
    match, wrong = _outcome(seed)
    assert _says(match) != "differs", (match.get("verdict"), match.get("prediction_test"))
    assert match.get("within") is True or match.get("error") or "not measurable" in str(
        match.get("verdict")), match.get("verdict")
    if _says(wrong) != "differs":
        assert wrong.get("error") or "not measurable:" in str(wrong.get("verdict")), wrong


@pytest.mark.parametrize("window", [KEPT, pytest.param(SEEDS, marks=pytest.mark.soak)],
                         ids=["kept", "window"])
def test_few_wrong_paddles_escape_as_not_measurable(window):
    """Of the property test's wrong paddles at most one in ten is not "differs" (each with
    its reason, above): measured none of the 12 (0-39: 2 of 40 Coulomb paddles)."""
    escaped = [s for s in window if _says(_outcome(s)[1]) != "differs"]
    assert len(escaped) <= len(window) // 10, escaped


@pytest.mark.parametrize("seed", MAIN_DIFFERS)
def test_the_review_turns_mains_wrong_differs(seed, monkeypatch):
    """The two matching paddles main said "differs" of say so still without the review
    (the class is in the record, not in a change of the fit), and within with it: the
    breaks cut, the fit again inside its interval. On the board main measured them on
    (:data:`IDEAL`)."""
    import hapsim.pipeline.unseen_review as ur
    match, _ = _outcome(seed, True)
    assert match.get("within") is True and match["prediction_test"]["explained"], match
    assert match["prediction_test"]["breaks"] >= 1
    monkeypatch.setattr(ur, "review_differs", lambda pred, m, state: m)
    _outcome.cache_clear()
    try:
        bare, _ = _outcome(seed, True)
    finally:
        _outcome.cache_clear()
    assert _says(bare) == "differs", bare.get("verdict")


def _synthetic(rng, n, z, events, sigma):
    """A free response of the poles ``z`` (one complex pair and a real pole) whose
    coefficients change at each row of ``events`` (an input of a few rows into the same
    loop), with Gaussian noise of deviation ``sigma`` [m]."""
    t = np.arange(n)
    y = np.zeros(n)
    edges = [0, *sorted(events), n]
    for a, b in zip(edges[:-1], edges[1:]):
        c = rng.normal(size=3) * 0.01
        tt = t[a:b] - a
        y[a:b] = (c[0] * np.abs(z[0]) ** tt * np.cos(np.angle(z[0]) * tt)
                  + c[1] * np.abs(z[0]) ** tt * np.sin(np.angle(z[0]) * tt)
                  + c[2] * z[1] ** tt)
    return y + rng.normal(scale=sigma, size=n)


def test_breaks_on_synthetic_records():
    """Closed form: records of known poles whose coefficients change at 1 to 6 random
    rows, with white noise at the stated floor. With the true poles the breaks fall on
    the changes (no piece kept holds one) and the residual
    is explained; with the pair's frequency 0.5 % off (what 1 % more mass does) it is
    not, whatever breaks are taken. 20 seeded records each way."""
    from hapsim.analysis.unseen_verdict import break_prediction
    for seed in range(20):
        rng = np.random.default_rng(seed)
        n = 300
        r, w = rng.uniform(0.97, 0.995), rng.uniform(0.05, 0.3)
        z = (r * np.exp(1j * w), rng.uniform(0.3, 0.8))
        events = sorted(rng.choice(np.arange(20, n - 20), size=int(rng.integers(1, 7)),
                                   replace=False).tolist())
        sigma = 1e-9
        y = _synthetic(rng, n, z, events, sigma)
        poles = [z[0], np.conj(z[0]), z[1]]
        fit = {"spec": [["pair", -np.log(r), w], ["real", z[1]]], "offset": False,
               "rows": [np.arange(n)]}
        got = break_prediction(y, fit, poles, floor=sigma, drop=5)
        assert got["explained"], (seed, got)
        # no piece kept holds a change (rows e - 1 and e both in it)
        assert not [e for e in events for a, b in got["pieces"] if a < e <= b], (
            seed, events, got["pieces"])
        off = [r * np.exp(1j * w * 1.005), r * np.exp(-1j * w * 1.005), z[1]]
        bad = break_prediction(y, fit, off, floor=sigma, drop=5)
        assert not bad["explained"], (seed, bad)


def _free_pair(y, z_real, start):
    """The pair of least residual over the whole record with no break (the free fit's,
    pulled by the record's events), the real pole kept: variable projection on (a, w)
    (Golub & Pereyra 1973), solved by least squares from ``start``."""
    from scipy.optimize import least_squares

    from hapsim.analysis.unseen_verdict import _basis

    def residual(th):
        phi = _basis([["pair", th[0], th[1]], ["real", z_real]], y.size, False)
        return y - phi @ np.linalg.lstsq(phi, y, rcond=None)[0]
    th = least_squares(residual, start, x_scale="jac", xtol=1e-14, ftol=1e-14).x
    return np.exp(-th[0] + 1j * th[1])


def test_breaks_do_not_explain_away_a_loop_that_differs(fac=1.1):
    """Closed form: breaks explain anything when enough are taken. Records of 800 rows of
    a known loop (a pair and a real pole) whose coefficients change at 1 to 10 random
    rows, white noise 1e-6 (1e-4 of the modes' size), tested against a prediction whose
    pair decays ``fac`` times slower (a device with more damping than the scene states):
    with the cap of a tenth of the rows, the predicted loop "explains" most of them by
    cutting them into ~70 pieces (measured: 19 of 20 at 1.1, 14 of 20 at 1.3, which the
    comparison also lets none pass; 1.1 is tested). The loop
    of the pair the record has, with its own breaks, explains each at a cost lower by
    more than two free parameters can gain under a matching loop
    (:func:`hapsim.analysis.unseen_verdict.break_cost_gain`): every one stands. And with
    the prediction the record's own loop, the alternative at the free fit's pair (the
    whole record, no break: pulled by the events), none stands."""
    from hapsim.analysis.unseen_verdict import break_cost_gain
    explained = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        n, sigma = 800, 1e-6
        r, w = rng.uniform(0.985, 0.997), rng.uniform(0.04, 0.2)
        z = (r * np.exp(1j * w), rng.uniform(0.3, 0.8))
        events = sorted(rng.choice(np.arange(20, n - 20), size=int(rng.integers(1, 11)),
                                   replace=False).tolist())
        y = _synthetic(rng, n, z, events, sigma)
        true = [z[0], np.conj(z[0]), z[1]]
        fit = {"offset": False, "rows": [np.arange(n)]}
        p = r ** (1.0 / fac) * np.exp(1j * w)
        got = break_cost_gain(y, fit, [p, np.conj(p), z[1]], true, floor=sigma, drop=5)
        explained += got["predicted"]["explained"]
        assert got["stands"], (seed, got["gain"], got["limit"])
        f = _free_pair(y, z[1], [-np.log(r), w])
        same = break_cost_gain(y, fit, true, [f, np.conj(f), z[1]], floor=sigma, drop=5)
        assert same["predicted"]["explained"] and not same["stands"], (seed, same["gain"])
    assert explained >= 10, explained          # the class happened: breaks explained it

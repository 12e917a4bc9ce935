"""A board on its own tick that mistimes holds no host sees, for
:func:`hapsim.pipeline.measure.identify_run`: the holds found in the record and cut
(:func:`cut_unseen_holds`), a "differs" reviewed against the predicted loop with the
breaks its unseen holds may have made (:func:`review_differs`,
:func:`hapsim.analysis.unseen_verdict.break_prediction`), and one left unsaid where the
board's tick walked across the host's writes (:func:`review_tick_walk`)."""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.measurement import verdict
from hapsim.drivers.sketch_timing import FIRMWARE_TICK_S
from hapsim.drivers.tick_align import TickAligned
from hapsim.errors import ConfigError

__all__ = ["cut_unseen_holds", "review_differs", "review_tick_walk", "TICK_MOVED_MAX"]

#: How far the board's tick may have moved against the host's writes over a run, found
#: by the probe at its stop, for a "differs" to stand [ticks]: the band the writes are
#: kept in from the boundary (:attr:`hapsim.drivers.tick_align.TickAligned.BAND`, 0.15),
#: the probe placing the boundary to a sixteenth of a tick and less.
TICK_MOVED_MAX = TickAligned.BAND


def review_tick_walk(measured: dict, driver) -> dict:
    """Leave a "differs" unsaid where the board's tick walked across the host's writes.

    A board whose oscillator is off the host's clock walks its tick across writes the
    host aligned to it once; the handle's read then moves from the command's end to the
    board's tick (or back), and the loop's delay changes within the record: offline, on
    random paddles 1,000-5,000 ppm off, the matching paddle was said to differ in 3 of 16
    (docs/drivers.md, "A board whose oscillator is off the host's clock"). The probe at
    the run's stop (:meth:`hapsim.drivers.tick_align.TickAligned.end_probe`) tells the
    walk's distance to a whole number of ticks, or that the boundary could not be placed
    again (a walk smearing the probe itself): more than :data:`TICK_MOVED_MAX`, or not
    placed, and the "differs" becomes "not measurable" with the reason. A walk within
    that of a whole number of ticks the placements cannot tell from none: the board's
    rate between two groups of them (``walk_rate``, ``walk_sd``:
    :func:`hapsim.drivers.tick_align.walk_from_placements`) tells it, and a "differs"
    stands only where that walk, three of its standard deviations added, is within
    ``1 - TICK_MOVED_MAX`` of none (no whole tick walked). A "within" is left as it is
    (on those paddles a device that differs was never said to be within).

    Parameters
    ----------
    measured : dict
        The run's measurement (``verdict``, ``within``); changed in place.
    driver : hapsim.drivers.base.Driver or None
        The run's driver: its ``tick_moved`` (None: not probed, nothing changed) and
        ``tick_s``, the board's nominal tick [s] (the Hapkit sketch's 0.992 ms where it
        has none).

    Returns
    -------
    dict
        ``measured``.
    """
    moved = getattr(driver, "tick_moved", None)
    if (moved is None or measured.get("within") is not False
            or not str(measured.get("verdict", "")).startswith("measured differs")):
        return measured
    rated = "walk_rate" in moved
    if (moved["found"] and abs(moved["moved"]) <= TICK_MOVED_MAX
            and (not rated or abs(moved["walk_rate"]) + 3 * moved["walk_sd"]
                 <= 1.0 - TICK_MOVED_MAX)):
        return measured
    tick_s = float(getattr(driver, "tick_s", 0.0) or FIRMWARE_TICK_S)
    if not moved["found"]:
        seen = ("could not be placed again at the run's stop (a tick walking across the "
                "probe's own writes)")
    elif rated and abs(moved["moved"]) <= TICK_MOVED_MAX:
        seen = (f"walked {moved['walk_rate']:+.2f} +- {moved['walk_sd']:.2f} ticks against "
                f"the host's writes over {moved['seconds']:.2f} s by the board's rate "
                f"({moved['rate_ppm']:+.0f} ppm off the host's clock): not told from a "
                f"walk of whole ticks (the placements alone read {moved['moved']:+.2f} of "
                f"a tick)")
    else:
        seen = (f"moved {abs(moved['moved']):.2f} of a tick against the host's writes "
                f"over {moved['seconds']:.2f} s (its oscillator at least "
                f"{abs(moved['moved']) * tick_s / max(moved['seconds'], 1e-9) * 1e6:.0f} "
                f"ppm off the host's clock)")
    measured["tick_walk"] = dict(moved)
    measured["verdict"] = (
        f"not measurable: the board's tick {seen}; the host aligned its writes to it once, "
        f"and a tick walking across them changes the loop's delay within the record: the "
        f"departure is no evidence that the device differs; rerun, or with the board in "
        f"lockstep")
    return measured


def review_differs(pred: dict, measured: dict, state: dict) -> dict:
    """Let a "differs" stand only where the predicted loop, broken where the board may
    have mistimed holds no host saw, does not explain the record to its noise.

    Nor where the loop of the pair measured, with its own breaks, explains it at a far
    lower cost (:func:`hapsim.analysis.unseen_verdict.break_cost_gain`: breaks explain
    anything when enough are taken; ``prediction_test`` then has ``explained`` False and
    ``measured_loop_gain``, ``gain_limit``, ``measured_loop_breaks``).

    When it does, the record is measured again with those breaks cut as the holds found
    are (:func:`hapsim.analysis.unseen_holds.hold_rows`): within the stated uncertainty
    then, that is the measurement; otherwise the run is "not measurable" with the reason
    and the breaks' count. When it does not, the "differs" stands, with the test's figures.

    Parameters
    ----------
    pred : dict
        The prediction (``k`` [N/m], ``b`` [N s/m]).
    measured : dict
        The measurement whose verdict is "differs" (:func:`hapsim.analysis.measurement.
        verdict`'s ``within`` False).
    state : dict
        What :func:`cut_unseen_holds` leaves for it: ``fitted``
        (``fitted(exclude, fit) -> dict``), ``fit`` (the last fit's modes and rows),
        ``exclude`` (bool, shape (n,): the rows cut), ``position`` [m], ``poles`` (the
        predicted poles), ``floor`` [m] and ``drop`` (rows dropped after a cut);
        optionally ``alternative``: the loop the record measured (``poles``, and
        ``position``, the record with its known inputs taken out through it); default
        the predicted loop with the pair the fit measured
        (:func:`hapsim.analysis.unseen_verdict.measured_loop_poles`).

    Returns
    -------
    dict
        The measurement to report, with ``prediction_test``: ``explained``, ``breaks``
        (count), ``chi2``, ``limit``, ``dof`` (:func:`~hapsim.analysis.unseen_verdict.
        break_prediction`).
    """
    from hapsim.analysis.unseen_holds import hold_rows
    from hapsim.analysis.unseen_verdict import (break_cost_gain, break_prediction,
                                                measured_loop_poles)
    got = break_prediction(state["position"], state["fit"], state["poles"],
                           floor=state["floor"], drop=state["drop"])
    test = {q: got[q] for q in ("explained", "chi2", "limit", "dof")}
    test["breaks"] = int(got["breaks"].size)
    measured["prediction_test"] = test
    if not got["explained"]:
        return measured
    # the measured pair's loop, with its own breaks: explaining the record at a far lower
    # cost, the departure stands whatever breaks the predicted loop was allowed
    other = state.get("alternative") or {}
    alt = other.get("poles")
    if alt is None:
        alt = measured_loop_poles(state["poles"], state["fit"].get("spec", []))
    if alt is not None:
        cmp = break_cost_gain(state["position"], state["fit"], state["poles"], alt,
                              floor=state["floor"], drop=state["drop"],
                              alternative_position=other.get("position"), predicted=got)
        test["measured_loop_gain"] = cmp["gain"]
        test["gain_limit"] = cmp["limit"]
        test["measured_loop_breaks"] = int(cmp["alternative"]["breaks"].size)
        if cmp["stands"]:
            test["explained"] = False
            return measured
    # measured again with the breaks cut as the holds found are
    ex = np.asarray(state["exclude"], bool) | hold_rows(len(state["position"]),
                                                         got["breaks"])
    again = state["fitted"](ex, {})
    verdict(pred, again)
    if again.get("within") is True:
        for q in ("unseen_holds", "unseen_hold_seqs", "unseen_hold_tau_ms", "note",
                  "prediction_test"):
            if q in measured:
                again.setdefault(q, measured[q])
        return again
    measured["within"] = False
    how = ("" if "k" not in again else
           f"; cut there, k {again['k']:.6g} +-{again['k_interval']:.3g}, "
           f"b {again['b']:.6g} +-{again['b_interval']:.3g}")
    measured["verdict"] = (
        f"not measurable: the board on its own tick mistimed holds no host saw, and the "
        f"predicted loop with {test['breaks']} breaks where such holds may have struck "
        f"explains the record to its noise (chi-square {test['chi2']:.3g} against "
        f"{test['limit']:.3g}, {test['dof']} degrees of freedom){how}: the departure is "
        f"no evidence that the device differs; rerun, or with the board in lockstep")
    return measured


def cut_unseen_holds(scene, fitted, exclude, position, cols, quantum, driver,
                     unread, poles, given=None) -> dict:
    """:func:`hapsim.pipeline.measure.identify_run`'s fit of a board on its own tick, with
    the holds it mistimed that no host saw cut out
    (:func:`hapsim.analysis.unseen_holds.find_unseen_holds`).

    Fit, find the rows whose hold signature stands out of the residual, cut them
    (:func:`~hapsim.analysis.unseen_holds.hold_rows`, as the host-marked holds), fit
    again, at most :data:`~hapsim.analysis.unseen_holds.MAX_PASSES` times more. With
    none found the first fit is the measurement, unchanged.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene.
    fitted : callable
        ``fitted(exclude, fit) -> dict``: :func:`hapsim.analysis.measurement.identify` on
        the run's record with these rows left out (``fit`` filled as it says).
    exclude : ndarray of bool, shape (n,)
        The rows already left out.
    position : ndarray, shape (n,)
        The record measured [m] (the late ticks' response taken out).
    cols : dict of ndarray
        The telemetry columns (``force`` [N], ``seq``), shape (n,).
    quantum : float
        The sensor's step [m].
    driver : hapsim.drivers.base.Driver
        The run's driver (its ``position_rel``: the wire's rounding in the floor).
    unread : ndarray of bool, shape (n,)
        Rows whose error the stated uncertainty bounds already (an estimated position, a
        force the account cannot name, a late tick's accounted force): no hold is sought
        near them (:func:`~hapsim.analysis.unseen_holds.find_unseen_holds`' ``unread``).
    poles : array_like of complex
        The predicted closed-loop poles (for a "differs"'s review,
        :func:`hapsim.pipeline.unseen_review.review_differs`).
    given : (list of int, list of float), optional
        Holds found before (rows, mistimings [s]: a measurement's ``_hold_rows``), cut
        without a search (:mod:`hapsim.pipeline.loop_refit`'s fits at other loops).

    Returns
    -------
    dict
        The measurement; with ``unseen_holds`` (how many were cut, 0 if none) and, when
        some were, ``unseen_hold_seqs`` (the ``seq`` of each one's first disturbed row,
        at most 100) and ``unseen_hold_tau_ms`` (each one's mistiming [ms], quarter
        ticks: positive, taken late); ``_unseen``, what a "differs"'s review needs
        (:func:`review_differs`' ``state``), popped by
        :func:`hapsim.pipeline.measure.identify_run`; ``_hold_rows``, the rows and
        mistimings cut (``given``'s form).
    """
    from hapsim.analysis.error_response import force_error_response, sensor_error_response
    from hapsim.analysis.identify import sensor_sd
    from hapsim.analysis.unseen_holds import (MAX_PASSES, find_unseen_holds, hold_rows,
                                              mistimings)
    n = int(cols["seq"].size)
    tried = mistimings(scene.period, float(driver.tick_s))
    x = np.asarray(position, float)
    pr = float(getattr(driver, "position_rel", 0.0) or 0.0)
    floor = math.hypot(sensor_sd(quantum, scene.device.noise),
                       pr * float(np.max(np.abs(x))) / math.sqrt(3.0) if n else 0.0)
    fit: dict = {}
    if given is not None:
        # the holds a search made before (at another loop), cut as they are
        rows, taus = [int(j) for j in given[0]], [float(t) for t in given[1]]
        ex = np.asarray(exclude, bool) | hold_rows(n, rows)
        measured = fitted(ex, fit)
        last = (fit, ex, measured)
        passes = 0
    else:
        measured = fitted(exclude, fit)
        if not fit:                    # no variable projection: an exact record, or none
            measured["unseen_holds"] = 0
            measured["_hold_rows"] = ([], [])
            return measured
        rows, taus = [], []
        ex = np.asarray(exclude, bool).copy()
        last = (fit, ex.copy(), measured)
        passes = MAX_PASSES
    try:
        S, H = sensor_error_response(scene, n), force_error_response(scene, n)
    except ConfigError:
        passes = 0
    for _ in range(passes):
        got = find_unseen_holds(x, cols["force"], fit, scene.period, S, H, tried,
                                floor=floor, lead=math.ceil(float(scene.device.delay)) + 3,
                                unread=unread)
        # a hold whose rows are cut already (one before a stretch, found again by its
        # tail) changes nothing: the search stops when no hold found cuts a new row
        new = [(j, t) for j, t in zip(got["rows"].tolist(), got["tau_s"].tolist())
               if np.any(hold_rows(n, [j]) & ~ex)]
        if not new:
            break
        rows += [j for j, _ in new]
        taus += [t for _, t in new]
        ex |= hold_rows(n, [j for j, _ in new])
        fit = {}
        measured = fitted(ex, fit)
        if not fit:
            break
        last = (fit, ex.copy(), measured)
    measured["unseen_holds"] = len(rows)
    measured["_hold_rows"] = (list(rows), list(taus))
    if last[2] is measured and "k" in measured and last[0]:
        measured["_unseen"] = {
            "fitted": fitted, "fit": last[0], "exclude": last[1], "position": x,
            "poles": poles, "floor": floor,
            "drop": math.ceil(float(scene.device.delay)) + 2}
    if rows:
        seq = np.asarray(cols["seq"], np.int64)
        measured["unseen_hold_seqs"] = [int(seq[j]) for j in rows[:100]]
        measured["unseen_hold_tau_ms"] = [round(t * 1e3, 3) for t in taus[:100]]
    return measured

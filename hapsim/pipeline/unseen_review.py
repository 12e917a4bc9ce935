"""A "differs" of a board on its own tick reviewed against the predicted loop with the
breaks its unseen holds may have made (:func:`hapsim.analysis.unseen_verdict.
break_prediction`), for :func:`hapsim.pipeline.measure.identify_run`."""

from __future__ import annotations

import numpy as np

from hapsim.analysis.measurement import verdict

__all__ = ["review_differs"]


def review_differs(pred: dict, measured: dict, state: dict) -> dict:
    """Let a "differs" stand only where the predicted loop, broken where the board may
    have mistimed holds no host saw, does not explain the record to its noise.

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
        What :func:`hapsim.pipeline.measure._cut_unseen_holds` leaves for it: ``fitted``
        (``fitted(exclude, fit) -> dict``), ``fit`` (the last fit's modes and rows),
        ``exclude`` (bool, shape (n,): the rows cut), ``position`` [m], ``poles`` (the
        predicted poles), ``floor`` [m] and ``drop`` (rows dropped after a cut).

    Returns
    -------
    dict
        The measurement to report, with ``prediction_test``: ``explained``, ``breaks``
        (count), ``chi2``, ``limit``, ``dof`` (:func:`~hapsim.analysis.unseen_verdict.
        break_prediction`).
    """
    from hapsim.analysis.unseen_holds import hold_rows
    from hapsim.analysis.unseen_verdict import break_prediction
    got = break_prediction(state["position"], state["fit"], state["poles"],
                           floor=state["floor"], drop=state["drop"])
    test = {q: got[q] for q in ("explained", "chi2", "limit", "dof")}
    test["breaks"] = int(got["breaks"].size)
    measured["prediction_test"] = test
    if not got["explained"]:
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

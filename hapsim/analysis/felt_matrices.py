"""The felt matrices measured against the predicted ones: the deviation of a fit from the
prediction (:func:`felt_deviation`), along the principal directions
(:func:`felt_directions`), and the verdict stated with its uncertainty
(:func:`felt_verdict`) -- the n-D run's statement, as
:func:`hapsim.analysis.measurement.verdict` is the 1-D run's."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["said_before_run", "felt_deviation", "felt_directions", "felt_verdict", "statement_name",
           "noise_pair_verdict", "MEASURABLE_WIRE", "FELT_QUANTITIES"]


def felt_deviation(fit: dict, chk) -> dict | None:
    """How far measured felt matrices are from the predicted ones.

    Parameters
    ----------
    fit : dict
        :func:`hapsim.analysis.pencil.fit_felt_nd`'s result.
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.

    Returns
    -------
    dict or None
        ``felt_stiffness`` and ``felt_damping``: the largest entry of
        ``|measured - predicted|`` over the predicted matrix's largest entry [-]; None
        when either side has no felt matrices.
    """
    k, b = chk.render.felt_stiffness, chk.render.felt_damping
    if fit["felt_stiffness"] is None or k is None:
        return None
    return {"felt_stiffness": float(np.max(np.abs(fit["felt_stiffness"] - k))
                                    / np.max(np.abs(k))),
            "felt_damping": float(np.max(np.abs(fit["felt_damping"] - b))
                                  / np.max(np.abs(b)))}

#: Largest first-order change (relative) that the readings' rounding may cause in a felt
#: quantity (the felt stiffness or damping matrix as a whole, or along one principal
#: direction) for that quantity to be stated: beyond it the excitation is too small for
#: the wire's or the encoders' resolution, the neglected higher orders of the fit's
#: perturbation (of the order of the first-order term's square) are no longer small
#: against the first, and that quantity is "not measurable".
MEASURABLE_WIRE = 0.25

FELT_QUANTITIES = ("felt_stiffness", "felt_damping")

def felt_directions(fit: dict, chk) -> dict | None:
    """The measured and predicted felt stiffness and damping along the prediction's
    principal directions.

    Along a unit direction ``e`` the felt stiffness is the quadratic form ``e^T k e``
    [N/m] (the force per displacement the hand feels along ``e`` when it pushes along
    ``e``; only the symmetric part of ``k`` contributes) and the felt damping ``e^T b e``
    [N s/m]. The directions are the check's principal directions ``e_i``
    (:mod:`hapsim.analysis.ths`: the major axis of rendered mode ``i``); for a loop
    that is symmetric in one basis (``M``, ``B0``, ``K``, ``B`` diagonal in it) they are
    the eigenvectors of ``k`` and ``b`` and ``e_i^T k e_i = m_i |s_i|^2`` (the check's
    ``direction_stiffness``); otherwise the two differ by the loop's asymmetric coupling
    (on the shipped scenes by at most 2e-5 relative) and the directions need not be
    orthogonal. The quadratic form is a statement about a fixed direction, so it stays
    well defined where two modes' poles coincide and their major axes are arbitrary;
    being linear in the matrix, its first-order wire term is exact
    (:func:`wire_terms_nd`).

    Parameters
    ----------
    fit : dict
        :func:`hapsim.analysis.pencil.fit_felt_nd`'s result.
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.

    Returns
    -------
    dict or None
        ``directions`` (n unit vectors, the columns ``e_i``), ``damping_factor``
        (``|s_i| / (2 |Re s_i|)`` of mode ``i`` [-]: the linearisation bound's factor
        for the damping along ``e_i``, :mod:`hapsim.analysis.linearisation`),
        ``largest`` (each predicted matrix's largest entry), and for
        ``felt_stiffness`` and ``felt_damping`` a list of n dicts ``predicted``,
        ``measured`` (``e_i^T X e_i``, [N/m] or [N s/m]) and ``deviation``
        (``|measured - predicted| / |predicted|`` [-], inf when ``predicted`` is 0). None
        when either side has no felt matrices.
    """
    r = chk.render
    if fit["felt_stiffness"] is None or r.felt_stiffness is None or r.directions is None:
        return None
    E = np.asarray(r.directions, float)
    s = np.log(np.asarray(r.rendered_poles, complex))   # s_i T: the factor is T-free
    out = {"directions": [E[:, i].tolist() for i in range(E.shape[1])],
           "damping_factor": [float(abs(v) / (2.0 * abs(v.real))) if v.real != 0
                              else math.inf for v in s]}
    out["largest"] = {}
    for q in FELT_QUANTITIES:
        P, Mx = np.asarray(getattr(r, q), float), np.asarray(fit[q], float)
        out["largest"][q] = float(np.max(np.abs(P)))
        rows = []
        for i in range(E.shape[1]):
            e = E[:, i]
            p, m = float(e @ P @ e), float(e @ Mx @ e)
            rows.append({"predicted": p, "measured": m,
                         "deviation": abs(m - p) / abs(p) if p != 0 else math.inf})
        out[q] = rows
    return out

_WORDS = {"felt_stiffness": "felt stiffness", "felt_damping": "felt damping"}

def statement_name(quantity: str, direction=None) -> str:
    """How a statement is named in a report: ``"felt stiffness"`` (the matrix as a whole)
    or ``"felt stiffness along (+0.000, +1.000)"``.

    Parameters
    ----------
    quantity : {"felt_stiffness", "felt_damping"}
    direction : array_like, shape (n,), optional
        The unit direction.

    Returns
    -------
    str
    """
    w = _WORDS[quantity]
    if direction is None:
        return w
    return w + " along (" + ", ".join(f"{v:+.3f}" for v in direction) + ")"

def _statement(quantity, direction, predicted, measured, deviation, lin, wire, limit,
               roundoff=0.0, why_not=None, how="first order") -> dict:
    """One statement of :func:`felt_verdict` (its notes)."""
    out = {"quantity": quantity, "direction": direction,
           "name": statement_name(quantity, direction), "predicted": predicted,
           "measured": measured, "deviation": deviation,
           "linearisation": lin if lin is not None and math.isfinite(lin) else None,
           "roundoff": roundoff if math.isfinite(roundoff) else None,
           "wire": wire if wire is not None and math.isfinite(wire) else None,
           "uncertainty": None, "verdict": "not measurable", "within": None,
           "reason": why_not}
    if why_not is not None:
        return out
    if lin is None or not math.isfinite(lin):
        out["reason"] = "no finite linearisation bound for it (an undamped mode)"
        return out
    if wire is not None and not (math.isfinite(wire) and wire <= limit):
        out["reason"] = (f"the readings' rounding alone may move it by {wire:.2g} "
                         f"(relative, {how}), above {limit:g}")
        return out
    if not (math.isfinite(deviation)):
        out["reason"] = "its predicted value is 0: no relative statement"
        return out
    u = lin + (wire or 0.0) + (roundoff if math.isfinite(roundoff) else 0.0)
    ok = deviation <= u
    out.update(uncertainty=u, verdict="within" if ok else "differs", within=bool(ok),
               reason=(f"measured - predicted {deviation:.2e} "
                       + ("<=" if ok else ">") + f" the stated uncertainty {u:.2e}"))
    return out

def felt_verdict(deviation, bound, wire=None, *, limit: float = MEASURABLE_WIRE,
                 estimated: int = 0, directions=None, excluded=None) -> dict:
    """The verdict of an n-D measurement against its stated uncertainty, per quantity
    and per principal direction.

    **What is stated.** The felt stiffness matrix and the felt damping matrix as a whole
    (the largest entry of ``|measured - predicted|`` over the predicted matrix's largest
    entry: :func:`felt_deviation`), and, given ``directions``, the felt stiffness and
    damping along each principal direction ``e_i`` of the prediction
    (``e_i^T X e_i`` over ``|e_i^T X_pred e_i|``: :func:`felt_directions`). Each
    statement says "within", "differs" or "not measurable" with its own uncertainty.

    **Each statement's uncertainty** (relative, first order) is the linearisation bound
    plus the wire's term plus the binary64 round-off allowance
    (:attr:`hapsim.analysis.linearisation.LinearisationBound.roundoff`, relative to
    the matrix's largest entry, so ``roundoff max|X_pred| / |e_i^T X_pred e_i|`` along a
    direction):

    * linearisation (:mod:`hapsim.analysis.linearisation`): a relative change
      ``eps`` of the loop's stiffness and inertia terms (``eps_k = (c_kin + c_link) a``)
      scales each rendered ``s_i^2`` by at most ``1 +- eps``, so the felt stiffness
      along ``e_i``, ``k_i = m_i |s_i|^2``, moves by at most ``eps_k k_i`` (relative
      ``eps_k``), and the felt damping ``b_i = -2 m_i Re s_i`` by at most
      ``m_i eps_k |s_i|``, relative ``eps_k |s_i| / (2 |Re s_i|)`` with mode ``i``'s own
      factor (a stiff, well-damped direction is not charged the lightly damped
      direction's factor). For a matrix as a whole the largest factor over the modes is
      taken (:attr:`LinearisationBound.damping`);
    * the wire (:func:`wire_terms_nd`): the first-order worst case of the same quantity's
      change under the readings' and the forces' rounding, whatever their signs and
      correlation: for a direction, Hoelder's inequality on the linear form
      ``e_i^T dX e_i`` of the fit's first-order change ``dX``, over ``|e_i^T X_pred e_i|``
      (for the two faders and the Hapkit pantograph's firmware taken over the errors'
      box with a margin, :mod:`hapsim.analysis.wire_box`: the fit is too
      ill-conditioned for the first-order term at the records alone to bound what
      errors within the bounds do; a verdict that states nothing then extrapolates the
      excitation needed from the first-order term, a lower bound; for the Falcon and
      the 2DIY their rounding by draws of its phase through the loop,
      :mod:`hapsim.analysis.wire_rounding`, named by the wire's ``how``, the 2DIY's
      other errors over the box).

    **When a statement is made.** Not at all when no felt matrices were measured, or
    when the amplitude reaches a contact's or a plane's depth (the law is not smooth:
    nothing linear holds). A quantity whose wire term exceeds ``limit`` (or is not
    finite, or whose predicted value is 0) is "not measurable": the excitation is too
    small for the resolution *for that quantity*, and the first-order expansion no longer
    holds for it. Along a stiff direction the same rounding is small against the force
    rendered while along a soft one it is not, and the damping (a small real part of
    each pole) is always more sensitive than the stiffness, so one run may state the
    stiffness along one direction and nothing else.

    **The run's verdict** is the conjunction of what was stated: "differs" when any
    stated quantity differs; "within" when every quantity was stated and is within;
    "partly within" when every stated one is within but some could not be stated (the
    reason and ``not_stated`` name them: a reader of the verdict alone is not told that
    an unmeasured damping was verified); "not measurable" when nothing could be stated.

    Parameters
    ----------
    deviation : dict or None
        :func:`felt_deviation`'s result.
    bound : hapsim.analysis.linearisation.LinearisationBound
    wire : dict or None, optional
        ``felt_stiffness`` and ``felt_damping``: the wire's relative terms for the
        matrices, and optionally ``directions`` (:func:`wire_terms_nd`); None: the
        record is exact, binary64 on the wire.
    limit : float, optional
        :data:`MEASURABLE_WIRE`.
    estimated : int, optional
        Estimated samples (missing replies) whose error bounds the wire's term carries
        (named in the reason).
    directions : dict, optional
        :func:`felt_directions`'s result (without it, or without the wire's
        ``directions`` when there is a wire, only the matrices are stated).
    excluded : dict, optional
        ``{statement name: reason}``: statements not made whatever their terms here (a
        prediction made before the run said they cannot be: a run never states what its
        own prediction excluded), "not measurable" with the reason.

    Returns
    -------
    dict
        ``verdict`` (``"within"``, ``"partly within"``, ``"differs"`` or ``"not
        measurable"``), ``within`` (bool: every *stated* quantity within; None when
        nothing was stated), ``uncertainty`` (``felt_stiffness``,
        ``felt_damping``: each matrix's stated uncertainty [-], None for one not stated;
        None when nothing was stated), ``reason`` (str), ``statements`` (list of dicts:
        ``quantity``, ``direction`` (unit vector or None for the matrix), ``name``,
        ``predicted``, ``measured`` (along the direction; None for a matrix),
        ``deviation``, ``linearisation``, ``wire``, ``roundoff``, ``uncertainty`` [-],
        ``verdict``,
        ``within``, ``reason``) and ``not_stated`` (the names of the quantities that
        were not measurable).
    """
    lin = bound.to_dict()
    wq = {q: (None if wire is None else float(wire[q])) for q in FELT_QUANTITIES}
    wdir = None if wire is None else (wire.get("directions") if isinstance(wire, dict)
                                      else None)
    dirs = directions if (directions is not None and (wire is None or wdir is not None)) \
        else None

    def no(reason):
        return {"verdict": "not measurable", "within": None, "uncertainty": None,
                "reason": reason, "statements": [], "not_stated": ["felt stiffness",
                                                                   "felt damping"]}
    if deviation is None:
        return no("the records give no felt matrices (fewer than n rendered pairs)")
    if lin["felt_stiffness"] is None:
        if not math.isnan(getattr(bound, "opening", math.nan)):
            return no(f"the records' motion toward opening {bound.opening_name!r} reaches "
                      f"{bound.opening:.3g} times its depth at rest (the motion "
                      f"{bound.amplitude:g} m from rest): the contact opens, no linear "
                      "estimate holds")
        return no(f"the motion ({bound.amplitude:g} m from rest) reaches the depth of "
                  f"{bound.depth_name!r} ({bound.depth:.3g} m): the contact opens, no "
                  "linear estimate holds")
    rnd = float(getattr(bound, "roundoff", 0.0))
    # the wire's term taken over the errors' box (hapsim.analysis.wire_box) or at first order
    how = ((wire.get("how") or ("over the errors' box" if wire.get("box")
                                else "first order")) if isinstance(wire, dict)
           else "first order")
    excluded = excluded or {}
    st = []
    for q in FELT_QUANTITIES:
        st.append(_statement(q, None, None, None, float(deviation[q]), lin[q], wq[q],
                             limit, rnd, excluded.get(statement_name(q)), how=how))
    if dirs is not None:
        eps = lin["felt_stiffness"]
        for q in FELT_QUANTITIES:
            for i, row in enumerate(dirs[q]):
                lq = eps if q == "felt_stiffness" else eps * dirs["damping_factor"][i]
                p = abs(row["predicted"])
                rq = rnd * dirs["largest"][q] / p if p > 0 else math.inf
                e = [float(v) for v in dirs["directions"][i]]
                st.append(_statement(q, e, row["predicted"], row["measured"],
                                     row["deviation"], lq,
                                     None if wdir is None else float(wdir[q][i]),
                                     limit, rq, excluded.get(statement_name(q, e)),
                                     how=how))
    stated = [s for s in st if s["verdict"] != "not measurable"]
    not_stated = [s["name"] for s in st if s["verdict"] == "not measurable"]
    what = ("linearisation bound plus the wire's rounding" if wire is not None else
            "the linearisation bound; binary64 on the wire adds nothing")
    unc = {q: st[j]["uncertainty"] for j, q in enumerate(FELT_QUANTITIES)}
    if not stated:
        wk, wd = wq["felt_stiffness"] or 0.0, wq["felt_damping"] or 0.0
        # a term over the error box carries the first-order one at the records: the
        # excitation needed is extrapolated from that one (inverse in the excitation to
        # first order), a lower bound, the box's term never being below it
        first = wire.get("first_order") if isinstance(wire, dict) else None
        big = max(wk, wd) if first is None else max(float(first[q]) for q in FELT_QUANTITIES)
        need = bound.amplitude * big / limit if math.isfinite(big) else None
        out_ = [s["name"] for s in st if excluded.get(s["name"]) is not None]
        if out_:
            rest = [s["name"] for s in st if s["name"] not in out_]
            reason = (f"{excluded[out_[0]]}: {', '.join(out_)}"
                      + (f"; {', '.join(rest)}: not measurable here either (each "
                         "statement's reason)" if rest else ""))
        elif estimated:
            reason = (f"the readings' errors (the wire's rounding and {estimated} "
                      f"estimated samples, missing replies) alone may move the felt "
                      f"stiffness by {wk:.2g} and the damping by {wd:.2g} (relative, "
                      f"{how}), above {limit:g}, and no principal direction is measurable "
                      "either: fewer missing replies (or a larger excitation) are needed")
        elif (not math.isfinite(max(wk, wd)) and isinstance(wire, dict)
              and wire.get("rounding")
              and wire["rounding"]["lost"] + wire["rounding"]["noise"] > 0):
            # a draw of the rounding's phase lost a pair of the loop or rendered a noise
            # pair (hapsim.analysis.wire_rounding)
            rd = wire["rounding"]
            reason = (f"in {rd['lost'] + rd['noise']} of {rd['draws']} draws of the "
                      "rounding's phase the fit lost a pair of the loop "
                      f"({rd['lost']}) or rendered a noise pair ({rd['noise']}): the "
                      "records do not determine every rendered pair (stretches cut "
                      f"short, or an excitation {bound.amplitude:g} m too small for the "
                      "wire's resolution)")
        elif not math.isfinite(max(wk, wd)) and how != "first order" and first is None:
            # a point of the box gave no felt matrices (hapsim.analysis.wire_box: fewer
            # than n pairs of the fit above the records' errors there)
            reason = (f"the readings' rounding alone may move the felt stiffness by "
                      f"{wk:.2g} and the damping by {wd:.2g} (relative, {how}), "
                      f"above {limit:g}, and no principal direction is measurable either: "
                      "within the errors' box the records do not determine every rendered "
                      "pair (stretches cut short, or an excitation "
                      f"{bound.amplitude:g} m too small for the wire's resolution)")
        else:
            reason = (f"the readings' rounding alone may move the felt stiffness by "
                      f"{wk:.2g} and the damping by {wd:.2g} (relative, {how}), "
                      f"above {limit:g}, and no principal direction is measurable either: "
                      f"the excitation {bound.amplitude:g} m is too small for the wire's "
                      "resolution" + ("" if need is None else
                                      f" (about {need:.2g} m or more is needed)"
                                      if first is None else
                                      f" (at least about {need:.2g} m is needed, the "
                                      "first-order term's extrapolation)"))
        out = no(reason)
        out.update(statements=st, not_stated=not_stated)
        return out
    bad = [s for s in stated if s["verdict"] == "differs"]
    ok = not bad
    if ok and not not_stated:
        reason = (f"measured = predicted within the stated uncertainty ({what})"
                  + (", as matrices and along each principal direction" if dirs is not None
                     else ""))
    elif ok:
        reason = (f"measured = predicted within the stated uncertainty ({what}): "
                  + ", ".join(s["name"] for s in stated))
    else:
        reason = ("measured differs from predicted by more than the stated uncertainty "
                  f"({what}): " + ", ".join(s["name"] for s in bad))
    if not_stated:
        reason += ("; not measurable (the wire's rounding too large against it"
                   + (f", {estimated} estimated samples" if estimated else "") + "): "
                   + ", ".join(not_stated))
    verdict = "differs" if not ok else ("partly within" if not_stated else "within")
    return {"verdict": verdict, "within": bool(ok),
            "uncertainty": unc, "reason": reason, "statements": st,
            "not_stated": not_stated}


def noise_pair_verdict(by: str) -> dict:
    """The verdict of records whose own fit renders a noise pair: nothing stated (a
    "differs" built on it would be wrong; :func:`hapsim.analysis.wire_rounding.noise_pair`).

    Parameters
    ----------
    by : str
        What set the noise pair, in words (``"the rounding"``, ``"the errors"``).

    Returns
    -------
    dict
        ``verdict`` "not measurable", ``within`` and ``uncertainty`` None, no statements,
        both felt matrices not stated, ``reason``.
    """
    return {"verdict": "not measurable", "within": None, "uncertainty": None,
            "statements": [], "not_stated": ["felt stiffness", "felt damping"],
            "reason": "the records' fit renders a pair nearer one of the loop's fast poles "
                      f"than any pair the loop renders (a noise pair set by {by}): no felt "
                      "matrices of the loop"}


def said_before_run(how: str, stated, not_stated, reason: str) -> str | None:
    """The sentence a run says on stderr before its loop when its prediction (the run's
    own records and statement taken in lockstep: the Falcon's
    :func:`hapsim.emulated.falcon_felt.felt_feasibility`, the 2DIY's) excludes
    statements (issue 31 item 4).

    Parameters
    ----------
    how : str
        How the prediction was made (in parentheses after "predicted before the run").
    stated, not_stated : list of str
        The statements' names (:func:`statement_name`) the prediction makes and does not.
    reason : str
        Why, with the numbers.

    Returns
    -------
    str or None
        None when every statement will be made.
    """
    if not not_stated:
        return None
    if not stated:
        return f"felt matrices not measurable, predicted before the run ({how}): {reason}"
    return (f"felt matrices partly measurable, predicted before the run ({how}): not "
            f"stated: {', '.join(not_stated)}: {reason}")


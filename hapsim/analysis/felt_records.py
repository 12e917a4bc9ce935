"""The felt matrices of records cut at their disturbances, each record fitted on its own
undisturbed stretches (issue 29): the wire's term of such a fit.

A measurement of the n-D felt matrices takes ``2n + 1`` free responses of the loop, the
first from rest (:func:`hapsim.lockstep.excitation_starts`). Whole records are fitted as
their differences against the record from rest
(:func:`hapsim.lockstep.wire_terms_nd`), which removes the equilibrium. A record cut
where a disturbance acted (a lost byte's re-synchronisation, a host stall: its
undisturbed stretches fitted jointly, :func:`hapsim.analysis.pencil.fit_felt_nd`'s
``usable``) cannot be differenced so: a difference holds only the rows undisturbed in
*both* records, so each record's cuts are the other's too. Measured on the Haply 2DIY's
records with 1 byte in 200 lost each way (``tools/driver_timing.py --drivers haply2
--loss 0.005``, seeds 1-6, about 5 re-synchronisations a record): the differences kept 1
to 53 equations of the 194 to 363 the records' own stretches hold; 2 of the 6 runs were
"not measurable", one of them with its fit off by 7e4 % in the felt stiffness, and none
stated the damping.

Here every record, the one from rest among them, is fitted on its own stretches, the
equilibrium taken by the affine prediction (:func:`hapsim.analysis.pencil.fit_felt_nd`
with ``offset=True``: one unknown more per coordinate, shared by every stretch; exact on
exact data, the equilibrium of a loop whose force is computed from its readings being
where that force is zero, whatever an encoder's offset). Each record's errors then enter
its own fit only (no record from rest's errors in every difference).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["wire_terms_records", "within_excursion", "window_rows"]

#: The error kinds (:func:`hapsim.lockstep.wire_terms_nd`'s).
_KINDS = ("reading", "force", "position", "velocity")


def wire_terms_records(scene, records, chk, order: int, errors, *, usable,
                       floor: float | None = None, added=None) -> dict:
    """The wire's term of the felt matrices fitted on records cut at their disturbances,
    each record on its own stretches about a common equilibrium (module notes): as
    :func:`hapsim.lockstep.wire_terms_nd` (the first-order worst case, Hoelder's
    inequality on the fit's sensitivity times each error's response through the loop,
    as a whole and along each principal direction, taken at the records and at each
    statement's worst errors within the bounds, the largest:
    :func:`hapsim.analysis.wire_box.box_worst_case`), the fit the affine one
    (:func:`hapsim.analysis.pencil.felt_sensitivity_nd` with ``offset=True``) and each
    record's errors in its own fit only. Sources: the least-squares estimate's
    first-order perturbation (G. A. F. Seber and C. J. Wild, *Nonlinear Regression*,
    1989, Sec. 2.1) and Hoelder's inequality for the worst case over bounded errors of
    any sign (:func:`hapsim.analysis.pencil.worst_case_nd`).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    records : sequence of ndarray, each shape (N, n)
        The records as fitted: handle positions [m] (absolute: the equilibrium is
        fitted).
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.
    order : int
        The fit's order.
    errors : sequence of (str, array_like, bounds)
        As :func:`hapsim.lockstep.wire_terms_nd`'s, the bounds a list with one array per
        record in the order of ``records`` (shape (N, m) or (m,)), or one array for
        every record.
    usable : sequence of array_like of bool, shape (N,)
        Per record, the rows of its undisturbed stretches, as fitted.
    floor : float, optional
        :func:`hapsim.lockstep.wire_terms_nd`'s (the pairs the records do not determine
        never taken for rendered ones).
    added : ndarray, optional
        :func:`hapsim.lockstep.wire_terms_nd`'s (another worst case added, absolute).

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping`` [-], ``directions``, ``first_order`` and
        ``box`` (True when the term was taken over the box), as
        :func:`hapsim.lockstep.wire_terms_nd`'s with ``box=True`` (every term inf when
        the records give no felt matrices).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.pencil.fit_felt_nd`; an error ``kind`` not one of
        ``"reading"``, ``"force"``, ``"position"``, ``"velocity"``.
    """
    from hapsim.analysis.felt_matrices import FELT_QUANTITIES
    from hapsim.analysis.pencil import felt_sensitivity_nd
    from hapsim.analysis.wire_box import box_worst_case, statement_terms
    from hapsim.lockstep import error_responses, relative_terms, state_responses
    for kind, _, _ in errors:
        if kind not in _KINDS:
            raise ConfigError(f"an error's kind must be one of {', '.join(_KINDS)}, got "
                              f"{kind!r}", key="errors")
    n = scene.dimension
    r = chk.render
    inf = {"felt_stiffness": math.inf, "felt_damping": math.inf,
           "directions": {q: [math.inf] * n for q in FELT_QUANTITIES},
           "first_order": None}
    if r.felt_stiffness is None or r.directions is None:
        return inf
    recs = [np.asarray(x, float) for x in records]
    N = int(recs[0].shape[0])
    E = np.asarray(r.directions, float)
    resp = dict(zip(_KINDS[:2], error_responses(scene, N)))
    if any(kind in _KINDS[2:] for kind, _, _ in errors):
        resp.update(zip(_KINDS[2:], state_responses(scene, N)))
    plan = [(resp[kind] @ np.asarray(G, float),
             list(bounds) if isinstance(bounds, (list, tuple)) else [bounds] * len(recs))
            for kind, G, bounds in errors]

    def terms_at(x):
        sens = felt_sensitivity_nd(x, scene.device.mass, scene.period, order,
                                   usable=usable, offset=True, floor=floor)
        if sens is None:
            return None
        return statement_terms(sens, E, plan)
    got = box_worst_case(terms_at, recs)
    if got is None:
        return {**inf, "box": True}
    # taken over the box, as hapsim.lockstep.wire_terms_nd(box=True) says it: the
    # verdict's reasons name it (hapsim.analysis.felt_matrices.felt_verdict)
    plus = 0.0 if added is None else np.asarray(added, float)
    return {**relative_terms(chk, got[1] + plus, got[0]), "box": True}


def within_excursion(scene, diffs, usable, amplitude: float) -> list:
    """``usable`` with the rows after a record's first cut left out where the handle is
    farther from rest than any undisturbed record goes (the largest excursion of the
    loop predicted in lockstep from the hand's starts, :class:`hapsim.lockstep.LockstepND`).

    A stretch after a host stall starts where the torque held over the stall left the
    handle, not from one of the hand's starts: its rows beyond the undisturbed excursion
    are at an amplitude the linearisation bound (stated at ``a``, as for a record without
    a cut) does not cover. Measured on the emulated board (configs/pantograph_wall.yaml,
    the 2DIY's board on its own clock): a 30 ms stall carried a record to 1.0 mm from rest,
    2.9 times the undisturbed excursion and out of the wall (its depth 0.5 mm), and the
    felt stiffness fitted there was 14 % off the prediction. The rows before the first
    cut are the hand's start's, as in a record without one (kept whatever their
    excursion).

    The same along each engaged contact's opening
    (:func:`hapsim.analysis.linearisation.engaged_contacts`: a plane on the handle along
    its normal, a contact with a ground mass by its distance): a row after the first cut
    whose motion toward a contact's opening goes beyond the undisturbed records' is left
    out too. The norm alone let such rows stay: on configs/pantograph_wall.yaml at the
    designed start (0.42 mm) the undisturbed excursion is 0.92 mm, along the wall's
    tangent, while the wall is 0.5 mm deep; with 1 byte in 200 lost, 4 of 16 seeded
    measurements (simulated time) said "not measurable", the wall opened (1.04-1.20 of its
    depth), on rows after a cut that the undisturbed records never reach.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D or 3-D scene with a port and a device (its undisturbed records are taken in
        lockstep).
    diffs : list of ndarray, each shape (N, n)
        The records minus the record from rest [m] (or minus the operating point).
    usable : list of ndarray of bool, each shape (N,)
        Each record's undisturbed rows (False at its cuts).
    amplitude : float
        The hand's ``a`` [m].

    Returns
    -------
    list of ndarray of bool, each shape (N,)
        ``usable`` less the rows left out.

    Raises
    ------
    hapsim.errors.ConfigError
        As :class:`hapsim.lockstep.LockstepND` (a scene it cannot close).
    """
    from hapsim.analysis.linearisation import engaged_contacts
    from hapsim.lockstep import exact_differences
    N = diffs[0].shape[0]
    toward = [motion for _, _, motion in engaged_contacts(scene) if motion is not None]
    clean = exact_differences(scene, amplitude, N)
    nominal = max(float(np.max(np.linalg.norm(d_, axis=1))) for d_ in clean)
    # the undisturbed motion toward each opening
    opening = [max(float(np.max(m(d_))) for d_ in clean) for m in toward]
    out = []
    for d_, u in zip(diffs, usable):
        u = np.asarray(u, bool).copy()
        cut = np.flatnonzero(~u)
        if cut.size:
            beyond = np.linalg.norm(d_, axis=1) > nominal
            for o, m in zip(opening, toward):
                beyond |= m(d_) > o
            u &= ~((np.arange(N) > cut[0]) & beyond)
        out.append(u)
    return out


def window_rows(usable, order: int) -> np.ndarray:
    """Rows ``k >= order`` whose rows ``k - order .. k`` are all usable (the equations
    :func:`hapsim.analysis.pencil.fit_felt_nd` forms), as a mask.

    Parameters
    ----------
    usable : array_like of bool, shape (N,)
        The rows of a record's undisturbed stretches.
    order : int
        The fit's prediction order ``p``.

    Returns
    -------
    ndarray of bool, shape (N,)
        True where row ``k`` closes an equation of the fit.
    """
    u = np.asarray(usable, bool)
    bad = np.concatenate(([0], np.cumsum(~u)))
    k = np.arange(u.size)
    return (k >= order) & (bad[k + 1] - bad[np.maximum(k - order, 0)] == 0)

"""Whether a "differs" stands on a board that mistimes holds no host sees: the predicted
loop, broken where the board's holds may have struck, against the record (issue 29;
docs/drivers.md, "Hapkit-serial: the sketch's tick").

A board on its own tick (the Hapkit sketch's 1 ms) that takes a command one or more ticks
late reads the handle late and holds the force before longer; when it stays late for a
run of commands (its process behind beside two CPU-bound ones) its whole grid is shifted
by whole ticks from the host's until it catches up. Each such event is an input of a few
rows (the force held longer or shorter, the reading's shift) into the same loop, after
which the record is again a free response of that loop from a new initial state: a change
of the modes' linear coefficients, the poles unchanged. The fit of free poles
(:func:`hapsim.analysis.measurement.identify`) absorbs part of such a change into its
poles, and its stated uncertainty on an emulated record is tiny (2.6e-8 relative), so an
event the hold search (:func:`hapsim.analysis.unseen_holds.find_unseen_holds`) does not
find can make a matching paddle "differ": a run of late commands is one (the search's
signature is a single late command's), and so is a hold next to a cut.

:func:`break_prediction` asks the question the verdict rests on, as a comparison of
models: does the **predicted** loop (its poles fixed, all of them, the fast ones too,
each piece of the record its own linear coefficients: the initial state) with a bounded
number of breaks explain the record to its noise floor? The breaks are placed greedily (binary segmentation of a
change in a linear model's coefficients, Vostrikova, Soviet Math. Dokl. 24, 1981; Bai &
Perron, Econometrica 66(1), 1998), each one kept only where it lowers the residual's sum
of squares by more than a chi-square's Bonferroni bound over the candidates (Kay,
*Fundamentals of Statistical Signal Processing, Vol. II*, 1998, Sec. 7.7: the
generalised likelihood ratio of a linear model's coefficients); what is left must pass the
chi-square test of the residual against the noise the record has under a matching loop
(the sensor's and the wire's, stated, not the residual's own scale, which a device that
differs inflates), with room for the breaks the cap leaves untaken, each below the
threshold. Under a matching device the breaks take the board's events and the residual
is the noise; a device that truly differs (30 % more mass, a hidden viscous or Coulomb
friction) leaves a misfit that grows along every piece (the phase or the decay drifts),
which breaks up to the cap do not take to the noise (tests/test_unseen_verdict.py). Under
the predicted poles the residual of an event is its full change of coefficients (none of
it taken into the poles), so the search has its greatest power there. A record whose
stated floor is below its real noise (a sensor noisier than the scene says) is not
explained, and its "differs" stands as the fit states it.

The number of breaks is bounded (:data:`BREAK_FRACTION` of the rows), so a record the
prediction explains only cut into pieces of a few rows does not pass for one.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["FALSE_ALARM", "BREAK_FRACTION", "KEEP_FRACTION", "pole_spec",
           "break_prediction", "prediction_rss", "measured_loop_poles", "break_cost_gain"]

#: False-alarm probability of each test (the breaks' family over the candidates, and the
#: final chi-square): the hold search's (:data:`hapsim.analysis.unseen_holds.
#: FALSE_ALARM`).
FALSE_ALARM = 1e-3
#: Most breaks, as a fraction of the rows fitted: the hold search's own cap (a tenth of the
#: rows tested, :func:`hapsim.analysis.unseen_holds.find_unseen_holds`' ``max_holds``).
BREAK_FRACTION = 0.1
#: Least share of the rows fitted that the breaks leave: a device that differs misfits
#: every piece, and breaks that drop whole pieces would otherwise take the record away
#: (a tenth of the rows in breaks can drop all of it). A quarter: with a half, a matching
#: paddle whose events were packed at the record's end was refused; with a quarter left,
#: 30 % more mass, a hidden viscous or Coulomb friction leave a residual 4e6 to 9e9 times
#: the test's limit (tests/test_unseen_verdict.py's paddles, seeds 0-39).
KEEP_FRACTION = 0.25


def pole_spec(poles) -> list:
    """The predicted loop's modes, every non-zero pole seen at the port: ``["pair", a, w]``
    for ``z = exp(-a +- i w)`` (one per conjugate pair) and ``["real", p]``, as
    :func:`hapsim.analysis.identify.measure_felt`'s ``fit`` writes them.

    All of them, the fast ones too (which the fit of free poles drops with the rows they
    live in): a piece after a break then needs only the delay line's rows dropped.

    Parameters
    ----------
    poles : array_like of complex
        The predicted closed-loop poles (conjugates included).

    Returns
    -------
    list
        The modes.
    """
    out = []
    for z in np.asarray(poles, complex).ravel():
        if abs(z.imag) > 1e-12 * max(abs(z), 1e-300):
            if z.imag > 0:
                out.append(["pair", -math.log(abs(z)), math.atan2(z.imag, z.real)])
        elif abs(z) > 0:
            out.append(["real", float(z.real)])
    return out


def _basis(spec, n: int, offset: bool) -> np.ndarray:
    """The modes' columns over ``n`` rows from the piece's own start, shape (n, q)."""
    t = np.arange(n, dtype=float)
    cols = []
    for kind, *par in spec:
        if kind == "pair":
            e = np.exp(-par[0] * t)
            cols += [e * np.cos(par[1] * t), e * np.sin(par[1] * t)]
        else:
            cols.append(np.power(par[0], t))
    if offset:
        cols.append(np.ones(n))
    return np.column_stack(cols) if cols else np.zeros((n, 0))


def _rss(y, phi) -> float:
    """The least-squares residual's sum of squares of ``y`` on the columns ``phi``."""
    if y.size <= phi.shape[1]:
        return 0.0
    c = np.linalg.lstsq(phi, y, rcond=None)[0]
    r = y - phi @ c
    return float(r @ r)


def _prefix_rss(r, phi, least: int) -> np.ndarray:
    """``out[a]``: the least-squares residual's sum of squares of ``r[:a]`` on
    ``phi[:a]``, for every ``a`` from ``least`` on (NaN below), shape (L + 1,).

    Formed from the running normal equations of ``r``, a residual of the whole piece on
    ``phi`` (its fit taken out leaves every prefix's residual unchanged, and the normal
    equations then cancel only to the residual's own scale); the columns scaled to unit
    norm first."""
    L, q = phi.shape
    out = np.full(L + 1, np.nan)
    if L < least or q == 0:
        return out
    sc = np.linalg.norm(phi, axis=0)
    ph = phi / np.where(sc > 0, sc, 1.0)
    G = np.cumsum(ph[:, :, None] * ph[:, None, :], axis=0)     # (L, q, q)
    bv = np.cumsum(ph * r[:, None], axis=0)                      # (L, q)
    rr = np.cumsum(r * r)
    k = np.arange(least - 1, L)
    x = np.einsum("lij,lj->li", np.linalg.pinv(G[k]), bv[k])
    out[k + 1] = np.maximum(rr[k] - np.einsum("li,li->l", bv[k], x), 0.0)
    return out


#: Candidate breaks of a piece fitted on their own columns (:class:`_Piece`).
_EXACT = 8


class _Piece:
    """A piece of a stretch (rows ``idx``, indices into the record) and its best break."""

    def __init__(self, y, idx, spec, offset, drop, least):
        self.y, self.idx = y, idx
        self.phi = _basis(spec, idx.size, offset)
        self.kept = idx.size >= least
        self.rss = _rss(y, self.phi) if self.kept else float(y @ y)
        self.best = None            # (gain [m^2], i, rows dropped, rss left, right, a, b)
        L = idx.size
        if not self.kept:
            return
        r = _residual(self)
        P = _prefix_rss(r, self.phi, least)
        S = _prefix_rss(r[::-1].copy(), self.phi[::-1].copy(), least)
        i = np.arange(1, L)
        a = np.maximum(i - 2, 0)
        b = np.minimum(i + drop, L)
        rl, rr = P[a], S[L - b]
        okl, okr = np.isfinite(rl), np.isfinite(rr)
        # a side too short is dropped whole (both: the piece goes)
        dropped = (b - a) + np.where(okl, 0, a) + np.where(okr, 0, L - b)
        gain = self.rss - np.where(okl, rl, 0.0) - np.where(okr, rr, 0.0)
        if not gain.size:
            return
        # the right side's fast modes start again at its own first row, which the
        # suffixes of this piece's columns cannot: the best few ranked so, then fitted
        # each on its own columns
        for m in np.argsort(gain)[::-1][:_EXACT]:
            right = None
            if okr[m]:
                right = _rss(y[b[m]:], _basis(spec, L - int(b[m]), offset))
            g = self.rss - (rl[m] if okl[m] else 0.0) - (right or 0.0)
            if self.best is None or g > self.best[0]:
                self.best = (float(g), int(i[m]), int(dropped[m]),
                             float(rl[m]) if okl[m] else None, right, int(a[m]), int(b[m]))


def break_prediction(position, fit: dict, poles, *, floor: float, drop: int,
                     false_alarm: float = FALSE_ALARM,
                     max_breaks: int | None = None) -> dict:
    """The predicted loop fitted to the record with breaks where the board's unseen holds
    may have struck (module notes).

    The record's stretches (``fit["rows"]``) are fitted with the predicted modes
    (:func:`pole_spec`, each piece its own linear coefficients: its initial state). A
    break at row ``j`` of a piece cuts rows ``j - 2`` and ``j - 1`` (as
    :func:`hapsim.analysis.unseen_holds.hold_rows`) and drops ``drop`` rows from ``j``
    (the inputs in flight, as the measurement drops after a cut); a side shorter than
    ``q + 2`` rows (``q`` the coefficients) is dropped whole. The break of greatest gain
    ``G = RSS - RSS_left - RSS_right`` over every piece is taken while ``G / sigma^2 - m``
    (``m`` the rows it drops, each ``sigma^2`` of the noise's expected share) exceeds
    ``thr = chi2.isf(alpha / N, q)`` (``N`` the rows, each a candidate: Bonferroni; Kay
    1998, Sec. 7.7), while at least :data:`KEEP_FRACTION` of the rows fitted stay, and
    at most ``max_breaks`` times; ``sigma`` is the sensor's and the wire's deviation
    ``floor`` (the noise the record has under a matching loop: not the residual's own
    scale, which a device that differs inflates). Then the residual left,
    ``chi2 = RSS / sigma^2`` over ``dof`` (the rows kept less the pieces'
    coefficients), is tested against ``chi2.isf(alpha, dof)`` plus what the breaks not
    taken may still hold: up to the cap, each below the threshold, at most
    ``thr + drop + q + 4`` (its gain and the rows its break would drop).

    Parameters
    ----------
    position : array_like, shape (n,)
        The record [m] (the late ticks' response taken out, as fitted).
    fit : dict
        :func:`hapsim.analysis.measurement.identify`'s ``fit`` (``offset``, ``rows``: an
        int array per stretch).
    poles : array_like of complex
        The predicted closed-loop poles seen at the port.
    floor : float
        The sensor's and the wire's standard deviation [m].
    drop : int
        Rows dropped from a break on (the delay line's ``d + 2``: the inputs still in
        flight).
    false_alarm : float
        :data:`FALSE_ALARM`.
    max_breaks : int, optional
        Most breaks (default :data:`BREAK_FRACTION` of the rows fitted).

    Returns
    -------
    dict
        ``breaks`` (int array: the rows ``j``, in the order found), ``explained`` (bool:
        the residual left passes), ``chi2`` (its statistic), ``limit`` (its bound),
        ``dof`` (the rows kept less the pieces' coefficients), ``rows`` (kept),
        ``pieces`` (the first and last row of each piece kept),
        ``threshold`` (``thr``) and ``cap`` (the most breaks).
    """
    # chi2.isf(p, df) is chdtri(df, p) in scipy.stats itself (chi2_gen._isf): taken from
    # scipy.special, without importing scipy.stats (0.55 CPU-s, docs/testing.md)
    from scipy.special import chdtri

    x = np.asarray(position, float)
    spec = pole_spec(poles)
    offset = bool(fit.get("offset"))
    q = sum(2 if s[0] == "pair" else 1 for s in spec) + int(offset)
    least = q + 2
    pieces = [_Piece(x[r], np.asarray(r, np.int64), spec, offset, int(drop), least)
              for r in fit["rows"] if np.asarray(r).size]
    n_rows = sum(p.idx.size for p in pieces)
    cap = max(int(BREAK_FRACTION * n_rows), 1) if max_breaks is None else int(max_breaks)
    breaks = []
    thr = float(chdtri(q, false_alarm / max(n_rows, 1)))
    sigma = float(floor)
    kept_rows = sum(p.idx.size for p in pieces if p.kept)
    while len(breaks) < cap and sigma > 0:
        cand = [(p.best[0] / sigma ** 2 - p.best[2], k) for k, p in enumerate(pieces)
                if p.kept and p.best is not None]
        if not cand:
            break
        score, k = max(cand)
        if not score > thr or kept_rows - pieces[k].best[2] < KEEP_FRACTION * n_rows:
            break
        kept_rows -= pieces[k].best[2]
        p = pieces.pop(k)
        _, i, _, rl, rr, a, b = p.best
        breaks.append(int(p.idx[i]))
        for lo, hi, r in ((0, a, rl), (b, p.idx.size, rr)):
            if r is not None:
                pieces.append(_Piece(p.y[lo:hi], p.idx[lo:hi], spec, offset, int(drop),
                                     least))
    kept = [p for p in pieces if p.kept]
    rows = sum(p.idx.size for p in kept)
    rss = float(sum(p.rss for p in kept))
    dof = int(rows - q * len(kept))
    # the breaks not taken, up to the cap: each below the threshold, its share of the
    # residual at most thr + the rows its break would drop (a side dropped whole too)
    allow = (cap - len(breaks)) * (thr + int(drop) + 2 + least)
    stat = rss / sigma ** 2 if sigma > 0 else math.inf
    limit = float(chdtri(max(dof, 1), false_alarm)) + allow
    return {"breaks": np.asarray(breaks, np.int64),
            "explained": bool(dof > 0 and stat <= limit),
            "chi2": float(stat), "limit": limit, "dof": dof, "rows": int(rows),
            "pieces": sorted((int(p.idx[0]), int(p.idx[-1])) for p in kept),
            "threshold": thr, "cap": int(cap)}


def _residual(p: _Piece) -> np.ndarray:
    """A kept piece's residual under the predicted modes [m]."""
    if p.y.size <= p.phi.shape[1]:
        return np.zeros(0)
    c = np.linalg.lstsq(p.phi, p.y, rcond=None)[0]
    return p.y - p.phi @ c


def prediction_rss(position, fit: dict, poles) -> float:
    """The residual's sum of squares of the record on the predicted modes with no break
    [m^2]: each stretch of ``fit["rows"]`` its own coefficients (:func:`break_prediction`
    with none taken, without its search).

    Parameters
    ----------
    position, fit, poles
        As :func:`break_prediction`.

    Returns
    -------
    float
    """
    x = np.asarray(position, float)
    spec = pole_spec(poles)
    offset = bool(fit.get("offset"))
    return float(sum(_rss(x[r], _basis(spec, np.asarray(r).size, offset))
                      for r in fit["rows"] if np.asarray(r).size))


def measured_loop_poles(poles, spec):
    """The predicted loop's poles with its felt pair (the conjugate pair nearest the
    fit's) replaced by the pair the fit measured: the alternative of
    :func:`break_cost_gain`, the predicted loop with two parameters more.

    Parameters
    ----------
    poles : array_like of complex
        The predicted closed-loop poles (conjugates included).
    spec : list
        The fit's modes (:func:`pole_spec`'s form: ``["pair", a, w]``, ``["real", p]``).

    Returns
    -------
    ndarray of complex or None
        The poles, the same count; None without a pair on either side.
    """
    P = np.asarray(poles, complex).ravel()
    pairs = [par for kind, *par in spec if kind == "pair"]
    upper = np.flatnonzero(P.imag > 1e-12 * np.maximum(np.abs(P), 1e-300))
    if not pairs or not upper.size:
        return None
    a, w = pairs[0]
    z = math.exp(-a) * complex(math.cos(w), math.sin(w))
    i = int(upper[np.argmin(np.abs(P[upper] - z))])
    j = int(np.argmin(np.abs(P - np.conj(P[i]))))
    out = P.copy()
    out[i], out[j] = z, np.conj(z)
    return out


def break_cost_gain(position, fit: dict, poles, alternative, *, floor: float,
                    drop: int, alternative_position=None, predicted=None) -> dict:
    """How much better the alternative loop (the measured pair,
    :func:`measured_loop_poles`) explains the record than the predicted one, each with
    the breaks the board's unseen holds may have made: the difference of their penalised
    costs, against what two free parameters gain under a matching device.

    Breaks explain anything when enough are taken: a paddle with 0.3 N s/m of friction
    the scene does not state (its b 0.53 N s/m against 0.23 predicted) was "explained"
    by the predicted loop with 33 breaks (chi-square 401 against 542,
    tests/test_unseen_holds.py), where its own loop needs those of its events only. Each
    model's cost is ``C = RSS / sigma^2 + B thr + m``: its residual, ``thr``
    (:func:`break_prediction`'s threshold) per break taken, one per row its breaks
    dropped (the greedy search's own criterion, a break taken where it lowers ``C``);
    the models are nested (the alternative frees the felt pair's decay and frequency), so
    under a matching device the alternative gains at most ``chi2.isf(alpha, 2)`` save
    with probability ``alpha`` (Wilks, *Ann. Math. Statist.* 9, 1938; the alternative at
    the fit's pair, not at its own least cost, gains less still). A gain beyond that is
    evidence the device differs, whatever the breaks.

    Parameters
    ----------
    position, fit, poles, floor, drop
        As :func:`break_prediction`.
    alternative : array_like of complex
        The alternative loop's poles.
    alternative_position : array_like, shape (n,), optional
        The record as the alternative loop measures it (its known inputs taken out through
        that loop); default ``position``. Both are fitted on ``fit``'s rows.
    predicted : dict, optional
        :func:`break_prediction`'s result for ``position``, ``fit`` and ``poles`` when the
        caller has it already (computed here otherwise).

    Returns
    -------
    dict
        ``gain`` (``C_predicted - C_alternative``), ``limit`` (``chi2.isf(alpha, 2)``),
        ``stands`` (bool: the gain beyond it), ``predicted`` and ``alternative``
        (:func:`break_prediction`'s results).
    """
    from scipy.special import chdtri           # chi2.isf's own formula (above)
    a = (break_prediction(position, fit, poles, floor=floor, drop=drop)
         if predicted is None else predicted)
    b = break_prediction(position if alternative_position is None else alternative_position,
                         fit, alternative, floor=floor, drop=drop)

    def cost(g):
        return g["chi2"] + g["threshold"] * g["breaks"].size - g["rows"]
    gain = float(cost(a) - cost(b))
    limit = float(chdtri(2, FALSE_ALARM))
    return {"gain": gain, "limit": limit, "stands": bool(gain > limit), "predicted": a,
            "alternative": b}

"""Holds a board on its own tick mistimed that no host saw, found in the record itself
(docs/drivers.md, "Hapkit-serial: the sketch's tick").

A board that takes commands on its own tick (the Hapkit sketch's 1 ms) reads the handle
and applies a command's force at its first tick after the command has come. When the
board itself is late to read a command (a real Hapkit's USB-serial bridge delivers bytes
in 1 ms frames; the emulated sketch's process is scheduled late under load) it takes it
``tau`` after the tick the host timed it for (whole ticks where it samples on its tick;
any time where it samples at the command's end, as the sketch does for most phases,
:func:`mistimings`): the reply's
position is then read ``tau`` late and the force before held ``tau`` longer. Its reply
names neither, and the host, which marks only the writes it made late or near the
probed boundary (:meth:`hapsim.drivers.transport.DriverTransport._note_hold`), cannot
see it. Beside two CPU-bound processes the emulated sketch took 1 to 8 such holds a run;
left in, they made a matching paddle "differ" (k 0.05 %, b 0.13 % off).

Such a hold at row ``j`` is a disturbance whose shape and size follow from the record
and ``tau`` alone (:func:`hold_signature`): the position logged at row ``j`` is off by
``x(t_j + tau) - x(t_j)`` (the handle's path interpolated from the rows around ``j``), an
error observed and fed back through the virtual links
(:func:`hapsim.analysis.error_response.sensor_error_response`), and the force of row
``j - 2`` held ``tau`` longer than the period instead of row ``j - 1``'s, a force error
``(F[j-2] - F[j-1]) tau / T`` over row ``j``'s period (the hold's impulse over the
period; :func:`hapsim.analysis.error_response.force_error_response`). On the emulated
sketch it reproduces a hold's disturbance of the record to a few per cent of its norm
(tests/test_unseen_holds.py).

:func:`find_unseen_holds` tests every row and every mistiming tried: the signature
taken off the fit's residual must lower its sum of squares by more than the threshold
(a likelihood-ratio test of "a hold of ``tau`` at row ``j``" against "noise", Kay,
*Fundamentals of Statistical Signal Processing, Vol. II: Detection Theory*, 1998,
Sec. 4.3, for a known signal; the size is not fitted, so the fit's own misfit near a hold
never passes for one), against the residual's own scale (its median absolute deviation,
which a few holds do not move: Hampel, "The influence curve and its role in robust
estimation", JASA 69, 1974) or the sensor's, whichever is larger, at a family-wise
false-alarm rate of :data:`FALSE_ALARM` over the tests (Bonferroni). The best is taken
off and the search goes on (matching pursuit, Mallat & Zhang, IEEE Trans. Signal
Process. 41(12), 1993). The run's measurement (:func:`hapsim.pipeline.measure.
identify_run`) cuts the rows found as it cuts the holds the host marked, and fits and
searches again until no row passes.

Why a cut and not a term in the stated uncertainty (as the 2DIY's link jitter,
:func:`hapsim.pipeline.haply2_host.link_uncertainty`): which rows the board mistimed is
not known to the host, so a term for them would have to bound a hold at every row, a
worst case over the whole record that widens the interval far past any use (each row's
share summed), while a found hold costs only its ``d + 4`` rows. A hold too small to be
found changes the record by less than the residual's own noise, which the fit's stated
uncertainty already covers (its residual variance counts it). A cut of a row that held no
hold (a false alarm) loses rows, never biases: each stretch left is still a free response
of the same loop from its own initial state. A device that truly differs (more inertia, a
hidden friction) leaves a residual at the noise once its own poles are fitted (the poles
are free in the fit), so nothing is cut there and it still "differs". A record with no hold
has no row that passes and is measured as before, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["FALSE_ALARM", "MAX_PASSES", "RELATIVE", "HOLD_STEPS", "fit_residual",
           "hold_signature", "mistimings", "find_unseen_holds", "hold_rows"]

#: Family-wise probability that a record with no unseen hold has a row found (the
#: Bonferroni threshold over the rows tested, Gaussian tails).
FALSE_ALARM = 1e-3
#: Most fits and searches :func:`hapsim.pipeline.measure.identify_run` makes after the
#: first: each pass finds what the holds cut before hid in the fit.
MAX_PASSES = 16
#: A search stops at the first row whose significance is below this fraction of the
#: first's: the largest holds bend the fit, and the residual they leave near themselves
#: can pass the threshold too; such a row is found again after the cut and re-fit if it
#: is one (the search and fit are repeated until no row is significant), so the fraction
#: trades only passes, never what is found at the end (a tenth of the passes' fits on a
#: run with 9 holds; rows near a pair of consecutive holds passed the threshold 25 times
#: in one search without it).
RELATIVE = 1.0 / 3.0
#: Mistimings of a hold tried per board tick (:func:`mistimings`): quarter ticks.
HOLD_STEPS = 4
#: MAD to standard deviation for Gaussian errors (1 / Phi^-1(3/4)).
_MAD_SD = 1.482602218505602


def fit_residual(position, fit: dict) -> list:
    """The residual of a variable-projection fit, stretch by stretch [m].

    Each stretch is fitted anew, its own linear coefficients (the modes' amplitudes and
    the offset) by least squares for the fitted poles, as
    :func:`hapsim.analysis.identify.measure_felt` does (Golub & Pereyra, SIAM J. Numer.
    Anal. 10(2), 1973): ``y - Phi (Phi^+ y)``.

    Parameters
    ----------
    position : array_like, shape (n,)
        The record the fit was made on [m].
    fit : dict
        :func:`hapsim.analysis.measurement.identify`'s ``fit``: ``spec`` (the modes,
        ``["pair", a, w]`` for ``z = exp(-a +- i w)`` or ``["real", p]``), ``offset``
        (bool) and ``rows`` (an int array per stretch, indices into ``position``).

    Returns
    -------
    list of ndarray
        One residual per stretch, the shape of its ``rows``.
    """
    return [r for r, _ in _stretch_fits(position, fit)]


def _stretch_fits(position, fit: dict) -> list:
    """Per stretch, ``(r, Q)``: the residual (:func:`fit_residual`) and an orthonormal
    basis of what the fit adjusts there, the linear columns ``Phi`` and the derivatives
    of ``Phi c`` in the poles (the fit's Jacobian; Golub & Pereyra 1973), shape (L, q):
    a disturbance ``g`` of the record leaves ``g - Q Q' g`` in the residual, to first
    order (the poles taken per stretch: more than the fit, which shares them, adjusts)."""
    x = np.asarray(position, float)
    out = []
    for rows in fit["rows"]:
        y = x[rows]
        t = np.arange(y.size, dtype=float)
        cols, ders = [], []
        for kind, *par in fit["spec"]:
            if kind == "pair":
                e = np.exp(-par[0] * t)
                c, s = e * np.cos(par[1] * t), e * np.sin(par[1] * t)
                cols += [c, s]
                ders.append((len(cols) - 2, -t * c, -t * s))      # d/da of (c, s)
                ders.append((len(cols) - 2, -t * s, t * c))       # d/dw of (c, s)
            else:
                cols.append(np.power(par[0], t))
                dp = np.zeros(y.size)
                if par[0] != 0:
                    dp[1:] = t[1:] * np.power(par[0], t[1:] - 1)
                ders.append((len(cols) - 1, dp, None))
        if fit.get("offset"):
            cols.append(np.ones(y.size))
        phi = np.column_stack(cols) if cols else np.zeros((y.size, 0))
        coef = np.linalg.lstsq(phi, y, rcond=None)[0] if cols else np.zeros(0)
        jac = [d0 * coef[k] + (0.0 if d1 is None else d1 * coef[k + 1])
               for k, d0, d1 in ders]
        B = np.column_stack(cols + jac) if cols else np.zeros((y.size, 0))
        if B.shape[1]:
            U, sv, _ = np.linalg.svd(B, full_matrices=False)
            Q = U[:, sv > np.finfo(float).eps * max(B.shape) * sv[0]]
        else:
            Q = B
        out.append((y - phi @ coef, Q))
    return out


def hold_signature(position, force, row: int, length: int, period: float,
                   sensor_response, force_response, tau: float) -> np.ndarray:
    """A mistimed hold's disturbance of the record [m].

    The board took the command answered at row ``j`` (``row``) ``tau`` late: the position
    logged at ``j`` is off by ``e = x(t_j + tau) - x(t_j)`` and the force of row ``j - 2``
    was held ``tau`` longer instead of row ``j - 1``'s (module notes). Through the loop
    the record from row ``j`` on is off by::

        g[m] = e s[m] + (F[j-2] - F[j-1]) tau / T h[m],    m = 0 .. length - 1

    ``s`` the sensor error's response (``s[0] = 1``), ``h`` the force error's
    (``h[0] = 0``); ``x(t)`` the cubic through rows ``j - 2``, ``j - 1``, ``j + 1``,
    ``j + 2`` (Lagrange; row ``j`` itself is the one off), ``e = v_j tau`` from the
    central difference where the record has no two rows on a side.

    Parameters
    ----------
    position, force : array_like, shape (n,)
        The logged positions [m] and forces [N] (row ``k``'s force is the one computed
        from its position, sent with the next command).
    row : int
        ``j``, the first row whose position is off.
    length : int
        Rows of signature wanted (from ``j`` on).
    period : float
        Sample period T [s].
    sensor_response, force_response : array_like
        :func:`hapsim.analysis.error_response.sensor_error_response` [m/m] and
        :func:`~hapsim.analysis.error_response.force_error_response` [m/N], at least
        ``length`` long.
    tau : float
        The mistiming [s] (positive: taken late).

    Returns
    -------
    ndarray, shape (length,)
        ``g`` [m].
    """
    x = np.asarray(position, float)
    f = np.asarray(force, float)
    j = int(row)
    e = float(_path_error(x, period, tau)[j])
    dF = float(f[j - 2] - f[j - 1]) if j >= 2 else 0.0
    s = np.asarray(sensor_response, float)[:length]
    h = np.asarray(force_response, float)[:length]
    return e * s + dF * tau / period * h


def _path_error(x, period, tau):
    """``x(t_j + tau) - x(t_j)`` for every row ``j`` [m] (:func:`hold_signature`)."""
    n = x.size
    out = np.zeros(n)
    if n < 2:
        return out
    v = np.empty(n)
    v[1:-1] = (x[2:] - x[:-2]) / (2.0 * period) if n > 2 else 0.0
    v[0], v[-1] = (x[1] - x[0]) / period, (x[-1] - x[-2]) / period
    out[:] = v * tau
    if n >= 5:
        s = tau / period
        nodes = (-2, -1, 1, 2)

        def lag(k, t):
            return math.prod((t - q) / (k - q) for q in nodes if q != k)
        w = [lag(k, s) - lag(k, 0.0) for k in nodes]
        out[2:-2] = sum(wk * x[2 + k:n - 2 + k] for wk, k in zip(w, nodes))
    return out


def _with_unread(Q, rows, unread, S, H, lead):
    """``Q`` widened by the responses of the unread rows' errors (a sensor error and a
    force error at each unread row within ``lead`` rows before the stretch or in it, its
    response through the loop over the stretch's rows), orthonormal: those errors are
    nuisances the search projects off, as the fit's own columns (module notes)."""
    rows = np.asarray(rows, np.int64)
    un = np.flatnonzero(np.asarray(unread, bool))
    un = un[(un >= rows[0] - int(lead)) & (un <= rows[-1])]
    if not un.size:
        return Q
    cols = []
    for u in un.tolist():
        m = rows - u
        ok = (m >= 0) & (m < min(S.size, H.size))
        for k in (S, H):
            c = np.zeros(rows.size)
            c[ok] = k[m[ok]]
            if np.any(c):
                cols.append(c)
    if not cols:
        return Q
    B = np.column_stack([Q] + cols) if Q.shape[1] else np.column_stack(cols)
    U, sv, _ = np.linalg.svd(B, full_matrices=False)
    return U[:, sv > np.finfo(float).eps * max(B.shape) * sv[0]]


def _correlate(R, kernels):
    """``c[j, ..., i] = sum_m R[..., i + m] k_j[m]`` over ``m < L - i`` (each kernel cut at
    the end), for the rows ``R[..., :]`` of length ``L`` and every kernel ``k_j`` of
    ``kernels``, in one batched FFT convolution; shape ``(len(kernels),) + R.shape``."""
    from hapsim.analysis.fftconv import fftconvolve
    R = np.asarray(R, float)
    L = R.shape[-1]
    K = np.zeros((len(kernels),) + (1,) * (R.ndim - 1) + (L,))
    for j, k in enumerate(kernels):
        K[j, ..., :min(L, k.size)] = k[:L]
    if R.size == 0:
        return np.zeros((len(kernels),) + R.shape)
    return fftconvolve(R[None, ..., ::-1], K, axes=-1)[..., :L][..., ::-1]


def mistimings(period: float, tick: float) -> list:
    """The mistimings a hold is searched at [s]: :data:`HOLD_STEPS` a tick, less than a
    period either way (a command taken a period late is answered after the next one has
    gone out: a late reply, which the host sees).

    The Hapkit sketch reads the handle at a command's end for most write phases, not on
    its tick (``Hapkit_arduino.ino:96-135``; :func:`hapsim.drivers.tick_align.
    fit_tick_jump`): a command it reads late by a USB frame is sampled that much late, no
    whole number of ticks. Whole ticks alone left a matching paddle "differs" at read
    latencies of 0.6-2.5 ticks (tests/test_unseen_verdict.py, seeds 8 and 18).

    Parameters
    ----------
    period : float
        The loop's period T [s].
    tick : float
        The board's tick [s], > 0.

    Returns
    -------
    list of float
        ``+-k tick / HOLD_STEPS`` for ``k = 1 .. HOLD_STEPS (round(T / tick) - 1)`` (at
        least one tick's worth).
    """
    per = max(int(round(period / tick)) - 1, 1)
    return [s * k * tick / HOLD_STEPS for k in range(1, per * HOLD_STEPS + 1)
            for s in (1, -1)]


def find_unseen_holds(position, force, fit: dict, period: float, sensor_response,
                      force_response, taus, *, floor: float = 0.0,
                      false_alarm: float = FALSE_ALARM, max_holds: int | None = None,
                      relative: float = RELATIVE, lead: int = 4, unread=None) -> dict:
    """The rows of a fitted record where a board's mistimed hold stands out of the
    residual (module notes).

    Per stretch, for every row ``j`` of it and the ``lead`` rows before it, and every
    mistiming ``tau`` of ``taus``, the signature ``g`` (:func:`hold_signature`, on the
    stretch's rows only) is a known signal, of which the fit leaves ``P g`` in its
    residual ``r`` (``P`` the projector off what the fit adjusts: the stretch's linear
    columns and its poles' derivatives; the fit took the rest; ``r`` projected so too):
    taken off ``r`` it lowers the sum of squares by ``D = 2 <r, g> - |P g|^2``. ``z = sqrt(D) / sigma`` is its significance
    (Kay 1998, Sec. 4.3: ``D > z^2 sigma^2`` implies ``<r, Pg> / |Pg| > z sigma``, the
    matched filter's statistic, ``N(0, 1)`` for white errors of deviation ``sigma``, so
    the false-alarm rate is at most the matched filter's). The best row over the record
    is taken while ``z`` passes the Bonferroni threshold ``Phi^-1(1 - false_alarm / 2N)``
    (``N`` rows times mistimings tested); its signature is taken off the residual and the
    scores computed again (matching pursuit), none within ``lead`` rows of one taken (its
    cut leaves them out), until the best is below the threshold or below ``relative``
    times the first's ``z``. ``sigma`` is the residual's median absolute deviation times
    1.4826 (its standard deviation for Gaussian errors, robust to the holds themselves) or
    ``floor``, whichever is larger.

    Parameters
    ----------
    position, force : array_like, shape (n,)
        The record the fit was made on [m] and the logged forces [N].
    fit : dict
        :func:`hapsim.analysis.measurement.identify`'s ``fit`` (:func:`fit_residual`).
    period : float
        Sample period T [s].
    sensor_response, force_response : array_like, shape (>= n,)
        As :func:`hold_signature`.
    taus : sequence of float
        The mistimings tested [s] (:func:`mistimings`: quarter ticks, as the sketch
        samples a command read late that much late for most phases).
    floor : float
        The sensor's standard deviation [m] (its quantum, noise and the wire's rounding):
        the least ``sigma``.
    false_alarm : float
        Family-wise false-alarm probability (:data:`FALSE_ALARM`).
    max_holds : int, optional
        Most rows found (default: a tenth of the rows tested).
    relative : float
        :data:`RELATIVE`.
    lead : int
        Rows before each stretch whose hold is sought too: a hold there reaches into the
        stretch by the inputs still in flight (the force computed from its position,
        the velocity term's next one, and the delay line: ``d + 3`` rows; the fit drops
        a stretch's first rows, where the fast modes are above the floor, so a hold
        there is no stretch's row).

    unread : array_like of bool, shape (n,), optional
        Rows whose error the stated uncertainty bounds already (a driver's missing reply
        stepped through with an estimated position, ``FLAG_ESTIMATED``; a force its
        account cannot name): their residual is left out (0), no hold is sought within
        ``lead`` rows of one (their error there would pass for a hold: 20 "holds" cut in
        one run that lost 1 byte in 200, its 51 estimated rows not apart), and the
        response of an error at each (a sensor error through ``sensor_response``, a
        force error through ``force_response``, from that row on) is projected off the
        residual with the fit's own columns: a nuisance of unknown size, which the
        stated uncertainty bounds, not noise (left in, its response through the loop,
        which outlasts ``lead`` by the oscillation's decay, passed the threshold against
        the residual's deviation: 16-23 "holds" cut in the wall-clock runs that lost 1
        byte in 200 and ended "not measurable", tests/test_unseen_holds.py).

    Returns
    -------
    dict
        ``rows`` (int array: the first disturbed row of each hold found, indices into
        ``position``, in the order found), ``tau_s`` (their mistiming [s]), ``z``
        (their significance), ``sigma`` [m], ``threshold`` and ``tested`` (rows).
    """
    # norm.isf(q) is -ndtri(q) in scipy.stats itself (_continuous_distns._norm_isf); taken
    # from scipy.special, without importing scipy.stats (0.55 CPU-s beyond scipy.optimize,
    # 2.1 s of wall time at load 6: parsing its distributions' docstrings)
    from scipy.special import ndtri

    x = np.asarray(position, float)
    f = np.asarray(force, float)
    S = np.asarray(sensor_response, float)
    H = np.asarray(force_response, float)
    taus = [float(t) for t in taus if t]
    E = np.array([_path_error(x, period, t) for t in taus]).reshape(len(taus), x.size)
    tw = np.asarray(taus, float)[:, None] / period        # the force error's share per tau
    dF = np.zeros(x.size)
    dF[2:] = f[:-2] - f[1:-1]
    cS, cH, cSH = (np.concatenate([[0.0], np.cumsum(q)]) for q in (S * S, H * H, S * H))
    stretches, scales = [], []
    for rows, (r, Q) in zip(fit["rows"], _stretch_fits(x, fit)):
        if rows.size == 0:
            continue
        # the residual off every column, the poles' derivatives too (the poles shared by
        # the stretches leave each a share along its own): else a signature the fit
        # would take almost whole matches that share at every stretch's first rows
        un = None
        plain = r - Q @ (Q.T @ r)          # (off the fit's own columns only: its scale)
        if unread is not None:
            un = np.asarray(unread, bool)[rows]
            r = np.where(un, 0.0, r)
            plain = plain[~un]
            Q = _with_unread(Q, rows, unread, S, H, lead)
        r = r - Q @ (Q.T @ r)
        scales.append(plain)
        # the candidates: the stretch's rows and the ``lead`` rows before it (a hold there
        # reaches into the stretch by its inputs still in flight), the residual 0 there
        p = min(int(lead), int(rows[0]))
        cand = np.concatenate([np.arange(rows[0] - p, rows[0]), rows])
        i = np.arange(cand.size)
        hi, lo = cand.size - i, np.maximum(p - i, 0)   # the signature's rows inside it
        norms = (cS[hi] - cS[lo], cSH[hi] - cSH[lo], cH[hi] - cH[lo])
        # what the fit takes of a signature: Q' g = e Q'S_i + w Q'H_i, per column of Q
        Qx = np.vstack([np.zeros((p, Q.shape[1])), Q])
        QS, QH = _correlate(Qx.T, (S, H))          # (columns of Q, candidates) each
        taken = np.zeros(cand.size, bool)
        if un is not None:
            for k in np.flatnonzero(un) + p:
                taken[max(k - int(lead), 0):k + int(lead) + 1] = True
        stretches.append([cand, np.concatenate([np.zeros(p), r]), norms, p, taken, Qx,
                          QS, QH])
    n_test = sum(st[0].size for st in stretches)
    out = {"rows": np.zeros(0, np.int64), "tau_s": np.zeros(0), "z": np.zeros(0),
           "sigma": 0.0, "threshold": math.inf, "tested": int(n_test)}
    if not n_test or not taus:
        return out
    allr = np.concatenate([st[1][st[3]:] for st in stretches])
    if unread is not None:
        allr = np.concatenate([st[1][st[3]:][~np.asarray(unread, bool)[st[0][st[3]:]]]
                               for st in stretches])
    # the residual's scale, off the nuisances and without their projection, the larger:
    # the projection takes their structure out of the statistics, never lowers the
    # threshold below what the residual itself has
    plain = np.concatenate(scales) if scales else np.zeros(0)
    sigma = max(_MAD_SD * float(np.median(np.abs(allr - np.median(allr)))),
                _MAD_SD * float(np.median(np.abs(plain - np.median(plain))))
                if plain.size else 0.0, float(floor))
    thr = float(-ndtri(false_alarm / (2.0 * n_test * len(taus))))
    out.update(sigma=sigma, threshold=thr)
    if not sigma > 0:
        return out
    cap = max(int(n_test // 10), 1) if max_holds is None else int(max_holds)
    found, tau_found, zs = [], [], []

    def stretch_best(si):
        """The stretch's best (D, stretch, row, tau, e, w): only the stretch a hold was
        taken from changes between two rounds of the pursuit."""
        cand, r, (nss, nsh, nhh), p, taken, _, QS, QH = stretches[si]
        rs, rh = _correlate(r, (S, H))
        # every tau at once, (taus, candidates): e the sensor error, w the force's
        e, w = E[:, cand], dF[cand][None, :] * tw
        # the residual lowered by the signature the fit leaves, P g: 2 <r, g> (r is
        # the fit's residual: <r, P g> = <r, g>) less |P g|^2
        D = (2 * (e * rs + w * rh) - (e * e * nss + 2 * e * w * nsh + w * w * nhh)
             + np.sum((e[:, None, :] * QS + w[:, None, :] * QH) ** 2, axis=1))
        D[:, taken] = -math.inf
        # the first best in (tau, row) order, as a loop over the taus would take it
        ti, i = np.unravel_index(int(np.argmax(D)), D.shape)
        return (float(D[ti, i]), si, int(i), taus[ti], float(e[ti, i]), float(w[ti, i]))

    bests = [stretch_best(si) for si in range(len(stretches))]
    while len(found) < cap:
        best = None
        for b in bests:                 # the first stretch's on a tie, as before
            if best is None or b[0] > best[0]:
                best = b
        D, si, i, t, e, w = best
        z = math.sqrt(D) / sigma if D > 0 else 0.0
        if not z > thr or (zs and z < relative * zs[0]):
            break
        cand, r, _, p, taken, Qx, _, _ = stretches[si]
        L = r.size - i
        g = np.zeros(r.size)
        g[i:] = e * S[:L] + w * H[:L]
        g[:p] = 0.0                               # the lead rows stay 0
        r -= g - Qx @ (Qx.T @ g)
        # one hold per ``lead`` rows a search: the rows near one match what is left of
        # its residual, and its cut leaves them out
        taken[max(i - int(lead), 0):i + int(lead) + 1] = True
        found.append(int(cand[i]))
        tau_found.append(t)
        zs.append(z)
        bests[si] = stretch_best(si)
    out.update(rows=np.asarray(found, np.int64), tau_s=np.asarray(tau_found),
               z=np.asarray(zs))
    return out


def hold_rows(n: int, rows) -> np.ndarray:
    """The rows a measurement leaves out for holds whose first disturbed row is ``j``:
    ``j - 2`` and ``j - 1``, as :meth:`hapsim.drivers.base.Driver.mistimed_rows` leaves
    out a host-marked hold (the record cut there; the stretch after it drops its first
    ``d + 2`` rows, ``j`` among them, the disturbance's inputs still in flight).

    Parameters
    ----------
    n : int
        Rows in the record.
    rows : array_like of int
        First disturbed rows (:func:`find_unseen_holds`'s ``rows``).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    out = np.zeros(int(n), bool)
    for j in np.asarray(rows, np.int64):
        for k in (j - 2, j - 1):
            if 0 <= k < n:
                out[k] = True
    return out

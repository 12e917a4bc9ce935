"""The device fit's search (:mod:`hapsim.analysis.device_fit`): the moving stretches, the
variable-projection model of one (hold, delay) candidate and its fit, the search over the
whole and sub-sample delays, and the nonlinear refinement with its block Jacobian.

The method is described in :mod:`hapsim.analysis.device_fit` ('Method'); the candidates'
intervals are :mod:`hapsim.analysis.device_fit_intervals`.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.device_fit_model import HOLDS, applied_force
from hapsim.analysis.lm import levenberg_marquardt

__all__ = ["correlation_guess", "fit_stretched", "search_candidates", "FRACTION_GRID", "FRACTION_TOL", "search_fraction",
           "fraction_candidate", "refine"]

#: ln m [kg] the fit searches within (1e-6 .. 1e6 kg: beyond, no device; the basis overflows).
_LM_RANGE = (math.log(1e-6), math.log(1e6))


def correlation_guess(x, f, T, max_delay, pieces=None):
    """Delay, hold and mass from the correlation of force steps with acceleration.

    The PRBS makes the force increments ``df[n]`` nearly white and much larger than the
    smooth centring part, so ``c_j = sum d2x[n+j] df[n] / sum df^2`` (``d2x[n] =
    x[n+1] - 2 x[n] + x[n-1]``) is the impulse response of ``df -> d2x``: for the exact ZOH
    with delay d, ``c_{d+1} ~ c_{d+2} ~ T^2/(2m)``; for the idealised image ``c_{d+1} ~
    T^2/m`` alone (correlation analysis, Ljung 1999 Sec. 6.1). Sensor noise is uncorrelated
    with past force steps.

    Parameters
    ----------
    x, f : ndarray, shape (n,)
        Positions [m] and forces sent [N].
    T : float
        Sample period [s].
    max_delay : int >= 0
        Largest delay [samples].
    pieces : list of (int, int), optional
        Row ranges of consecutive ticks (a difference across a lost STATE is left out).

    Returns
    -------
    tuple
        ``(d, hold, m)``: the delay [samples] in ``0 .. max_delay``, the hold's code
        (:data:`~hapsim.analysis.device_fit_model.HOLDS`) and the mass [kg] (0.1 when the
        taps' sum is not positive): a starting point of the search.
    """
    d2 = np.zeros_like(x)
    d2[1:-1] = x[2:] - 2 * x[1:-1] + x[:-2]
    df = np.zeros_like(f)
    df[1:] = np.diff(f)
    if pieces is not None and len(pieces) > 1:
        inside = np.zeros(x.size, bool)
        for a, b in pieces:
            inside[a + 1:b - 1] = True
        d2 = np.where(inside, d2, 0.0)
        df[[a for a, _ in pieces]] = 0.0
    D = int(max_delay) + 3
    n = x.size
    den = float(np.dot(df[:n - D], df[:n - D])) or 1.0
    c = np.array([float(np.dot(d2[j:n - D + j], df[:n - D])) / den for j in range(D)])
    j = int(np.argmax(c[1:])) + 1
    # the first of two equal taps: the earlier one if it is comparable
    if j >= 2 and c[j - 1] > 0.6 * c[j]:
        j -= 1
    nxt = c[j + 1] if j + 1 < D else 0.0
    zoh = nxt > 0.4 * c[j]
    s = c[j] + (nxt if zoh else 0.0)
    m = T * T / s if s > 0 else 0.1
    return max(min(j - 1, int(max_delay)), 0), (0 if zoh else 1), float(m)


class _Stretched:
    """Variable-projection model of one (hold, delay) candidate on the moving stretches.

    For given ``(m, b0)`` the positions are linear in the stretch states ``(x_s, v_s)``
    and, for the ZOH, in ``(fc+, fc-)``: those are solved by linear least squares
    (the stretch states eliminated stretch by stretch), and only ``(ln m, b0)`` are
    searched (G. H. Golub & V. Pereyra, SIAM J. Numer. Anal. 10(2), 1973).
    """

    def __init__(self, x, u, T, hold, st, frac=0.0):
        from hapsim.kernels.device_sim import stretch_basis, stretch_projection
        self.x, self.u, self.T, self.hold = x, u, T, hold
        self.frac = float(frac)
        self.starts, self.ends, self.dirs = st
        self.coulomb = hold == 0
        self._basis = stretch_basis
        self._project_kernel = stretch_projection
        n = x.size
        self._yu, self._g, self._c = np.zeros(n), np.zeros(n), np.zeros(n)
        self.idx = np.concatenate([np.arange(a, b) for a, b in zip(self.starts, self.ends)])
        lens = self.ends - self.starts
        self.sid = np.repeat(np.arange(self.starts.size), lens)
        self.offs = np.concatenate([[0], np.cumsum(lens)[:-1]])
        self.dir_i = self.dirs[self.sid]
        self._longest = int(lens.max()) if lens.size else 1
        self._bad = np.ones(self.idx.size)
        # what every _solve used to form again: the positions on the stretches and each
        # stretch's sample count (np.add.reduceat of ones: whole numbers, exact)
        self._xi = self.x[self.idx]
        self._L = np.add.reduceat(np.ones(self.idx.size), self.offs) if self.idx.size else \
            np.zeros(0)

    def _solve(self, lm, b0):
        """The variable projection at ``(ln m, b0)``: ``(r, phi, cx, cv)``, the residual on
        the stretches [m] (positions minus model), ``(fc+, fc-)`` [N] (zeros without
        Coulomb friction) and the stretches' initial positions [m] and velocities [m/s]
        (:func:`hapsim.kernels.device_sim.stretch_projection`, one compiled call: the same
        least squares as the numpy projection of :meth:`_projector`, at a tenth of its
        cost). Leaves the basis of ``(lm, b0)`` in ``_yu``, ``_g``, ``_c``.
        """
        ns = self.starts.size
        # outside the physical range the basis overflows (a negative b0 on a light mass
        # grows as exp(|b0| t / m)) and the least squares would get NaN: the optimiser
        # gets a residual far worse than any physical model's instead (1 m per sample),
        # so it steps back
        if not (_LM_RANGE[0] < lm < _LM_RANGE[1] and math.isfinite(b0)
                and abs(b0) * self.T * self._longest < 50.0 * math.exp(lm)):
            return self._bad, np.zeros(2), np.zeros(ns), np.zeros(ns)
        r, phi = np.empty(self.idx.size), np.empty(2)
        cx, cv = np.empty(ns), np.empty(ns)
        if not self._project_kernel(self.u, self.starts, self.ends, self.dirs, math.exp(lm),
                                    float(b0), self.T, self.hold, self.frac, self.coulomb,
                                    self._xi, self._yu, self._g, self._c, r, phi, cx, cv):
            return self._bad, np.zeros(2), np.zeros(ns), np.zeros(ns)
        return r, phi, cx, cv

    def _projector(self):
        """The projection on the complement of ``[1, g]`` stretch by stretch, ``g`` the
        basis of the last :meth:`_solve`: ``project(z) -> (z - fit, cx, cv)``, z of shape
        (rows,)."""
        g = self._g[self.idx]
        off = self.offs
        L = self._L
        Sg = np.add.reduceat(g, off)
        Sgg = np.add.reduceat(g * g, off)
        det = L * Sgg - Sg * Sg
        det = np.where(np.abs(det) > 0, det, 1.0)

        def project(z):
            """z minus its least-squares fit by [1, g] on each stretch."""
            Sz = np.add.reduceat(z, off)
            Sgz = np.add.reduceat(g * z, off)
            cx = (Sgg * Sz - Sg * Sgz) / det
            cv = (L * Sgz - Sg * Sz) / det
            return z - cx[self.sid] - cv[self.sid] * g, cx, cv
        return project

    def residual(self, p):
        return -self._solve(p[0], p[1])[0]

    def full(self, p):
        """Model positions on the stretches, all parameters, and the full Jacobian."""
        lm, b0 = p
        r, phi, cx, cv = self._solve(lm, b0)
        i = self.idx
        c = self._c[i].copy()

        def model(lm_, b0_):
            m = math.exp(lm_)
            yu, gg, cc = np.zeros_like(self.x), np.zeros_like(self.x), np.zeros_like(self.x)
            self._basis(self.u, self.starts, self.ends, m, b0_, self.T, self.hold, yu, gg, cc,
                        self.frac)
            y = yu[i] + cx[self.sid] + cv[self.sid] * gg[i]
            if self.coulomb:
                y = y + np.where(self.dir_i > 0, -cc[i] * phi[0], cc[i] * phi[1])
            return y
        y0 = model(lm, b0)
        hl, hb = 1e-6, 1e-6 * max(abs(b0), 1e-2)
        jl = (model(lm + hl, b0) - model(lm - hl, b0)) / (2 * hl)
        jb = (model(lm, b0 + hb) - model(lm, b0 - hb)) / (2 * hb)
        cols = [jl, jb]
        if self.coulomb:
            cols += [np.where(self.dir_i > 0, -c, 0.0), np.where(self.dir_i < 0, c, 0.0)]
        # Frisch-Waugh-Lovell: the stretch states partialled out of the Jacobian leave the
        # marginal covariance of (ln m, b0, fc+, fc-) (the projector of the last _solve)
        self._solve(lm, b0)
        project = self._projector()
        Jr = np.column_stack([project(cc)[0] for cc in cols])
        params = np.concatenate([[lm, b0], phi if self.coulomb else []])
        return y0, params, Jr, 2 * self.starts.size


class _Difference:
    """What both forward differences share: the residual remembered at the point
    :meth:`fun` last returned it (scipy passes its ``f0`` the same way), and scipy's step
    ``h_j = sqrt(eps) sign(x_j) max(1, |x_j|)`` (sign 1 at 0;
    ``scipy.optimize._numdiff._compute_absolute_step``, ``'2-point'``)."""

    def __init__(self, fun):
        self._fun = fun
        self._last = None

    def fun(self, p):
        """The residual at ``p``, remembered for the Jacobian at the same point."""
        f = np.atleast_1d(self._fun(p))
        self._last = (np.array(p, float), f.copy())
        return f

    def _base(self, p):
        """``(x0, f(x0), h)`` for a Jacobian at ``p``."""
        x0 = np.asarray(p, float)
        if self._last is not None and np.array_equal(self._last[0], x0):
            f0 = self._last[1]
        else:
            f0 = np.atleast_1d(self._fun(x0.copy()))
        sign = (x0 >= 0).astype(float) * 2 - 1
        h = np.finfo(np.float64).eps ** 0.5 * sign * np.maximum(1.0, np.abs(x0))
        return x0, f0, h


class _ForwardDifference(_Difference):
    """The variable projection's Jacobian by forward differences, the same numbers, bit for
    bit, as ``least_squares(..., jac='2-point')`` forms them
    (``scipy.optimize.approx_derivative``, dense, no bounds), without its wrapping.

    Column ``j`` is ``(f(x + h_j e_j) - f(x)) / ((x_j + h_j) - x_j)`` with scipy's step
    ``h_j = sqrt(eps) sign(x_j) max(1, |x_j|)`` (sign 1 at 0); ``f(x)`` is the residual
    :meth:`fun` last returned at the same point (as scipy passes its ``f0``), else
    evaluated. With two parameters and a compiled residual
    (:func:`hapsim.kernels.device_sim.stretch_projection`, ~60 us) scipy's wrapping was
    most of a Jacobian's cost. ``tests/test_device_fit_projection.py`` compares the two.

    Parameters
    ----------
    fun : callable
        ``fun(p) -> ndarray, shape (n_rows,)``, the residual; a new array each call.
    """

    def __call__(self, p):
        """The Jacobian at ``p``: ndarray, shape ``(n_rows, p.size)``."""
        x0, f0, h = self._base(p)
        J = np.empty((f0.size, x0.size))
        for j in range(x0.size):
            x1 = x0.copy()
            x1[j] = x0[j] + h[j]
            J[:, j] = (np.atleast_1d(self._fun(x1)) - f0) / ((x0[j] + h[j]) - x0[j])
        return J


def fit_stretched(x, u, T, hold, st, starts, frac=0.0):
    """The variable-projection fit of one (hold, delay) candidate on the stretches.

    ``(ln m, b0)`` by Levenberg-Marquardt (``scipy.optimize.least_squares``, ``"lm"``, as
    :func:`levenberg_marquardt` calls it, its Jacobian scipy's forward difference as
    :class:`_ForwardDifference` forms it) from each
    start, the stretch states and Coulomb frictions eliminated by linear least
    squares at every step (Golub & Pereyra 1973); the least cost of the starts is kept.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Positions [m].
    u : ndarray, shape (n,)
        Force applied over each period [N] (:func:`applied_force` at the delay).
    T : float
        Sample period [s].
    hold : int
        The hold's code (:data:`~hapsim.analysis.device_fit_model.HOLDS`).
    st : tuple of ndarray
        ``(starts, ends, dirs)`` of :func:`~hapsim.analysis.device_fit_stretches.moving_stretches`.
    starts : sequence of (float, float)
        Starting ``(ln m [ln kg], b0 [N s/m])``.
    frac : float in [0, 1)
        Sub-sample part of the delay [periods] (the split hold).

    Returns
    -------
    tuple
        ``(model, result)``: the candidate's model (its ``residual``, ``full`` and
        stretches) and the ``OptimizeResult`` of the best start (:func:`levenberg_marquardt`),
        None when no start
        converged to a finite residual.
    """
    mod = _Stretched(x, u, T, hold, st, frac)
    best = None
    for p0 in starts:
        jac = _ForwardDifference(mod.residual)
        try:
            r = levenberg_marquardt(jac.fun, jac, p0, tol=1e-11, max_nfev=200)
        except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(r.fun)) and (best is None or r.cost < best.cost):
            best = r
    return mod, best


def search_candidates(x, f, T, late, holds, max_delay, st, d0, h0, m0, known=None, seq=None):
    """Fit every (hold, delay): the correlation's guess from three starts, then the others
    warm-started from it. With ``known = (u, d)`` (the force the device applied, from its
    account) only the holds are tried, at the device's delay ``d``.

    Parameters
    ----------
    x, f : ndarray, shape (n,)
        Positions [m] and forces sent [N].
    T : float
        Sample period [s].
    late : array_like of bool, shape (n,), or None
        Rows the device reported holding an older force.
    holds : sequence of str
        Hold names tried (:data:`~hapsim.analysis.device_fit_model.HOLDS`).
    max_delay : int >= 0
        Largest delay tried [samples].
    st : tuple of ndarray
        ``(starts, ends, dirs)`` of :func:`~hapsim.analysis.device_fit_stretches.moving_stretches`.
    d0, h0, m0 : int, int, float
        The guess of :func:`correlation_guess`: delay [samples], hold code, mass [kg].
    known : tuple (ndarray, int), optional
        The applied force [N] per row and the device's delay [samples].
    seq : ndarray of int, shape (n,), optional
        The rows' ticks (:func:`applied_force`).

    Returns
    -------
    list of dict
        One per fitted model: ``hold`` (name), ``delay`` [samples], ``frac`` [periods],
        ``cost`` (half the residual's sum of squares [m^2]), ``_mod`` (its
        variable-projection model), ``_res`` (scipy's ``OptimizeResult``).
    """
    inv = {v: k for k, v in HOLDS.items()}
    delays = range(int(max_delay) + 1) if known is None else (known[1],)
    if known is not None:
        d0 = known[1]
    first = (inv[h0] if inv[h0] in holds else holds[0], d0)
    order = [first] + [(h, d) for h in holds for d in delays if (h, d) != first]
    starts = [(math.log(m0), b) for b in (1.0, 0.1, 4.0)]
    cands = []
    for hname, d in order:
        u = applied_force(f, d, late, seq) if known is None else known[0]
        mod, res = fit_stretched(x, u, T, HOLDS[hname], st, starts)
        if res is None:
            continue
        cands.append({"hold": hname, "delay": d, "frac": 0.0, "cost": float(res.cost),
                      "_mod": mod, "_res": res})
        if len(cands) == 1:
            starts = [res.x]
    return cands


#: Most Jacobian entries (rows x parameters) the refinement hands to least squares as a
#: dense array, solved by its ``tr_solver="exact"`` (an SVD of the Jacobian per step); a
#: larger one goes as a sparse matrix to its ``"lsmr"`` (scipy's documentation: "exact"
#: for small dense Jacobians, "lsmr" for large sparse ones). A 2 s record at 1 kHz with
#: its stretches (~2,000 x 10-30) is well under it: the sparse path's operator layers were
#: three quarters of a refinement there (the blind identification of 50 devices, 12.9 ->
#: 5.2 CPU-s); 2e5 entries (1.6 MB) keep the SVD at a few ms.
DENSE_JACOBIAN_MAX = 200_000

#: Grid of the sub-sample delay's fraction searched first (then refined around the best).
FRACTION_GRID = (0.25, 0.5, 0.75)
#: Half-width of the bounded search around the grid's best [periods]: one grid step.
_FRACTION_STEP = 0.25
#: The bounded search's tolerance on the fraction [periods]: the fraction is not known
#: better than this whatever the record (a noise-free one's likelihood interval is far
#: narrower), and the intervals cover it (:func:`hapsim.analysis.device_fit.fit_device`).
FRACTION_TOL = 2e-3


def fraction_candidate(x, u, T, st, start, d, fr):
    """One zero-order-hold candidate at the delay ``d + fr``, on the refined cost.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Positions [m].
    u : ndarray, shape (n,)
        The force applied at the whole delay ``d`` [N].
    T : float
        Sample period [s].
    st : tuple of ndarray
        The stretches (:func:`~hapsim.analysis.device_fit_stretches.moving_stretches`).
    start : list of ndarray
        Starting points ``(ln m, b0)`` (:func:`fit_stretched`).
    d : int
        Whole delay [samples].
    fr : float in [0, 1)
        Fraction [periods].

    Returns
    -------
    dict or None
        The candidate (``hold``, ``delay``, ``frac``, ``cost``, ``_mod``, ``_res``,
        ``_ref``), None when the fit fails.
    """
    mod, res = fit_stretched(x, u, T, HOLDS["zoh"], st, start, float(fr))
    if res is None:
        return None
    c = {"hold": "zoh", "delay": d, "frac": float(fr), "cost": float(res.cost), "_mod": mod,
         "_res": res}
    if mod.coulomb:
        # the profile over the fraction on the refined cost (Coulomb reversals inside a
        # stretch), as the best whole delay's is: a refined best beside unrefined
        # neighbours made every neighbour "ruled out" (intervals of zero width that
        # missed the truth, 6 of 30 devices)
        ref = refine(mod, res.x)
        c["_ref"] = ref if ref is not None and ref[4] < c["cost"] else None
        if c["_ref"] is not None:
            c["cost"] = c["_ref"][4]
    return c


def search_fraction(x, T, late, st, cands, known=None, seq=None, f=None):
    """Sub-sample delays ``d + frac`` for the zero-order hold (issue 29 item 3): the
    split hold (:mod:`hapsim.analysis.subsample`) fitted at ``frac`` on
    :data:`FRACTION_GRID`, then refined around the best by a bounded scalar search of
    the cost (Brent's method, R. P. Brent, *Algorithms for Minimization without
    Derivatives*, 1973, ch. 5); every fit a candidate (``frac`` > 0) beside the whole
    delays'. The whole part: the account's delay (a device that names the force it
    applied), else the best whole delay's and the one below it (the truth lies between
    two whole delays the plain hold tried).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Positions [m].
    T : float
        Sample period [s].
    late : array_like of bool, shape (n,), or None
        Rows the device reported holding an older force.
    st : tuple of ndarray
        ``(starts, ends, dirs)`` of :func:`~hapsim.analysis.device_fit_stretches.moving_stretches`.
    cands : list of dict
        The whole delays' candidates (:func:`search_candidates`); those near the new ones
        get their refinement (``_ref``, ``cost``) here.
    known : tuple (ndarray, int), optional
        The applied force [N] per row and the device's delay [samples].
    seq : ndarray of int, shape (n,), optional
        The rows' ticks.
    f : ndarray, shape (n,), optional
        Forces sent [N] (needed without ``known``).

    Returns
    -------
    list of dict
        One per fitted model: ``hold`` (name), ``delay`` [samples], ``frac`` [periods],
        ``cost`` (half the residual's sum of squares [m^2]), ``_mod`` (its
        variable-projection model), ``_res`` (scipy's ``OptimizeResult``).
        Only the new (sub-sample) candidates, each with its refinement ``_ref`` (None
        when it did not lower the cost).
    """
    from scipy.optimize import minimize_scalar
    zoh = [c for c in cands if c["hold"] == "zoh"]
    if not zoh:
        return []
    best = min(zoh, key=lambda c: c["cost"])
    bases = ([known[1]] if known is not None
             else sorted({best["delay"], max(best["delay"] - 1, 0)}))
    new = []
    for d in bases:
        u = known[0] if known is not None else applied_force(f, d, late, seq)
        start = [c["_res"].x for c in zoh if c["delay"] == d] or [best["_res"].x]
        seen = {}

        def fit(fr, d=d, u=u, start=start, seen=seen):
            fr = float(fr)
            if fr in seen:
                return seen[fr]
            c = fraction_candidate(x, u, T, st, start, d, fr)
            seen[fr] = c
            if c is not None:
                new.append(c)
            return c
        grid = [(fr, fit(fr)) for fr in FRACTION_GRID]
        base = [c for c in zoh if c["delay"] == d]
        pts = [(0.0, base[0] if base else None)] + grid
        ok = [(fr, c) for fr, c in pts if c is not None]
        if not ok:
            continue
        fb = min(ok, key=lambda t: t[1]["cost"])[0]
        lo, hi = max(fb - _FRACTION_STEP, 0.0), min(fb + _FRACTION_STEP, 0.999)
        if hi - lo > 1e-3:
            minimize_scalar(lambda fr: (fit(fr) or {"cost": math.inf})["cost"],
                            bounds=(lo, hi), method="bounded",
                            options={"xatol": FRACTION_TOL, "maxiter": 10})
    # the whole delays beside them on the same (refined) cost: the profile's ends
    near = set(bases) | {b + 1 for b in bases}
    for c in zoh:
        if c["delay"] in near and "_ref" not in c and c["_mod"].coulomb:
            ref = refine(c["_mod"], c["_res"].x)
            c["_ref"] = ref if ref is not None and ref[4] < c["cost"] else None
            if c["_ref"] is not None:
                c["cost"] = c["_ref"][4]
    return new


class _BlockDifference(_Difference):
    """The refinement's Jacobian by forward differences, as scipy's sparse finite difference
    forms it, in ``k + 2`` evaluations.

    The residual of row ``r`` depends on the ``k`` shared parameters and on its own
    stretch's two states only (``k + sid[r]``, ``k + ns + sid[r]``): every shared
    parameter is stepped alone, every stretch's initial position at once, then every
    initial velocity at once (A. R. Curtis, M. J. D. Powell & J. K. Reid, J. Inst. Math.
    Appl. 13, 1974). Each entry is ``(f(x + h_j e_j)_r - f(x)_r) / ((x_j + h_j) - x_j)``
    with scipy's step ``h_j = sqrt(eps) sign(x_j) max(1, |x_j|)``
    (``scipy.optimize.approx_derivative``, ``method='2-point'``): the same numbers, bit
    for bit, as ``least_squares(..., jac_sparsity=S)`` computes (its column groups stepped
    together too, the structure exact), returned in the same canonical CSR layout, without
    the sparse indexing it repeats at every call (two thirds of a fit's time).
    ``tests/test_device_fit_jacobian.py`` compares the two.

    Parameters
    ----------
    fun : callable
        ``fun(p) -> ndarray, shape (n_rows,)``, the residual; a new array each call.
    k : int
        Shared parameters (columns ``0 .. k-1``, dense).
    sid : ndarray of int, shape (n_rows,)
        Each row's stretch.
    ns : int
        Stretches (columns ``k .. k+ns-1``: initial positions; ``k+ns .. k+2ns-1``:
        initial velocities).
    """

    def __init__(self, fun, k, sid, ns):
        super().__init__(fun)
        self.k, self.sid, self.ns = int(k), np.asarray(sid), int(ns)
        m = self.sid.size
        n = self.k + 2 * self.ns
        self.shape = (m, n)
        w = self.k + 2
        self._cols = np.empty((m, w), np.int32)
        self._cols[:, :self.k] = np.arange(self.k)
        self._cols[:, self.k] = self.k + self.sid
        self._cols[:, self.k + 1] = self.k + self.ns + self.sid
        self._rows = np.arange(m)[:, None]
        self._indices = self._cols.ravel()
        self._indptr = np.arange(0, m * w + 1, w, dtype=np.int32)
        self._groups = [np.arange(n) == j for j in range(self.k)]
        self._groups += [(np.arange(n) >= self.k) & (np.arange(n) < self.k + self.ns),
                         np.arange(n) >= self.k + self.ns]

    def data(self, p):
        """The Jacobian's entries at ``p``, row by row, shape ``(n_rows, k + 2)`` (column
        ``g`` of row ``r`` is ``J[r, cols[r, g]]``)."""
        x0, f0, h = self._base(p)
        m = self.shape[0]
        data = np.empty((m, self.k + 2))
        for g, e in enumerate(self._groups):
            x = x0 + h * e
            dx = x - x0
            df = np.atleast_1d(self._fun(x)) - f0
            data[:, g] = df / dx[self._cols[:, g]]
        return data

    def dense(self, p):
        """The Jacobian at ``p`` as a dense array, shape ``(n_rows, n)``: the entries of
        :meth:`data` in their columns, zeros elsewhere."""
        d = np.zeros(self.shape)
        d[self._rows, self._cols] = self.data(p)
        return d

    def __call__(self, p):
        """The Jacobian at ``p``: a ``scipy.sparse.csr_array`` of shape ``(n_rows, n)``."""
        from scipy.sparse import csr_array
        return csr_array((self.data(p).ravel(), self._indices, self._indptr),
                         shape=self.shape)


def _refine_residual(mod, out, xi):
    """The refinement's residual ``p -> model - positions`` on the stretches of ``mod``, ``p``
    = ``(ln m, b0[, fc+, fc-], x_s..., v_s...)`` (``out``: the positions' scratch, shape
    (n,); ``xi``: the recorded positions on the stretches)."""
    from hapsim.kernels.device_sim import simulate_device
    k = 4 if mod.coulomb else 2
    ns = mod.starts.size
    i = mod.idx

    lo, hi = _LM_RANGE

    def resid(p):
        if not lo <= p[0] <= hi:
            # no device there (exp(ln m) under- or overflows the simulation): a residual
            # that is not finite, which the trust region answers by shrinking its step
            # (scipy's trf), not an exception
            return np.full(i.size, np.inf)
        fp_, fn = (p[2], p[3]) if mod.coulomb else (0.0, 0.0)
        simulate_device(mod.u, math.exp(p[0]), p[1], fp_, fn, mod.starts, mod.ends,
                        np.ascontiguousarray(p[k:k + ns]),
                        np.ascontiguousarray(p[k + ns:k + 2 * ns]), mod.T, mod.hold, out,
                        mod.frac)
        return out[i] - xi
    return resid


def _refine_difference(mod, jac, out, xi):
    """``jac.data`` (a :class:`_BlockDifference` of :func:`_refine_residual`), bit for bit,
    in one compiled call (:func:`hapsim.kernels.device_sim.refine_jacobian`: the ``k + 2``
    residuals and their differences without a numpy call each)."""
    from hapsim.kernels.device_sim import refine_jacobian
    k, ns = jac.k, jac.ns
    groups = np.array(jac._groups, float)
    colx, colv = k + mod.sid, k + ns + mod.sid
    i = mod.idx

    def data(p):
        x0, f0, h = jac._base(p)
        X = x0 + h * groups               # the steps as _BlockDifference.data takes them
        dX = X - x0
        masses = np.array([math.exp(v) for v in X[:, 0]])     # Python's exp, as resid's
        d = np.empty((i.size, k + 2))
        refine_jacobian(mod.u, masses, X, dX, mod.coulomb, mod.starts, mod.ends, mod.T,
                        mod.hold, mod.frac, i, xi, f0, colx, colv, out, d)
        return d
    return data


def refine(mod, p_lin):
    """Nonlinear output error on the stretches (Coulomb friction with the mock's stick and
    reversal rules), from the variable-projection solution: a velocity that reverses for a
    sample inside a stretch (too briefly for the positions to show) is then modelled.
    Trust-region reflective least squares over all parameters, its Jacobian by
    :class:`_BlockDifference`, dense and solved exactly up to :data:`DENSE_JACOBIAN_MAX`
    entries, sparse (LSMR) beyond; the stretch states are partialled out of the Jacobian
    stretch by stretch (Frisch-Waugh-Lovell).

    Parameters
    ----------
    mod : object
        A candidate's model (:func:`fit_stretched`).
    p_lin : ndarray, shape (2,)
        The variable projection's ``(ln m, b0)``.

    Returns
    -------
    tuple or None
        ``(y, theta, J_theta_partialled, n_nuisance, cost)``: the model's positions on
        the stretches [m], shape (n_s,); ``(ln m, b0[, fc+, fc-])``; their Jacobian with
        the stretch states partialled out, shape (n_s, k); the stretch states' count;
        half the residual's sum of squares [m^2]. None when the fit fails or diverges.
    """
    from scipy.optimize import least_squares

    _, phi, cx, cv = mod._solve(p_lin[0], p_lin[1])
    k = 4 if mod.coulomb else 2
    ns = mod.starts.size
    i = mod.idx
    out = np.zeros_like(mod.x)
    xi = mod.x[i]
    resid = _refine_residual(mod, out, xi)
    p0 = np.concatenate([[p_lin[0], p_lin[1]], phi if mod.coulomb else [], cx, cv])
    rows = np.arange(i.size)
    jac = _BlockDifference(resid, k, mod.sid, ns)
    jac.data = _refine_difference(mod, jac, out, xi)     # the same entries, compiled
    try:
        dense = jac.shape[0] * jac.shape[1] <= DENSE_JACOBIAN_MAX
        r = least_squares(jac.fun, p0, method="trf", x_scale="jac",
                          jac=jac.dense if dense else jac,
                          tr_solver="exact" if dense else "lsmr",
                          xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=60)
    except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(r.fun)):
        return None
    J = r.jac.toarray() if hasattr(r.jac, "toarray") else np.asarray(r.jac)
    # Frisch-Waugh-Lovell: partial the stretch states out, stretch by stretch
    off = mod.offs
    a1 = J[rows, k + mod.sid]
    a2 = J[rows, k + ns + mod.sid]
    s11 = np.add.reduceat(a1 * a1, off)
    s12 = np.add.reduceat(a1 * a2, off)
    s22 = np.add.reduceat(a2 * a2, off)
    det = s11 * s22 - s12 * s12
    det = np.where(np.abs(det) > 0, det, 1.0)
    cols = []
    for c in range(k):
        zc = J[:, c]
        t1 = np.add.reduceat(a1 * zc, off)
        t2 = np.add.reduceat(a2 * zc, off)
        c1 = (s22 * t1 - s12 * t2) / det
        c2 = (s11 * t2 - s12 * t1) / det
        cols.append(zc - c1[mod.sid] * a1 - c2[mod.sid] * a2)
    y = r.fun + xi
    return y, r.x[:k], np.column_stack(cols), 2 * ns, float(r.cost)

"""The device fit's statistics (:mod:`hapsim.analysis.device_fit`): the delay's interval,
the verdict's test, the residual's effective samples, the Newey-West covariance, the
sensor noise and its interval, and the replicates of a quantised record.

The intervals are described in :mod:`hapsim.analysis.device_fit` ('Intervals', 'Verdict').
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.device_fit_model import LEVEL, POSITION_FLOOR, Estimate
from hapsim.analysis.device_fit_search import fit_stretched, refine

__all__ = ["delay_interval", "explains", "effective_samples", "best_residual",
           "ambiguity_sentence", "UNDETERMINED_VARIANCE", "hac_covariance", "MAD_EFFICIENCY",
           "chi2_ppf_1", "noise_estimate", "MASS_SPAN", "REPLICATES", "grid_replicates"]


def delay_interval(cands, best, close, n_lr, s_best, crit, nu):
    """The delay ``d + frac`` [periods] as an :class:`Estimate`: the best candidate's, its
    interval the set the likelihood ratio does not rule out among the zero-order hold's
    candidates (whole and sub-sample), each end interpolated to where the ratio crosses
    its bound between the last candidate inside and the first outside (linear in the
    ratio's signed root, exact for a quadratic profile); an end with no candidate outside
    beyond it stays at the last one inside. Under the idealised hold: the whole delay,
    its interval ``delay_range``.

    Parameters
    ----------
    cands : list of dict
        The candidates (:func:`~hapsim.analysis.device_fit_search.search_candidates`,
        :func:`~hapsim.analysis.device_fit_search.search_fraction`).
    best : dict
        The best candidate.
    close : callable
        ``close(c)``: the likelihood ratio does not rule candidate ``c`` out.
    n_lr : float
        Samples the likelihood ratio counts (:func:`effective_samples`).
    s_best : float
        The best cost, at least half of ``nu`` times :data:`POSITION_FLOOR` squared
        [m^2].
    crit : float
        The ratio's bound (:func:`chi2_ppf_1` at :data:`LEVEL`).
    nu : int
        Samples on the stretches.

    Returns
    -------
    Estimate
        The delay [periods] with its interval.
    """
    def total(c):
        return c["delay"] + c.get("frac", 0.0)
    zoh = sorted((c for c in cands if c["hold"] == "zoh"), key=total)
    if best["hold"] != "zoh" or not zoh:
        d = [c["delay"] for c in cands if close(c)] or [best["delay"]]
        return Estimate(float(best["delay"]), float(min(d)), float(max(d)), "periods")

    def h(c):
        # the signed root of the likelihood ratio: linear in the delay where the cost is
        # quadratic about its minimum (a chord of the ratio itself, convex, crossed its
        # bound too early: an interval 0.427..0.433 for a true 0.4345)
        return math.sqrt(max(n_lr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2)
                                             / s_best), 0.0))
    bound = math.sqrt(crit)
    inside = [i for i, c in enumerate(zoh) if close(c)]
    if not inside:
        v = total(best)
        return Estimate(v, v, v, "periods")
    i0, i1 = inside[0], inside[-1]

    def cross(i_in, i_out):
        a, b = zoh[i_in], zoh[i_out]
        ha, hb = h(a), h(b)
        t = 0.0 if not hb > ha else min(max((bound - ha) / (hb - ha), 0.0), 1.0)
        return total(a) + t * (total(b) - total(a))
    lo = cross(i0, i0 - 1) if i0 > 0 else total(zoh[i0])
    # the top with no candidate beyond it (a device's account fixes the whole delay d:
    # the fractions tried end at d + 0.75) is not ruled out up to d + 1, where the
    # fraction's range ends
    hi = cross(i1, i1 + 1) if i1 + 1 < len(zoh) else float(zoh[i1]["delay"] + 1)
    v = total(best)
    return Estimate(v, min(lo, v), max(hi, v), "periods")


def explains(resid, q: float) -> tuple[bool, float, float]:
    """The verdict's test (:mod:`hapsim.analysis.device_fit`, 'Verdict'): the residual's
    RMS against the sensor's ``floor = sqrt(q^2/12 + sigma_w^2)``.

    Parameters
    ----------
    resid : array_like, shape (n_s,)
        The model's residual on the stretches [m].
    q : float >= 0
        Encoder quantum [m].

    Returns
    -------
    tuple (bool, float, float)
        ``(explained, rms, floor)``: ``rms <= 2 floor`` (plus three
        :data:`POSITION_FLOOR`), the RMS and the floor [m] (``sigma_w``: white noise from
        the median absolute second difference of the residual).
    """
    resid = np.asarray(resid, float)
    rms = float(math.sqrt(np.mean(resid ** 2)))
    d2 = np.diff(resid, 2)
    sig_w = float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))
    floor = math.sqrt(q ** 2 / 12.0 + sig_w ** 2)
    return bool(rms <= 2.0 * floor + 3 * POSITION_FLOOR), rms, floor


def effective_samples(r, offs, lag: int) -> float:
    """Independent samples a residual is worth: ``N / tau`` with ``tau = 1 + 2 sum_k
    (1 - k/(L+1)) rho_k`` (``k = 1 .. L``, Bartlett weights, ``rho_k`` the residual's
    autocorrelation pooled over the stretches, never across two), at least 1 sample and
    at most ``N``. The integrated autocorrelation time of a stationary series (M. B.
    Priestley, *Spectral Analysis and Time Series*, 1981, Sec. 5.3; the Newey-West weights
    of :func:`hac_covariance`): a quantiser's error on a slow motion is a sawtooth
    correlated over many samples, and a likelihood ratio that counts its ``N`` samples as
    independent tells candidates apart that the record cannot.

    Parameters
    ----------
    r : array_like, shape (N,)
        The residual on the stretches [m].
    offs : sequence of int
        Each stretch's first row in ``r``.
    lag : int >= 0
        Bartlett lag ``L`` [samples].

    Returns
    -------
    float
        ``N / tau`` in ``[1, N]`` (``max(N, 1)`` for a residual of fewer than 2 samples or
        all zero).
    """
    r = np.asarray(r, float)
    n = r.size
    den = float(np.dot(r, r))
    if n < 2 or den <= 0:
        return float(max(n, 1))
    bounds = list(zip(offs, list(offs[1:]) + [n]))
    tau = 1.0
    for k in range(1, int(lag) + 1):
        num = sum(float(np.dot(r[a:b - k], r[a + k:b])) for a, b in bounds if b - a > k)
        tau += 2.0 * (1.0 - k / (lag + 1.0)) * num / den
    return float(min(max(n / max(tau, 1.0), 1.0), n))


def best_residual(best) -> np.ndarray:
    """The best candidate's residual on its stretches (its refinement's when kept).

    Parameters
    ----------
    best : dict
        A candidate (:func:`~hapsim.analysis.device_fit_search.search_candidates`), with
        ``_ref`` when refined.

    Returns
    -------
    ndarray, shape (n_s,)
        Model minus measured positions [m].
    """
    mod = best["_mod"]
    if best.get("_ref") is not None:
        return best["_ref"][0] - mod.x[mod.idx]
    return mod.residual(best["_res"].x)


def ambiguity_sentence(best, rival, nu, n_eff, q, length_unit: str = "m") -> str:
    """The sentence naming two delays a record cannot tell apart.

    Parameters
    ----------
    best, rival : dict
        The two candidates.
    nu : int
        Samples on the stretches.
    n_eff : float
        Effective samples of the likelihood ratio (:func:`effective_samples`).
    q : float >= 0
        Encoder quantum [m] ([rad] on a rotary axis).
    length_unit : str
        The positions' unit, said in micro-units (``"m"``, or ``"rad"``).

    Returns
    -------
    str
    """
    def said(c_):
        return (f"d = {c_['delay']} ({c_['hold']} hold, residual RMS "
                f"{math.sqrt(2.0 * c_['cost'] / nu) * 1e6:.3g} u{length_unit})")
    enc = f"a {q * 1e6:.3g} u{length_unit} encoder" if q > 0 else "the sensor's noise"
    return (f"the delay is ambiguous: {said(best)} and {said(rival)} explain the record "
            f"alike (likelihood ratio within the {LEVEL:.1%} chi-square bound over "
            f"{n_eff:.0f} effective samples of {nu}: the residual of {enc} is correlated)")


#: Variance given to a parameter the record does not determine (its Jacobian column is
#: zero, or lies in the span of the others', after scaling): finite, so that weighted sums
#: of the covariance stay numbers, and so large that any interval through it is the whole
#: line (a mass interval of exp(1e150): refused as not determined).
UNDETERMINED_VARIANCE = 1e300


def _bread(JtJ):
    """The inverse of the normal matrix, column-scaled, and which parameters it leaves
    undetermined.

    ``np.linalg.pinv(JtJ)`` cuts singular values below 1e-15 of the largest: a parameter
    whose sensitivity is tiny beside another's (a mass of 6.5e11 kg fitted to a record
    of straight stretches, beside the Coulomb terms) got variance ZERO, a narrow interval
    around a wrong value. Scaling every column to unit norm first (the covariance is
    invariant to it: Jacobi scaling) leaves only the collinearity the record really has;
    the directions of the scaled matrix below the rank tolerance of
    ``numpy.linalg.matrix_rank`` (largest eigenvalue times size times the machine
    epsilon) are not determined: every parameter with weight on them beyond
    ``sqrt(eps)`` is marked undetermined.

    Returns ``(bread, undetermined)``: ndarray (p, p) and a bool mask (p,).
    """
    p = JtJ.shape[0]
    d = np.sqrt(np.maximum(np.diag(JtJ), 0.0))
    ok = np.isfinite(d) & (d > 0.0)
    s = np.where(ok, d, 1.0)
    A = JtJ / np.outer(s, s)
    A[~ok, :] = 0.0
    A[:, ~ok] = 0.0
    lam, V = np.linalg.eigh(A)
    eps = np.finfo(float).eps
    tol = max(float(lam.max(initial=0.0)), 0.0) * p * eps
    keep = lam > tol
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    bread = (V * inv) @ V.T / np.outer(s, s)
    null = V[:, ~keep]
    undetermined = ~ok | (np.abs(null).max(axis=1, initial=0.0) > math.sqrt(eps))
    return bread, undetermined


def hac_covariance(J, r, lag, extra=0):
    """Newey-West covariance of the least-squares parameters (Newey & West 1987); a
    parameter the record does not determine (:func:`_bread`) has variance
    :data:`UNDETERMINED_VARIANCE` and no covariance with the others.

    Parameters
    ----------
    J : ndarray, shape (n, p)
        The residual's Jacobian in the parameters (nuisance parameters partialled out).
    r : ndarray, shape (n,)
        The residual [m].
    lag : int >= 0
        Bartlett lag [samples].
    extra : int
        Nuisance parameters partialled out (counted in the degrees of freedom).

    Returns
    -------
    ndarray, shape (p, p)
        ``(J'J)^-1 S (J'J)^-1 n / (n - p - extra)`` plus :data:`POSITION_FLOOR` squared
        times ``(J'J)^-1`` (in the parameters' units squared).
    """
    n, p = J.shape
    JtJ = J.T @ J
    bread, undetermined = _bread(JtJ)
    g = J * r[:, None]
    S = g.T @ g
    for lg in range(1, min(lag, n - 1) + 1):
        w = 1.0 - lg / (lag + 1.0)
        G = g[lg:].T @ g[:-lg]
        S += w * (G + G.T)
    cov = bread @ S @ bread * n / max(n - p - extra, 1)
    cov += POSITION_FLOOR ** 2 * bread
    if np.any(undetermined):
        cov[undetermined, :] = 0.0
        cov[:, undetermined] = 0.0
        cov[undetermined, undetermined] = UNDETERMINED_VARIANCE
    return cov


#: Asymptotic efficiency of the median absolute deviation as a Gaussian scale estimator
#: (P. J. Huber & E. M. Ronchetti, *Robust Statistics*, 2nd ed., 2009, Sec. 5.5: 36.7 %).
MAD_EFFICIENCY = 0.367
#: Integrated autocorrelation time of the second differences of white noise: their
#: autocorrelation is -4/6 at lag 1 and 1/6 at lag 2, so ``1 + 2 (16 + 1) / 36``.
_D2_TAU = 1.0 + 2.0 * (16.0 + 1.0) / 36.0


def _noise_white(r, offs, delta, z):
    """The white sensor noise of an unquantised record from its residual's second
    differences (module notes): ``sigma = 1.4826 median|D2 r| / sqrt(6)``, the differences
    taken inside each stretch (``offs``: their first rows), never across two.

    A model error is smooth between the device's events (a stick, a reversal) and its
    second differences are ~0 but for a few samples there, which the median ignores: the
    residual's own variance counted it as noise (a device with no noise got an interval
    of 8-11 um, the model's Coulomb mismatch). The interval is the median absolute
    deviation's normal one, ``sigma (1 +- z / sqrt(2 MAD_EFFICIENCY N / _D2_TAU))``, its
    lower end less the model output's own share ``delta`` and POSITION_FLOOR (in
    quadrature), at least 0."""
    r = np.asarray(r, float)
    edges = list(np.asarray(offs, np.int64)) + [r.size]
    d2 = np.concatenate([np.diff(r[a:b], 2) for a, b in zip(edges[:-1], edges[1:])
                         if b - a >= 3] or [np.zeros(0)])
    if d2.size < 8:
        return Estimate(0.0, 0.0, math.inf, "m")
    sig = float(1.4826 * np.median(np.abs(d2)) / math.sqrt(6.0))
    h = z / math.sqrt(2.0 * MAD_EFFICIENCY * d2.size / _D2_TAU)
    lo2 = (sig * max(1.0 - h, 0.0)) ** 2 - (delta ** 2 + POSITION_FLOOR ** 2)
    hi = sig * (1.0 + h) + POSITION_FLOOR
    return Estimate(sig, math.sqrt(lo2) if lo2 > 0 else 0.0, hi, "m")


def chi2_ppf_1(p: float) -> float:
    """The quantile ``p`` of the chi-square distribution with one degree of freedom.

    Parameters
    ----------
    p : float
        Probability, in (0, 1).

    Returns
    -------
    float
        ``2 gammaincinv(1/2, p)``: the formula of ``scipy.stats.chi2.ppf(p, 1)``, the same
        number bit for bit (scipy 1.1x), without importing ``scipy.stats`` (~1 CPU-s in
        each process that fits a device; the quantiles here are of ``norm``, ``t`` and
        ``chi2`` only, taken from ``scipy.special`` as ``scipy.stats`` takes them).
    """
    from scipy.special import gammaincinv
    return float(2 * gammaincinv(0.5, p))


def noise_estimate(y, xm, q, delta, z, dof, offs=None):
    """ML estimate and profile interval of the sensor noise (the notes of
    :mod:`hapsim.analysis.device_fit`, 'Intervals'); an unquantised record's from its
    second differences (:func:`_noise_white`), and so is a quantised record's whose noise
    is at least twice the quantum, less the quantiser's variance ``q^2/12`` (Widrow &
    Kollar, *Quantization Noise*, 2008, Sec. 5.2 and 11.1).

    Parameters
    ----------
    y, xm : ndarray, shape (n_s,)
        Measured and model positions on the stretches [m].
    q : float >= 0
        Encoder quantum [m] (0: none).
    delta : float >= 0
        The model output's own error [m].
    z : float
        The normal quantile of :data:`LEVEL`.
    dof : int
        Parameters fitted (the unquantised likelihood's degrees of freedom).
    offs : sequence of int, optional
        Each stretch's first row (an unquantised record's noise from its second
        differences needs it).

    Returns
    -------
    Estimate
        The noise's standard deviation [m] with its interval.
    """
    from scipy.special import log_ndtr
    r = y - xm
    if offs is not None:
        white = _noise_white(r, offs, delta, z)
        if q <= 0:
            return white
        if white.value >= 2.0 * q:
            # a noise of at least twice the quantum: the quantiser's error is then
            # uniform, white, of variance q^2/12 and independent of the signal to a
            # relative 1e-8 (B. Widrow & I. Kollar, *Quantization Noise*, Cambridge 2008,
            # Sec. 5.2 and 11.1: Gaussian input, sigma >= q), so the second differences'
            # estimate holds, less that variance in quadrature. The likelihood below
            # reads the residual, from which the fitted stretch states took a share of
            # the noise: 8 of 480 blind devices' noise intervals fell below their truths
            # (e.g. 25.7 um against [20.3, 25.6], a 5.4 um quantum)
            c = q * q / 12.0
            return Estimate(math.sqrt(max(white.value ** 2 - c, 0.0)),
                            math.sqrt(max(white.lo ** 2 - c, 0.0)), white.hi, "m")
    crit = 0.5 * chi2_ppf_1(LEVEL)
    floor2 = delta ** 2 + POSITION_FLOOR ** 2
    if q > 0:
        def loglik(sig):
            s = np.sqrt(sig * sig + floor2)
            hi = (r + q / 2) / s
            lo = (r - q / 2) / s
            # log(Phi(hi) - Phi(lo)) computed stably
            la, lb = log_ndtr(hi), log_ndtr(lo)
            return float(np.sum(la + np.log1p(-np.exp(np.minimum(lb - la, -1e-300)))))
    else:
        ss = float(np.sum(r * r)) * r.size / max(r.size - dof, 1)
        n = r.size

        def loglik(sig):
            s2 = sig * sig + floor2
            return -0.5 * (ss / s2 + n * math.log(s2))
    with np.errstate(divide="ignore", invalid="ignore"):
        return _noise_interval(loglik, r, crit)


def _noise_interval(loglik, r, crit):
    from scipy.optimize import brentq, minimize_scalar
    top = max(1e-6, 20.0 * float(np.std(r)) + 1e-9)
    res = minimize_scalar(lambda ls: -loglik(math.exp(ls)), bounds=(math.log(1e-11),
                          math.log(top)), method="bounded", options={"xatol": 1e-6})
    s_hat = math.exp(res.x)
    l_hat = -res.fun
    if loglik(0.0) > l_hat:
        s_hat, l_hat = 0.0, loglik(0.0)

    def g(sig):
        return loglik(sig) - (l_hat - crit)
    lo = 0.0 if g(0.0) >= 0 else brentq(g, 0.0, max(s_hat, 1e-12), xtol=1e-13)
    hi = brentq(g, max(s_hat, 1e-12), top * 10, xtol=1e-13) if g(top * 10) < 0 else top * 10
    return Estimate(float(s_hat), float(lo), float(hi), "m")


#: A mass interval wider than this ratio hi / lo is "not identified".
MASS_SPAN = 100.0
#: Replicates of the quantised record (:func:`grid_replicates`).
REPLICATES = 24


def grid_replicates(mod, ym, theta, q, sigma, reps=REPLICATES, seed=0):
    """Estimates from records the fitted model would give through the same encoder.

    A quantiser's error is a deterministic, bounded function of the true position: on a
    slow motion it is a sawtooth correlated over many samples, and its effect on the
    estimates is neither white nor, on a record of few counts, small or unbiased (the
    estimator is nonlinear in the data). Its only unknown is where the grid lies relative
    to the motion. So the fitted model's positions ``ym`` (stretch states, forces and all)
    are passed ``reps`` times through the encoder with a random grid phase ``U(-q/2,
    q/2)`` after Gaussian noise ``sigma`` (the model of the module notes), and refitted
    exactly as the record was (same stretches, hold and delay, the variable projection
    from ``theta``, then the nonlinear refinement): a parametric bootstrap (B. Efron &
    R. Tibshirani, *An Introduction to the Bootstrap*, 1993, Sec. 6.5 and 10.2 for the
    bias). The spread and mean shift of the replicates are the quantisation's effect on
    the estimates at the fitted device.

    Parameters
    ----------
    mod : _Stretched
        The chosen candidate's model (its stretches, hold, applied force).
    ym : ndarray, shape (n_s,)
        The fitted model's positions on the stretches [m].
    theta : ndarray, shape (k,)
        Fitted ``(ln m, b0[, fc+, fc-])``.
    q, sigma : float
        Encoder quantum [m] (> 0) and noise standard deviation [m].
    reps : int
        Replicates.
    seed : int
        Seed of the grid phases and noise (the fit is deterministic).

    Returns
    -------
    ndarray, shape (r, k)
        The replicates' estimates (``r <= reps``: those whose fit converged).
    """
    rng = np.random.default_rng(seed)
    st = (mod.starts, mod.ends, mod.dirs)
    out = []
    y = mod.x.copy()
    for _ in range(reps):
        ph = rng.uniform(-0.5, 0.5)
        e = sigma * rng.standard_normal(ym.size) if sigma > 0 else 0.0
        y[mod.idx] = q * (np.round((ym + e) / q + ph) - ph)
        m2, res = fit_stretched(y, mod.u, mod.T, mod.hold, st, [theta[:2]], mod.frac)
        if res is None:
            continue
        th = None
        if mod.coulomb:
            ref = refine(m2, res.x)
            if ref is not None and ref[4] < res.cost:
                th = ref[1]
        if th is None:
            th = m2.full(res.x)[1]
        if np.all(np.isfinite(th)):
            out.append(np.asarray(th, float)[:theta.size])
    return np.array(out).reshape(-1, theta.size)

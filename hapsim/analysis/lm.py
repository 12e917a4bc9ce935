"""Levenberg-Marquardt as ``scipy.optimize.least_squares(method="lm")`` runs it, without its
per-evaluation bookkeeping: the device fit's searches (:mod:`hapsim.analysis.
device_fit_search`) and the felt pair's variable projection (:mod:`hapsim.analysis.
identify`) call it thousands of times a run."""

from __future__ import annotations

import numpy as np

__all__ = ["levenberg_marquardt"]


def levenberg_marquardt(fun, jac, p0, *, tol, max_nfev):
    """``scipy.optimize.least_squares(fun, p0, jac=jac, method="lm", x_scale="jac",
    ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev)``'s ``x``, ``cost`` and ``fun``, bit
    for bit, without its wrapping (its ``VectorFunction`` set-up was ~half of a variable
    projection fit's time): the same MINPACK ``lmder`` call (J. J. More, *The
    Levenberg-Marquardt algorithm*, Lecture Notes in Mathematics 630, 1978) with the same
    arguments, through the public :func:`scipy.optimize.leastsq` (``diag`` None: the
    Jacobian's column norms, ``factor`` 100), and least_squares' refusals before it.

    Parameters
    ----------
    fun : callable
        ``fun(p) -> ndarray, shape (m,)``, the residual.
    jac : callable
        ``jac(p) -> ndarray, shape (m, n)``.
    p0 : array_like, shape (n,)
        Start.
    tol : float
        ``ftol = xtol = gtol`` (above machine epsilon).
    max_nfev : int
        Residual evaluations allowed.

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x``, ``cost`` (half the residual's sum of squares), ``fun`` (the residual at
        ``x``), ``nfev``.

    Raises
    ------
    ValueError
        As least_squares: a start with NaN, a residual not finite at the start, fewer
        residuals than parameters.
    """
    from scipy.optimize import OptimizeResult, leastsq
    x0 = np.atleast_1d(p0).astype(float)
    if not np.all((x0 >= -np.inf) & (x0 <= np.inf)):
        raise ValueError("Initial guess is outside of provided bounds")
    f0 = np.atleast_1d(fun(x0))
    if not np.all(np.isfinite(f0)):
        raise ValueError("Residuals are not finite in the initial point.")
    if f0.size < x0.size:
        raise ValueError("Method 'lm' doesn't work when the number of residuals is less "
                         "than the number of variables.")
    x, _, info, _, _ = leastsq(fun, x0, Dfun=jac, full_output=True, col_deriv=False,
                               ftol=tol, xtol=tol, gtol=tol, maxfev=max_nfev, factor=100.0,
                               diag=None)
    f = info["fvec"]
    return OptimizeResult(x=x, cost=0.5 * np.dot(f, f), fun=f, nfev=info["nfev"])

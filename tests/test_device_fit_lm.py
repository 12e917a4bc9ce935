"""The variable projection's Levenberg-Marquardt (hapsim.analysis.device_fit_search.
levenberg_marquardt: MINPACK's lmder through the public scipy.optimize.leastsq, issue 31
item 2) is ``least_squares(method="lm", x_scale="jac")`` bit for bit, and refuses what it
refuses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

pytestmark = pytest.mark.numerical
@pytest.mark.parametrize("seed,m,start", [(12, 200, (0.0, 0.5)), (13, 40, (-2.0, 3.0)),
                                          (14, 500, (1.5, 0.01))])
def test_the_variable_projections_lm_is_least_squares_lm_bit_for_bit(seed, m, start):
    """fit_stretched's Levenberg-Marquardt (MINPACK through scipy.optimize.leastsq) against
    ``least_squares(method="lm", x_scale="jac")`` with its tolerances and budget: the
    same point, cost, residual and evaluations."""
    from hapsim.analysis.device_fit_search import _ForwardDifference, levenberg_marquardt
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 4.0, m))
    data = np.exp(-0.7 * t) * np.cos(2.3 * t) + rng.normal(0.0, 0.05, m)

    def f(p):
        return np.exp(-p[1] * t) * np.cos(np.exp(p[0]) * t) - data
    for tol, nfev in ((1e-11, 200), (1e-11, 4)):
        jac_a = _ForwardDifference(f)
        a = least_squares(jac_a.fun, np.asarray(start, float), jac=jac_a, method="lm",
                          x_scale="jac", ftol=tol, xtol=tol, gtol=tol, max_nfev=nfev)
        jac_b = _ForwardDifference(f)
        b = levenberg_marquardt(jac_b.fun, jac_b, start, tol=tol, max_nfev=nfev)
        assert np.array_equal(a.x, b.x) and a.cost == b.cost, (a.x, b.x)
        assert np.array_equal(a.fun, b.fun) and a.nfev == b.nfev


def test_the_lm_refuses_what_least_squares_refuses():
    """A start with NaN, a residual not finite at the start, fewer residuals than
    parameters: ValueError from both."""
    from hapsim.analysis.device_fit_search import _ForwardDifference, levenberg_marquardt

    def f(p):
        return np.array([p[0] - 1.0, p[1] + 2.0, 1.0 / p[0]])

    def short(p):
        return np.array([p[0] + p[1]])
    for fun, start in ((f, (np.nan, 1.0)), (f, (0.0, 1.0)), (short, (1.0, 1.0))):
        with np.errstate(divide="ignore", invalid="ignore"):
            jac = _ForwardDifference(fun)
            with pytest.raises(ValueError):
                least_squares(jac.fun, np.asarray(start, float), jac=jac, method="lm")
            with pytest.raises(ValueError):
                levenberg_marquardt(jac.fun, jac, start, tol=1e-11, max_nfev=200)

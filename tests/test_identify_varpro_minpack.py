"""The felt pair's variable projection calls MINPACK's lmder through ``scipy.optimize.
leastsq`` (hapsim.analysis.identify._varpro), as ``least_squares(method="lm",
x_scale="jac")`` calls it, without the bookkeeping ``least_squares`` wraps round every
evaluation: the same iterates, so the same poles and cost bit for bit, and the same
fallback to the starting poles where ``least_squares`` refuses (fewer residuals than
poles, residuals not finite at the start) or an evaluation raises."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from hapsim.analysis import identify as idf


def _reference(spec, y, offset, lens=None):
    """_varpro as it was: scipy's least_squares."""
    theta0 = idf._theta(spec)
    scale = float(np.max(np.abs(y))) or 1.0
    ys = np.ascontiguousarray(np.asarray(y, dtype=float) / scale)
    layout = idf._layout(spec, ys.size, lens)

    def res(th):
        return idf._compiled("residual", spec, th, ys, offset, layout=layout)

    def jac(th):
        return idf._compiled("jacobian", spec, th, ys, offset, layout=layout)

    try:
        th = least_squares(res, theta0, jac=jac, method="lm", x_scale="jac", xtol=1e-14,
                           ftol=1e-14, gtol=1e-14, max_nfev=200 * (theta0.size + 1)).x
    except (ValueError, np.linalg.LinAlgError):
        th = theta0
    out = idf._spec_at(spec, th)
    return out, float(np.sum(res(idf._theta(out)) ** 2)) * scale * scale


def _problem(rng):
    """A record of 1-3 damped pairs and 0-2 real poles, noisy, in 1-3 stretches, and
    starting poles off the true ones by a few per cent."""
    n = int(rng.integers(80, 400))
    spec_true, spec0 = [], []
    for _ in range(int(rng.integers(1, 4))):
        a, w = float(rng.uniform(0.002, 0.08)), float(rng.uniform(0.05, 1.2))
        spec_true.append(["pair", a, w])
        spec0.append(["pair", a * float(rng.uniform(0.7, 1.3)),
                      w * float(rng.uniform(0.97, 1.03))])
    for _ in range(int(rng.integers(0, 3))):
        p = float(rng.uniform(0.2, 0.9))
        spec_true.append(["real", p])
        spec0.append(["real", p * float(rng.uniform(0.95, 1.05))])
    offset = bool(rng.integers(0, 2))
    k = int(rng.integers(1, 4))
    cuts = np.sort(rng.choice(np.arange(30, n - 30), size=k - 1, replace=False)) if k > 1 \
        else np.zeros(0, int)
    lens = np.diff(np.concatenate([[0], cuts, [n]])).tolist()
    ys = []
    for L in lens:
        phi, _ = idf._basis(spec_true, idf._theta(spec_true), L, offset, derivatives=False)
        ys.append(phi @ rng.standard_normal(phi.shape[1]))
    y = np.concatenate(ys) * float(10.0 ** rng.uniform(-5, 0))
    y = y + float(rng.uniform(0, 0.02)) * np.std(y) * rng.standard_normal(n)
    return spec0, y, offset, (lens if k > 1 else None)


def _same(a, b) -> bool:
    (sa, ca), (sb, cb) = a, b
    flat = [(u, v) for x, z in zip(sa, sb) for u, v in zip(x, z)]
    return len(sa) == len(sb) and all(
        (u == v if isinstance(u, str) else float(u).hex() == float(v).hex())
        for u, v in flat) and float(ca).hex() == float(cb).hex()


@pytest.mark.parametrize("seed", range(4))
def test_random_fits_are_least_squares_own_bit_for_bit(seed):
    """60 random records a seed: poles and cost equal to least_squares' to the bit."""
    rng = np.random.default_rng(seed)
    for _ in range(60):
        spec0, y, offset, lens = _problem(rng)
        assert _same(idf._varpro(spec0, y, offset, lens),
                     _reference(spec0, y, offset, lens)), (spec0, offset, lens)


def _outcome(f, *args):
    """What a fit gives: its poles and cost, or the exception's type."""
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return f(*args)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return type(exc)


def test_the_refusals_end_as_least_squares_ended():
    """Fewer samples than poles, a record not finite, a starting pole that overflows the
    columns (the compiled residual raises): the same poles and cost as with
    least_squares, or the same error."""
    rng = np.random.default_rng(5)
    spec0, y, offset, lens = _problem(rng)
    bad = y.copy()
    bad[7] = np.nan
    cases = [([["pair", 0.01, 0.3], ["pair", 0.02, 0.6], ["real", 0.5]], y[:3], False, None),
             (spec0, bad, offset, lens),
             ([["pair", -5.0, 0.3]], np.sin(0.3 * np.arange(400.0)), False, None)]
    for case in cases:
        got, ref = _outcome(idf._varpro, *case), _outcome(_reference, *case)
        assert (got is ref) if isinstance(ref, type) else _same(got, ref), (case[0], got, ref)

"""The variable projection's residual and Jacobian in closed form, compiled
(hapsim.kernels.varpro.projected through hapsim.analysis.identify._compiled; issue 31 item 2:
string.yaml's felt-pair fit formed the Jacobian by finite differences, one least squares
per parameter, 26 CPU-s a fit) against an independent derivative: the complex step
(Squire & Trapp, "Using complex variables to estimate derivatives of real functions", SIAM
Review 40(1), 1998) of the projected residual written here from its definition, the model's
columns evaluated at complex parameters and the linear coefficients from the normal
equations (an analytic function of the parameters, which an SVD is not). A complex step
``h = 1e-30`` has no cancellation: its error is the residual's own round-off, not a
truncation."""

from __future__ import annotations

import numpy as np
import pytest

import hapsim.analysis.identify as ident
from tolerance import rel_tol


def _record(rng, pairs, n, real=None, offset=0.0):
    """A noisy record of ``pairs`` damped oscillations (and a real pole, an offset) and a
    start a little off its modes: the residual at the start is far from zero, where the
    second term of the Jacobian matters."""
    t = np.arange(n, dtype=float)
    y = np.full(n, offset)
    spec = []
    for _ in range(pairs):
        a, w = rng.uniform(0.002, 0.02), rng.uniform(0.05, 2.5)
        y += rng.normal() * np.exp(-a * t) * np.cos(w * t + rng.uniform(0, 6.3))
        spec.append(["pair", a * (1 + 0.05 * rng.normal()), w * (1 + 0.002 * rng.normal())])
    if real is not None:
        y += 0.5 * real ** t
        spec.append(["real", real * 0.99])
    return y + 1e-4 * rng.standard_normal(n), spec


def _residual(spec, theta, y, offset, lens):
    """``Phi c - y`` per stretch, ``c`` from ``Phi^T Phi c = Phi^T y`` (plain transposes:
    analytic in complex ``theta``)."""
    out, start = [], 0
    for L in (lens or [y.size]):
        yb = y[start:start + L]
        start += L
        t = np.arange(L, dtype=float)
        cols, i = [], 0
        for kind, *_ in spec:
            if kind == "pair":
                a, w = theta[i], theta[i + 1]
                cols += [np.exp(-a * t) * np.cos(w * t), np.exp(-a * t) * np.sin(w * t)]
                i += 2
            else:
                cols.append(theta[i] ** t)
                i += 1
        if offset:
            cols.append(np.ones(L))
        phi = np.column_stack(cols)
        c = np.linalg.solve(phi.T @ phi, phi.T @ yb)
        out.append(phi @ c - yb)
    return np.concatenate(out)


CASES = [
    {"pairs": 6, "n": 600},
    {"pairs": 4, "n": 500, "lens": [180, 170, 150]},
    {"pairs": 3, "n": 400, "real": 0.97, "offset": 0.3},
]


@pytest.mark.parametrize("case", CASES)
def test_jacobian_is_the_complex_step_derivative(case):
    rng = np.random.default_rng(31)
    y, spec = _record(rng, case["pairs"], case["n"], case.get("real"), case.get("offset", 0.0))
    offset, lens = "offset" in case, case.get("lens")
    theta = ident._theta(spec)
    J = ident._compiled("jacobian", spec, theta, y, offset, lens)
    assert J.shape == (y.size, theta.size)
    h = 1e-30
    Jcs = np.empty_like(J)
    for k in range(theta.size):
        th = theta.astype(complex)
        th[k] += 1j * h
        Jcs[:, k] = _residual(spec, th, y, offset, lens).imag / h
    # the residual the Jacobian belongs to is the one the fit minimises
    r = ident._compiled("residual", spec, theta, y, offset, lens)
    r_np = ident._solve(spec, theta, y, offset, lens, derivatives=False)[1]   # numpy's
    r_ne = _residual(spec, theta.astype(complex), y, offset, lens).real
    # forward error <= condition x backward error (Higham Sec. 1.6): the normal equations
    # solve with the basis' condition squared (Higham Sec. 20.4), every entry an inner
    # product over a stretch's rows; the SVD's share (condition to the first power) is less
    cond = max(np.linalg.cond(ident._solve(spec, theta, y[a:b], offset)[0][0][0])
               for a, b in ident._bounds(y.size, lens))
    tol = rel_tol(y.size, cond * cond)
    assert np.linalg.norm(J - Jcs) <= tol * np.linalg.norm(Jcs), (cond, tol)
    assert np.linalg.norm(r - r_ne) <= tol * np.linalg.norm(y), (cond, tol)
    assert np.linalg.norm(r - r_np) <= tol * np.linalg.norm(y), (cond, tol)
    # the test can tell: Kaufman's approximation (the first term alone) is off here,
    # where the start leaves a residual
    kaufman = []
    for (a, b) in ident._bounds(y.size, lens):
        blocks, _ = ident._solve(spec, theta, y[a:b], offset)
        phi, dcols, c = blocks[0]
        Dc = np.column_stack([sum(c[col] * d for col, d in parts) for parts in dcols])
        kaufman.append(Dc - phi @ np.linalg.lstsq(phi, Dc, rcond=None)[0])
    off = np.linalg.norm(np.concatenate(kaufman) - Jcs) / np.linalg.norm(Jcs)
    assert off > 1e3 * tol, (off, tol)


def test_a_record_that_is_not_finite_is_refused_as_lstsq_refuses_it():
    """A column past the float range (a pole far outside the unit circle) or a record
    with a NaN: LinAlgError, as numpy.linalg.lstsq raises (the fit then keeps its start)."""
    rng = np.random.default_rng(5)
    y, spec = _record(rng, 1, 200)
    theta = ident._theta(spec)
    for which in ("residual", "jacobian"):
        with pytest.raises(np.linalg.LinAlgError):
            ident._compiled(which, spec, np.array([-5.0, theta[1]]), y, False)
        bad = y.copy()
        bad[7] = np.nan
        with pytest.raises(np.linalg.LinAlgError):
            ident._compiled(which, spec, theta, bad, False)

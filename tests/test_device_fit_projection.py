"""The device fit's variable projection in one compiled call
(:func:`hapsim.kernels.device_sim.stretch_projection`, behind
``hapsim.analysis.device_fit_search._Stretched._solve``; issue 31 item 2: the numpy
projection it replaced cost ~40 calls on ~1000 rows at each of a fit's ~630 evaluations,
ten times the compiled one) is the same least squares as that numpy one, written again here
as the reference: the stretch states by ``[1, g]`` per stretch, the Coulomb frictions by
``numpy.linalg.lstsq`` (SVD) on the projected columns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.analysis.device_fit_search import _Stretched
from hapsim.analysis.device_fit_stretches import moving_stretches
from hapsim.kernels.device_sim import simulate_device, stretch_basis
from tolerance import measured


def _reference(mod, lm, b0):
    """The numpy variable projection (the implementation before the compiled one):
    ``(r, phi, cx, cv)``."""
    n = mod.x.size
    yu, g, c = np.zeros(n), np.zeros(n), np.zeros(n)
    stretch_basis(mod.u, mod.starts, mod.ends, math.exp(lm), b0, mod.T, mod.hold, yu, g, c,
                  mod.frac)
    i, off, sid = mod.idx, mod.offs, mod.sid
    g, yu, c = g[i], yu[i], c[i]
    t = mod.x[i] - yu
    L = np.add.reduceat(np.ones(i.size), off)
    Sg = np.add.reduceat(g, off)
    Sgg = np.add.reduceat(g * g, off)
    det = L * Sgg - Sg * Sg

    def project(z):
        Sz = np.add.reduceat(z, off)
        Sgz = np.add.reduceat(g * z, off)
        cx = (Sgg * Sz - Sg * Sgz) / det
        cv = (L * Sgz - Sg * Sz) / det
        return z - cx[sid] - cv[sid] * g, cx, cv
    phi = np.zeros(2)
    if mod.coulomb:
        d = mod.dirs[sid]
        cols = [np.where(d > 0, -c, 0.0), np.where(d < 0, c, 0.0)]
        P = np.column_stack([project(z)[0] for z in cols])
        used = [k for k in range(2) if np.any(P[:, k])]
        phi[used] = np.linalg.lstsq(P[:, used], project(t)[0], rcond=None)[0]
        t = t - cols[0] * phi[0] - cols[1] * phi[1]
    r, cx, cv = project(t)
    return r, phi, cx, cv


def _record(seed, hold, frac, one_way=False):
    """A device's positions under a random held force (m, b0, Coulomb friction, noise),
    its moving stretches and the model of them."""
    rng = np.random.default_rng(seed)
    n, T = 2000, 1e-3
    m, b0 = float(np.exp(rng.uniform(math.log(0.02), 0.0))), float(rng.uniform(0.0, 5.0))
    fc = float(rng.uniform(0.05, 0.3))
    u = np.repeat(rng.choice([-1.0, 1.0], n // 50), 50) * 2.0 + rng.normal(0, 0.3, n)
    if one_way:
        u = np.where(u > 0.0, u, 0.0)            # pushes + and rests: fc- has no column
    x = np.zeros(n)
    simulate_device(u, m, b0, fc, fc, np.array([0]), np.array([n]), np.zeros(1),
                    np.zeros(1), T, hold, x, frac)
    x += rng.normal(0.0, 1e-6, n)
    st = moving_stretches(x, 0.0)
    return _Stretched(x, u, T, hold, st, frac), (math.log(m), b0)


@pytest.mark.parametrize("seed,hold,frac,one_way", [(1, 0, 0.0, False), (2, 0, 0.3, False),
                                                    (3, 1, 0.0, False), (4, 0, 0.0, True)])
def test_the_compiled_projection_is_the_numpy_least_squares(seed, hold, frac, one_way):
    """At the device's parameters and 20 points around them (mass x/÷ 3, b0 +- 2 N s/m):
    the residual, the stretch states and the Coulomb frictions of both. The tolerances are
    the largest differences measured (this test's ``_record`` and points for
    seeds 1-4 and 10-39, holds, fractions and one-way records alternating, 34 records x 21
    points; this machine, numpy 2.4 with its OpenBLAS; the compiled normal equations of
    ``[1, g]`` per stretch by Cramer's rule and sequential sums, against reduceat's pairwise
    sums and LAPACK's SVD): 2.3e-12 of max |x| (residual; the heavily damped points, where
    ``g`` is nearly constant on a stretch and ``[1, g]`` ill-conditioned), 1.2e-11 and
    1.7e-10 relative (initial positions, velocities), 6.8e-13 relative (frictions); a
    margin of 100 keeps them bounds for another summation order or BLAS, while a wrong
    formula (a column's sign, a stretch's rows, a dropped column) moves them by percents."""
    mod, (lm0, b00) = _record(seed, hold, frac, one_way)
    assert mod.starts.size >= (1 if one_way else 5) and mod.coulomb == (hold == 0)
    rng = np.random.default_rng(seed + 100)
    pts = [(lm0, b00)] + [(lm0 + rng.uniform(-1.1, 1.1), max(b00 + rng.uniform(-2, 2), 0.0))
                          for _ in range(20)]
    scale = float(np.max(np.abs(mod.x)))
    for lm, b0 in pts:
        r, phi, cx, cv = mod._solve(lm, b0)
        assert r is not mod._bad, (lm, b0)        # inside the physical range
        r0, phi0, cx0, cv0 = _reference(mod, lm, b0)
        assert np.max(np.abs(r - r0)) <= measured(2.3e-12, 100) * scale, (lm, b0)
        assert np.allclose(cx, cx0, rtol=measured(1.2e-11, 100), atol=0.0), (lm, b0)
        assert np.allclose(cv, cv0, rtol=measured(1.7e-10, 100), atol=0.0), (lm, b0)
        assert np.allclose(phi, phi0, rtol=measured(6.8e-13, 100), atol=0.0), (lm, b0)
        assert np.array_equal(phi == 0.0, phi0 == 0.0), (lm, b0, phi, phi0)
        if one_way:
            assert phi[1] == 0.0                   # no stretch moving -: no fc- column
    # at the truth the residual is the noise's: the model and its frictions found
    r, phi, _, _ = mod._solve(lm0, b00)
    assert np.sqrt(np.mean(r * r)) < 2e-6


def test_outside_the_physical_range_the_residual_is_the_bad_one():
    """A mass outside 1e-6 .. 1e6 kg, a non-finite b0, or a b0 whose basis would grow past
    e^50 over the longest stretch: 1 m per sample (the optimiser steps back), and zeros."""
    mod, (lm0, b00) = _record(5, 0, 0.0)
    for lm, b0 in [(math.log(1e-7), b00), (math.log(2e6), b00), (lm0, math.nan),
                   (lm0, -1e9)]:
        r, phi, cx, cv = mod._solve(lm, b0)
        assert np.array_equal(r, np.ones(mod.idx.size)) and not phi.any()
        assert not cx.any() and not cv.any()


@pytest.mark.parametrize("seed,hold,frac", [(6, 0, 0.0), (7, 1, 0.0), (8, 0, 0.6)])
def test_the_forward_difference_is_scipys_bit_for_bit(seed, hold, frac):
    """``_ForwardDifference`` (the variable projection's Jacobian without scipy's wrapping)
    forms scipy's ``approx_derivative(..., method='2-point')`` numbers bit for bit, at
    points of both signs and at 0 (scipy's step sign 1 there); and Levenberg-Marquardt with
    it ends where ``jac='2-point'`` ends, bit for bit, from the same starts."""
    from scipy.optimize import least_squares
    from scipy.optimize._numdiff import approx_derivative

    from hapsim.analysis.device_fit_search import _ForwardDifference
    mod, (lm0, b00) = _record(seed, hold, frac)
    for p in [(lm0, b00), (lm0 + 0.3, 0.0), (-0.2, -b00 * 1e-3), (0.0, b00 + 1.0)]:
        p = np.array(p)
        ref = approx_derivative(mod.residual, p, method="2-point")
        jac = _ForwardDifference(mod.residual)
        assert np.array_equal(jac(p), ref)                   # f(p) evaluated
        jac.fun(p)
        assert np.array_equal(jac(p), ref)                   # f(p) remembered
    for p0 in [(lm0 + 0.5, 1.0), (lm0 - 0.7, 0.1)]:
        kw = dict(method="lm", x_scale="jac", xtol=1e-11, ftol=1e-11, gtol=1e-11,
                  max_nfev=200)
        a = least_squares(mod.residual, np.array(p0), **kw)
        jac = _ForwardDifference(mod.residual)
        b = least_squares(jac.fun, np.array(p0), jac=jac, **kw)
        assert np.array_equal(a.x, b.x) and a.cost == b.cost and np.array_equal(a.jac, b.jac)
        # it found the device: ln m within measured(7.0e-4, 70) of the truth (7.0e-4
        # the worst of these six fits, 1 um of noise; margin 70, 5 % of the mass: the
        # check is that it converged to the device, not to another stationary point)
        assert abs(b.x[0] - lm0) < measured(7.0e-4, 70)

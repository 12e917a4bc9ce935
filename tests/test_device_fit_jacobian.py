"""The refinement's Jacobian (hapsim.analysis.device_fit_search._BlockDifference, issue 31 item 2:
scipy's sparse finite difference spent two thirds of ``hapsim identify``'s fit indexing its
sparsity pattern again at every call) is scipy's own, bit for bit: the same entries in the
same CSR layout as ``approx_derivative(..., sparsity=S)``, and ``least_squares`` ends at the
same point with either, on residuals with the refinement's structure (shared parameters in
every row, two per stretch in its rows only)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative
from scipy.sparse import csr_array, lil_matrix

from hapsim.analysis.device_fit_search import _BlockDifference


def _problem(seed, k, ns, m):
    """A residual of the refinement's structure: row r depends on the k shared parameters
    and on its stretch's two (``k + sid[r]``, ``k + ns + sid[r]``) only."""
    rng = np.random.default_rng(seed)
    sid = np.sort(rng.integers(0, ns, m))
    sid[:ns] = np.arange(ns)                  # every stretch has rows
    sid.sort()
    t = rng.uniform(0.0, 3.0, m)
    data = rng.normal(size=m)

    def f(p):
        a = np.exp(-p[1] * t) * np.cos(p[0] * t)
        extra = p[2] * np.tanh(t) if k > 2 else 0.0
        return a + extra + p[k + sid] + p[k + ns + sid] * t - data

    S = lil_matrix((m, k + 2 * ns), dtype=int)
    S[:, :k] = 1
    rows = np.arange(m)
    S[rows, k + sid] = 1
    S[rows, k + ns + sid] = 1
    p0 = rng.normal(size=k + 2 * ns) * 2.0
    p0[0] = 0.0                      # scipy's step at 0 (sign 1) and at negative values
    p0[1] = abs(p0[1]) + 0.1
    return f, S, sid, p0


@pytest.mark.parametrize("seed,k,ns,m", [(1, 4, 7, 300), (2, 2, 1, 50), (3, 3, 20, 400)])
def test_the_jacobian_is_scipys_sparse_difference_bit_for_bit(seed, k, ns, m):
    f, S, sid, p0 = _problem(seed, k, ns, m)
    ref = csr_array(approx_derivative(f, p0, method="2-point", sparsity=S))
    got = _BlockDifference(f, k, sid, ns)(p0)
    assert got.shape == ref.shape
    assert np.array_equal(got.indptr, ref.indptr)
    assert np.array_equal(got.indices, ref.indices)
    assert np.array_equal(got.data, ref.data)


@pytest.mark.parametrize("seed,k,ns,m", [(4, 4, 6, 240), (5, 2, 3, 90)])
def test_least_squares_ends_at_the_same_point_bit_for_bit(seed, k, ns, m):
    """The refinement's call (trf, x_scale='jac', its tolerances and evaluation budget)
    with scipy's sparse difference and with the block difference."""
    f, S, sid, p0 = _problem(seed, k, ns, m)
    opts = dict(method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=60)
    a = least_squares(f, p0, jac_sparsity=S, **opts)
    jac = _BlockDifference(f, k, sid, ns)
    b = least_squares(jac.fun, p0, jac=jac, **opts)
    assert a.nfev == b.nfev and a.status == b.status
    assert np.array_equal(a.x, b.x) and a.cost == b.cost
    assert np.array_equal(a.jac.toarray(), b.jac.toarray())


@pytest.mark.parametrize("seed,k,ns,m", [(1, 4, 7, 300), (2, 2, 1, 50), (3, 3, 20, 400)])
def test_the_dense_jacobian_holds_the_sparse_ones_entries_bit_for_bit(seed, k, ns, m):
    """The refinement's dense path (up to DENSE_JACOBIAN_MAX entries, scipy's "exact"
    trust-region solver) gets the very entries of the sparse one, zeros elsewhere: scipy's
    own dense 2-point difference, which steps each column alone, bit for bit. (The
    solver's answers on the refinement's records are tested against the devices' truths:
    tests/test_identify.py's blind identification.)"""
    f, S, sid, p0 = _problem(seed, k, ns, m)
    jac = _BlockDifference(f, k, sid, ns)
    assert np.array_equal(jac.dense(p0), jac(p0).toarray())
    assert np.array_equal(jac.dense(p0), approx_derivative(f, p0, method="2-point"))


def test_the_fit_quantiles_are_scipy_stats_own_bit_for_bit():
    """The device fit takes its quantiles from scipy.special (hapsim.analysis.device_fit:
    ``scipy.stats`` costs ~1 CPU-s to import in each process that fits): the same numbers
    as ``scipy.stats``' ``chi2.ppf(p, 1)``, ``norm.ppf`` and ``t.ppf``, at the fit's level
    and at other probabilities."""
    from scipy.special import ndtri, stdtrit
    from scipy.stats import chi2, norm, t

    from hapsim.analysis.device_fit import LEVEL
    from hapsim.analysis.device_fit_intervals import REPLICATES, chi2_ppf_1
    for p in (LEVEL, 0.5, 0.9, 0.95, 0.99, 1e-6, 1 - 1e-9):
        assert chi2_ppf_1(p) == float(chi2.ppf(p, 1)), p
        q = 0.5 + p / 2
        assert float(ndtri(q)) == float(norm.ppf(q)), p
        for df in (max(REPLICATES - 1, 1), 1, 7):
            assert float(stdtrit(df, q)) == float(t.ppf(q, df)), (p, df)


@pytest.mark.parametrize("hold,frac,q", [(0, 0.0, 0.0), (0, 0.37, 5e-6), (1, 0.0, 2e-6)])
def test_the_compiled_refinement_jacobian_is_the_block_difference_bit_for_bit(hold, frac, q):
    """refine's Jacobian in one compiled call (device_sim.refine_jacobian) against
    :meth:`_BlockDifference.data` on the refinement's residual itself: a record of the
    device model (Coulomb friction, reversals, a quantiser), at the start and at points
    around it, under the plain and the split zero-order hold and the idealised image."""
    from hapsim.analysis.device_fit_search import (
        _refine_difference, _refine_residual, _Stretched)
    from hapsim.analysis.device_fit_stretches import moving_stretches
    from hapsim.kernels.device_sim import simulate_device
    rng = np.random.default_rng(15 + hold)
    n, T = 1500, 1e-3
    u = np.repeat(rng.uniform(-1.5, 1.5, n // 50), 50) + rng.normal(0.0, 0.1, n)
    x = np.zeros(n)
    simulate_device(u, 0.08, 0.7, 0.15, 0.12, np.array([0]), np.array([n]), np.zeros(1),
                    np.zeros(1), T, hold, x, frac)
    if q:
        x = q * np.round(x / q)
    st = moving_stretches(x, q)
    mod = _Stretched(x, u, T, hold, st, frac)
    k = 4 if mod.coulomb else 2
    ns = mod.starts.size
    assert ns >= 3
    _, phi, cx, cv = mod._solve(np.log(0.08), 0.7)
    p0 = np.concatenate([[np.log(0.08), 0.7], phi if mod.coulomb else [], cx, cv])
    out = np.zeros(n)
    xi = x[mod.idx]
    resid = _refine_residual(mod, out, xi)
    jac = _BlockDifference(resid, k, mod.sid, ns)
    fast = _refine_difference(mod, jac, out, xi)
    for j in range(6):
        p = p0 * (1.0 + 0.01 * rng.normal(size=p0.size)) if j else p0
        if j == 3:
            p[0] = 0.0                              # scipy's step sign at 0
        jac.fun(p)                                   # the remembered residual, as trf's
        a = jac.data(p)
        b = fast(p)
        assert np.array_equal(a, b, equal_nan=True), np.max(np.abs(a - b))

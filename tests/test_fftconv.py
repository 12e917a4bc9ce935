"""hapsim.analysis.fftconv against the direct sum and against scipy.signal.fftconvolve.

The fits' error propagation convolves by FFT without importing ``scipy.signal`` (about 1
CPU-s in every measuring process). Its result must be the full linear convolution: checked
against ``np.convolve`` (the direct sum, an independent computation) with the FFT's rounding
bound, and against scipy's routine, which it replaces in the three places it is called.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import scipy.fft
import scipy.signal

from hapsim.analysis.fftconv import fast_length, fftconvolve
from tolerance import EPS, SAFETY  # same directory (pytest prepend import mode)


def _fft_tol(a, b, n: int) -> float:
    """Rounding bound of an FFT convolution of length ``n``: ``log2(n) eps |a|_2 |b|_2``
    per output, times the forward and inverse transforms' three passes (Higham 2002,
    Sec. 24.1: the FFT's normwise backward error ``O(log2 n) u``), times SAFETY."""
    return SAFETY * 3 * max(math.log2(n), 1.0) * EPS * float(np.linalg.norm(a)) * float(
        np.linalg.norm(b))


def test_fast_length_is_scipys_five_smooth_length():
    """Every length up to 20,000 padded as ``scipy.fft.next_fast_len(n, real=True)``."""
    got = [fast_length(n) for n in range(1, 20001)]
    want = [scipy.fft.next_fast_len(n, real=True) for n in range(1, 20001)]
    assert got == want
    with pytest.raises(ValueError, match="at least 1"):
        fast_length(0)


def test_one_dimensional_full_convolution_is_the_direct_sum():
    """Random lengths 1-2000: the direct sum within the FFT's rounding bound, and scipy's
    ``fftconvolve`` within the same bound (both round; on one machine they agree bit for bit
    today, which this test does not require)."""
    rng = np.random.default_rng(20261124)
    for _ in range(60):
        a = rng.normal(size=int(rng.integers(1, 2000)))
        b = rng.normal(size=int(rng.integers(1, 2000)))
        got = fftconvolve(a, b)
        direct = np.convolve(a, b)
        tol = _fft_tol(a, b, fast_length(a.size + b.size - 1))
        assert got.shape == direct.shape
        assert np.max(np.abs(got - direct)) <= tol
        assert np.max(np.abs(got - scipy.signal.fftconvolve(a, b))) <= 2 * tol


@pytest.mark.parametrize("form", ["columns", "rows"])
def test_convolution_along_one_axis_broadcasts_the_other(form):
    """The two forms the fits use: columns ``(L, p)`` with a response ``(L, 1)`` along
    axis 0 (:func:`hapsim.analysis.identify.measure_felt`'s covariance), rows ``(O, N)``
    with ``(1, L)`` along axis 1 (:mod:`hapsim.analysis.pencil`): each column or row is its
    own direct sum."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        L, M, p = int(rng.integers(1, 600)), int(rng.integers(1, 600)), int(rng.integers(1, 5))
        if form == "columns":
            A, h, ax = rng.normal(size=(L, p)), rng.normal(size=(M, 1)), 0
            direct = np.stack([np.convolve(A[:, j], h[:, 0]) for j in range(p)], axis=1)
        else:
            A, h, ax = rng.normal(size=(p, L)), rng.normal(size=(1, M)), 1
            direct = np.stack([np.convolve(A[j], h[0]) for j in range(p)], axis=0)
        got = fftconvolve(A, h, axes=ax)
        assert got.shape == direct.shape == scipy.signal.fftconvolve(A, h, axes=ax).shape
        assert np.max(np.abs(got - direct)) <= _fft_tol(A, h, fast_length(L + M - 1))


def test_bad_inputs_are_refused_and_empty_ones_are_empty():
    with pytest.raises(ValueError, match="dimensions"):
        fftconvolve(np.ones(3), np.ones((3, 1)))
    with pytest.raises(ValueError, match="broadcast"):
        fftconvolve(np.ones((3, 2)), np.ones((3, 3)), axes=0)
    assert fftconvolve(np.zeros(0), np.ones(3)).size == 0


def test_a_measuring_run_never_imports_scipy_signal_or_sparse():
    """``hapsim run configs/wall.yaml --lockstep`` predicts (the rest position's balance)
    and measures (its error propagation convolves) without importing ``scipy.signal``
    (~1 CPU-s a process) or ``scipy.sparse`` (~0.4 CPU-s; a dense solve for a few
    masses, :func:`hapsim.analysis.virtual_network.rest_position`)."""
    code = ("import sys\nfrom hapsim.cli import main\n"
            "rc = main(['run', 'configs/wall.yaml', '--lockstep', '--duration', '0.5'])\n"
            "assert rc == 0, rc\n"
            "print([m for m in ('scipy.signal', 'scipy.sparse') if m in sys.modules])\n")
    from pathlib import Path
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=str(Path(__file__).resolve().parents[1]), timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout[-500:]


def test_the_unseen_hold_search_correlates_every_row_with_every_kernel():
    """``hapsim.analysis.unseen_holds._correlate`` (one batched FFT for the fit's columns
    and both signatures) against the direct sum ``c[j, r, i] = sum_m R[r, i + m] k_j[m]``
    over ``m < L - i``, kernels shorter and longer than the rows, one row and a matrix of
    rows, within the FFT's rounding bound (above); no rows: zeros of the right shape."""
    from hapsim.analysis.unseen_holds import _correlate
    rng = np.random.default_rng(5)
    L = 97
    R = rng.standard_normal((4, L))
    ks = (rng.standard_normal(30), rng.standard_normal(150))
    got = _correlate(R, ks)
    assert got.shape == (2, 4, L)
    for j, k in enumerate(ks):
        kk = np.zeros(L)
        kk[:min(L, k.size)] = k[:L]
        for r in range(4):
            want = np.array([np.dot(R[r, i:], kk[:L - i]) for i in range(L)])
            tol = _fft_tol(R[r], kk, fast_length(2 * L - 1))
            assert np.max(np.abs(got[j, r] - want)) <= tol
            one = _correlate(R[r], (k,))
            assert one.shape == (1, L) and np.max(np.abs(one[0] - want)) <= tol
    assert _correlate(np.zeros((0, L)), ks).shape == (2, 0, L)

"""``continuous_poles``: the continuous-time image ``ln(z) / T`` of sampled poles, over the
whole disc (hapsim.analysis.ths.felt; the felt pairs and the rendered poles of every
dimension read it).

Near the unit circle it keeps the damping's relative precision through ``log1p``; deep
inside, where that sum cancels, ``ln|z|`` itself: before, ``|z| = 1e-9`` gave ``-inf``
for ``ln|z| = -20.7`` (with numpy's divide-by-zero warning, in ``test_ports``' delay
lines), and ``z = 0`` a NaN imaginary part. Checked against CPython's ``cmath.log``, an
independent implementation (it takes ``log1p`` near the circle and ``log(hypot)``
elsewhere)."""

from __future__ import annotations

import cmath
import warnings

import numpy as np

from hapsim.analysis.ths.felt import continuous_poles
from tolerance import rel_tol


def test_every_pole_of_the_disc_is_cmaths_log_over_T():
    rng = np.random.default_rng(25)
    T = 1e-3
    # magnitudes from 1e-300 to 1.2 (log-uniform), every angle; the circle's
    # neighbourhood (|z| 0.7-1.2) as densely again
    r = np.concatenate([10.0 ** rng.uniform(-300, 0.08, 3000), rng.uniform(0.7, 1.2, 3000)])
    z = r * np.exp(1j * rng.uniform(-np.pi, np.pi, r.size))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = continuous_poles(z, T)
    ref = np.array([cmath.log(complex(v)) for v in z]) / T
    # each part a few roundings from the exact value on either side (|z|^2 - 1, log1p or
    # log, the division by T; cmath's own): 16 operations' worth, on the part's scale;
    # the real part where the circle's cancellation leaves it (|z| near 1) on |s|'s
    tol = rel_tol(16)
    assert np.all(np.abs(got.imag - ref.imag) <= tol * np.abs(ref.imag))
    scale = np.where(np.abs(r - 1.0) < 0.3, np.abs(ref), np.abs(ref.real))
    assert np.all(np.abs(got.real - ref.real) <= tol * scale)


def test_a_zero_pole_is_minus_infinity_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = continuous_poles(np.array([0j, 0.5 + 0.5j]), 1e-3)
        one = continuous_poles(0j, 1e-3)
    assert s[0] == complex(-np.inf, 0.0) and not np.isnan(s[0].imag)
    assert one == complex(-np.inf, 0.0) and np.ndim(one) == 0

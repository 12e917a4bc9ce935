"""How far the sensor's and the actuator's quantisers may move the felt (k, b): bounds
derived from the two quantisers, nothing fitted (docs/design.md, 'Identification').

Two effects: the describing-function gain of each quantiser on the loop's oscillation
(Gelb & Vander Velde 1968), which moves the virtual (K, B) the device renders, and the
position quantiser's error seen as observation noise by the fit of the free response
(Widrow & Kollar 2008). ``hapsim run``, the emulated Hapkit board and its tests read them.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.identify import pair_noise_sensitivity

__all__ = ["quantiser_gain", "quantiser_gain_bound", "quantisation_bound"]

def quantiser_gain(a: float) -> float:
    """Describing function of a mid-tread (round-to-nearest) quantiser of unit step.

    For an input ``a sin(wt)`` the first harmonic of the output is ``N(a) a sin(wt)`` with
    ``N(a) = 4 / (pi a) * sum_{i=1..n} sqrt(1 - ((2 i - 1) / (2 a))^2)``,
    ``n = floor(a + 1/2)`` (0 below half a step): Gelb & Vander Velde, *Multiple-Input
    Describing Functions and Nonlinear System Design* (1968), the quantiser entry of their
    table of describing functions.

    Parameters
    ----------
    a : float
        Input amplitude in quantiser steps, >= 0.

    Returns
    -------
    float
        N(a), -> 1 as a grows.
    """
    n = int(math.floor(a + 0.5))
    if n <= 0:
        return 0.0
    s = 0.0
    for i in range(1, n + 1):
        u = (2 * i - 1) / (2.0 * a)
        s += math.sqrt(max(0.0, 1.0 - u * u))
    return 4.0 / (math.pi * a) * s


def _max_gain_error(lo: float, hi: float, points: int = 4000) -> float:
    """max |N(a) - 1| over amplitudes a in [lo, hi] steps (dense grid)."""
    return max(abs(quantiser_gain(float(a)) - 1.0) for a in np.linspace(lo, hi, points))


def quantiser_gain_bound(loop, K: float, B: float, a_max: float, a_min: float, q_x: float,
                         q_f: float = 0.0) -> dict:
    """How far the quantisers' loop gain may move the felt (k, b): part 1 of
    :func:`quantisation_bound`.

    The position quantiser (step ``q_x``) passes an oscillation of amplitude A with the
    describing-function gain N(A / q_x), the force quantiser (step ``q_f``, 0: none) the
    force's with N(K A / q_f) (:func:`quantiser_gain`; Gelb & Vander Velde 1968); over the
    amplitudes ``[a_min, a_max]`` of a record the virtual (K, B) act within
    ``(1 +- eps)``, ``eps = (1 + d_x)(1 + d_f) - 1``, ``d`` the largest ``|N - 1|``, and
    the felt (k, b) within the THS map (:func:`hapsim.analysis.ths.render`) of the four
    corners.

    Parameters
    ----------
    loop : hapsim.analysis.loop.LoopModel
        The device side of the THS.
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m].
    a_max, a_min : float
        Largest and smallest oscillation amplitude of the record [m].
    q_x, q_f : float
        Position step [m] and force step [N] (0: that quantiser is absent).

    Returns
    -------
    dict
        ``dk`` [N/m], ``db`` [N s/m], ``eps``, ``d_x``, ``d_f``.
    """
    from hapsim.analysis.ths import render

    pred = render(loop, K, B)
    d_x = _max_gain_error(a_min / q_x, a_max / q_x) if q_x > 0 else 0.0
    d_f = _max_gain_error(K * a_min / q_f, K * a_max / q_f) if q_f > 0 else 0.0
    eps = (1.0 + d_x) * (1.0 + d_f) - 1.0
    if eps == 0.0:
        return {"dk": 0.0, "db": 0.0, "eps": 0.0, "d_x": d_x, "d_f": d_f}
    corners = [render(loop, K * (1 + u), B * (1 + v)) for u in (-eps, eps) for v in (-eps, eps)]
    return {"dk": max(abs(c.k - pred.k) for c in corners),
            "db": max(abs(c.b - pred.b) for c in corners), "eps": eps, "d_x": d_x, "d_f": d_f}


def quantisation_bound(loop, K: float, B: float, x0: float, t_fit: float, q_x: float,
                       q_f: float, n_samples: int, sigmas: float = 4.0) -> dict:
    """How far the ADC and PWM quantisation may move the felt (k, b) from the THS
    prediction, derived from the two quantisers (nothing fitted).

    Two effects, added:

    1. **Loop gain.** Over the fit window the free response is a decaying sinusoid of
       amplitude A from ``x0`` down to ``A_min = x0 exp(-sigma t_fit)`` (sigma = b / 2m of
       the prediction). The position quantiser (step ``q_x``) passes its first harmonic
       with the gain N(A / q_x), the PWM quantiser (step ``q_f``) the force's with
       N(F / q_f), F >= K A (:func:`quantiser_gain`). So the virtual spring and damper act
       with K', B' in ``[K, B] (1 +- eps)``, ``eps = (1 + d_x)(1 + d_f) - 1``, ``d`` the
       largest |N - 1| over the window; the felt (k, b) lie within the THS map
       (:func:`hapsim.analysis.ths.render`) of the four corners (K (1 +- eps), B (1 +- eps)).
    2. **Observation.** The logged positions carry the quantisation error, uniform over one
       step: white noise of variance ``q_x^2 / 12`` (Widrow & Kollar, *Quantization Noise*,
       2008, ch. 4). A least-squares fit of ``A exp(-sigma t) cos(omega t + phi) + c`` to
       ``n_samples`` such samples has the covariance ``q_x^2 / 12 (J^T J)^-1`` (J: the
       model's Jacobian at the predicted parameters); ``sigmas`` standard deviations of
       k = m (omega^2 + sigma^2) and b = 2 m sigma are added.

    Parameters
    ----------
    loop : hapsim.analysis.loop.LoopModel
        The device side of the THS (m, b0, rate, delay, hold).
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m].
    x0 : float
        Initial amplitude of the free response [m].
    t_fit : float
        Length of the fit window [s].
    q_x, q_f : float
        Position step [m] (HELLO.position_scale) and force step [N] (HELLO.force_scale).
    n_samples : int
        Samples in the fit window.
    sigmas : float
        Standard deviations of the observation noise term.

    Returns
    -------
    dict
        ``k``, ``b`` (predicted), ``dk``, ``db`` (the bounds), ``eps``, ``d_x``, ``d_f``,
        ``a_min`` [m], ``k_noise_sd``, ``b_noise_sd``.
    """
    from hapsim.analysis.ths import render

    pred = render(loop, K, B)
    m = loop.mass
    sig = pred.b / (2.0 * m)
    om = math.sqrt(max(pred.k / m - sig * sig, 0.0))
    a_min = x0 * math.exp(-sig * t_fit)
    g = quantiser_gain_bound(loop, K, B, x0, a_min, q_x, q_f)
    eps, d_x, d_f, dk_gain, db_gain = g["eps"], g["d_x"], g["d_f"], g["dk"], g["db"]
    # observation noise through the least-squares fit (the sensitivity of measure_felt's)
    T = loop.period
    y = x0 * np.exp(-sig * T * np.arange(n_samples)) * np.cos(om * T * np.arange(n_samples))
    s_k, s_b = pair_noise_sensitivity(y, T, m, sig, om)
    q_sd = q_x / math.sqrt(12.0)
    k_sd, b_sd = q_sd * s_k, q_sd * s_b
    return {"k": float(pred.k), "b": float(pred.b), "dk": dk_gain + sigmas * k_sd,
            "db": db_gain + sigmas * b_sd, "eps": eps, "d_x": d_x, "d_f": d_f,
            "a_min": a_min, "k_noise_sd": k_sd, "b_noise_sd": b_sd}

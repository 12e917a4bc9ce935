"""measurement.estimated_bounds against the motion it bounds: a device driven by a
zero-order-held force (m x'' + b0 x' + Coulomb = F, solved exactly over each period), its
missing replies stepped through as DriverTransport.estimate does (the position extrapolated
linearly from the last two records, by their seq, which a missing reply between them
leaves two ticks apart), the extrapolation's true error at or below the stated bound at
every estimated row, over random forces and random loss patterns (at most two estimates in
a row, as the host loop allows)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.analysis.measurement import estimated_bounds

FLAG_ESTIMATED = 32


def _free_motion(rng, n, T, m, b0, fc, f_max, v0):
    """Exact samples of m x'' = F_k - b0 x' - c_k under a held F_k, from velocity ``v0``
    [m/s], ``c_k`` the Coulomb force ``fc`` against the motion at the period's start (any
    force of at most ``fc`` is one the bound allows); returns positions (n,) and forces
    (n,)."""
    x, v = 0.0, v0
    xs, fs = np.empty(n), rng.uniform(-f_max, f_max, n)
    for k in range(n):
        xs[k] = x
        f = fs[k] - fc * math.copysign(1.0, v if v != 0.0 else fs[k])
        if b0 > 0:
            vinf = f / b0
            e = math.exp(-b0 * T / m)
            x += vinf * T + (v - vinf) * m / b0 * (1.0 - e)
            v = vinf + (v - vinf) * e
        else:
            x += v * T + 0.5 * f / m * T * T
            v += f / m * T
    return xs, fs


def _lossy_record(rng, xs, p_loss):
    """The loop's record: estimated rows extrapolated from the last two records by seq."""
    n = xs.size
    pos, flags = xs.copy(), np.zeros(n, np.uint8)
    recs = [(0, xs[0]), (1, xs[1])]
    run = 0
    for k in range(2, n):
        run = run + 1 if run < 2 and rng.random() < p_loss else 0
        if run:
            (s0, x0), (s1, x1) = recs[-2], recs[-1]
            pos[k] = x1 + (x1 - x0) / (s1 - s0) * (k - s1)
            flags[k] = FLAG_ESTIMATED
        else:
            recs.append((k, xs[k]))
    return pos, flags


@pytest.mark.parametrize("seed", range(6))
def test_each_estimate_within_its_bound(seed):
    """Random device (m, b0, a Coulomb friction up to 3 times the largest force), random
    held forces, losses of 10-40 %: the error of every estimated position is at most its
    bound; patterns with a record lost between the
    two extrapolated from (estimate, record, estimate) occur in each draw."""
    rng = np.random.default_rng(seed)
    T = 1.0 / float(rng.choice([250.0, 1000.0, 4000.0]))
    m, b0 = float(rng.uniform(0.02, 1.0)), float(rng.choice([0.0, rng.uniform(0.05, 3.0)]))
    f_max = float(rng.uniform(0.1, 5.0))
    fc = float(rng.choice([0.0, rng.uniform(0.5, 3.0) * f_max]))
    xs, fs = _free_motion(rng, 3000, T, m, b0, fc, f_max, float(rng.uniform(-0.5, 0.5)))
    pos, flags = _lossy_record(rng, xs, float(rng.uniform(0.1, 0.4)))
    est = flags != 0
    gaps = np.flatnonzero(est[2:] & ~est[1:-1] & est[:-2])
    assert gaps.size > 0
    cols = {"seq": np.arange(xs.size), "position": pos, "force": fs, "flags": flags}
    bound = estimated_bounds(cols, T, m, b0, 0.0, coulomb=fc)
    err = np.abs(pos - xs)
    assert np.all(err[est] <= bound[est] * (1 + 1e-9) + 1e-15), \
        float(np.max(err[est] / bound[est]))
    assert np.all(bound[~est] == 0.0)

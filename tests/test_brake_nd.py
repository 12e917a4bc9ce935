"""The braking law of every dimension (:mod:`hapsim.braking`) over random 2-D and 3-D
devices, on the simulated clock (the exact sampled plant, one period a reading):

- with ``B = g M / T`` each mode of a frictionless device sees the scalar gain: the
  n-D loop's poles (:func:`brake_loop_matrix`, from the matrix exponential) are the
  roots of the 1-D closed form (:func:`brake_mode_polynomial`), each ``n`` times, and
  their spectral radius the 1-D one, below 1 for every delay up to 5 (as the
  instantaneous-velocity loop's is below the Levin & May bound, :func:`gain_bound`);
- with random friction and a hand's inertia added to the plant (``B`` still from the
  device's own ``M``) the loop stays stable for every delay 0-5;
- a device thrown at speed and braked through :class:`hapsim.braking.Brake` (its
  readings, its clamp, its rest rule) comes to rest with less travel than its friction
  alone gives from the same speed, and far less when the friction is light.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

from hapsim.analysis.stability import brake_loop_matrix
from hapsim.braking import (BRAKE_GAIN, BRAKE_MAX_S, Brake, brake_damping,
                            brake_mode_polynomial, brake_rest, gain_bound)
from tolerance import eig_tol, expm_tol, roots_tol  # same directory

RATE = 1000.0
T = 1.0 / RATE


def _spd(rng, n, lo, hi):
    """A random symmetric positive definite matrix, eigenvalues log-uniform in [lo, hi],
    random orientation."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    w = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
    S = Q @ np.diag(w) @ Q.T
    return 0.5 * (S + S.T)


def _devices(count, seed):
    rng = np.random.default_rng(seed)
    for i in range(count):
        n = 2 + i % 2
        M = _spd(rng, n, 5e-5, 2e-3)                    # joint inertia [kg m^2]
        Bf = _spd(rng, n, 1e-5, 5e-3)                   # joint friction [N m s/rad]
        hand = _spd(rng, n, 1e-6, 5e-4) * rng.uniform(0.0, 1.0)   # m_h J^T J, PSD
        d = int(rng.integers(0, 6))
        yield n, M, Bf, hand, d, rng


def _entries_err(M, B, d):
    """A bound on the 2-norm of the round-off in :func:`brake_loop_matrix`'s entries:
    the exponential's (:func:`expm_tol` of the frictionless augmented matrix, times its
    norm) through the braking's gain ``B / T`` (the products' own round-off, a few eps,
    is well inside: SAFETY in tolerance.py)."""
    n = M.shape[0]
    aug = np.zeros((3 * n, 3 * n))
    aug[:n, n:2 * n] = np.eye(n)
    aug[n:2 * n, 2 * n:] = np.linalg.inv(M)
    aug *= T
    E = scipy.linalg.expm(aug)
    return (expm_tol(aug) * float(np.linalg.norm(E, 2))
            * max(1.0, float(np.linalg.norm(B, 2)) / RATE * RATE) * (d + 2))


@pytest.mark.parametrize("d", range(0, 6))
def test_each_mode_sees_the_scalar_gain_and_the_1d_bound_carries_over(d):
    rng = np.random.default_rng(100 + d)
    p = brake_mode_polynomial(BRAKE_GAIN, d)
    roots = np.roots(p)
    rho1 = float(np.max(np.abs(roots)))
    assert rho1 < 1.0, rho1          # 0.994 at d = 5 (module notes): stable, every d <= 5
    # the instantaneous-velocity loop's closed-form bound holds g at every d <= 5
    assert BRAKE_GAIN < gain_bound(d)
    for n in (2, 3):
        M = _spd(rng, n, 5e-5, 2e-3)
        B = brake_damping(M, RATE)
        np.testing.assert_array_equal(B, BRAKE_GAIN * M * RATE)
        A = brake_loop_matrix(M, 0.0, B, T, d)
        w = np.linalg.eigvals(A)
        # round-off: the matrix's entries from expm (expm_tol), its eigenvalues (eig_tol),
        # the polynomial's roots (roots_tol)
        tol = eig_tol(A, err=_entries_err(M, B, d)) + roots_tol(p)
        # every pole of the n-D loop is a root of the 1-D closed form ...
        dist = np.min(np.abs(w[:, None] - roots[None, :]), axis=1)
        assert np.max(dist) <= tol, (np.max(dist), tol)
        # ... each root n times (the n modes), and the spectral radius the 1-D one
        for r in roots:
            assert np.sum(np.abs(w - r) <= tol) >= n, (r, w)
        assert abs(float(np.max(np.abs(w))) - rho1) <= tol


def test_random_devices_with_friction_and_a_hand_stay_stable_for_delays_up_to_5():
    for n, M, Bf, hand, d, _ in _devices(40, 7):
        B = brake_damping(M, RATE)                  # the device's own M, no hand
        A = brake_loop_matrix(M + hand, Bf, B, T, d)
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        # friction and a hand's inertia only lower each mode's gain into (0, g]: still
        # inside the unit circle. Its distance from 1 is far above the round-off of the
        # eigenvalues (eig_tol: ~1e-12 here)
        assert rho < 1.0 - eig_tol(A), (n, d, rho)


def _throw(M, Bf, d, v0, limit, rest, braking=True):
    """A device thrown at ``v0`` from 0 and braked by the law (the exact sampled plant,
    ``d`` periods between a reading and the period its torque is held over), then left
    at zero torque: the travel to rest, the coast after the last torque in closed form
    ``x + B_f^-1 M v``. Returns (travel [rad], report)."""
    n = M.shape[0]
    A = np.zeros((3 * n, 3 * n))
    A[:n, n:2 * n] = np.eye(n)
    A[n:2 * n, n:2 * n] = -np.linalg.solve(M, Bf)
    A[n:2 * n, 2 * n:] = np.linalg.inv(M)
    E = scipy.linalg.expm(A * T)
    Phi, Gam = E[:2 * n, :2 * n], E[:2 * n, 2 * n:]
    s = np.concatenate([np.zeros(n), v0])
    law = Brake(brake_damping(M, RATE) if braking else np.zeros((n, n)), limit, rest)
    flight = [np.zeros(n)] * d                  # torques computed, not yet held
    periods, ended = 0, "time"
    while braking and periods * T < BRAKE_MAX_S:
        law.observe(s[:n], T if periods else None)
        if law.at_rest:
            ended = "rest"
            break
        flight.append(law.command())
        s = Phi @ s + Gam @ flight.pop(0)
        periods += 1
    for tau in flight + [np.zeros(n)]:           # in flight, then the zero torque
        s = Phi @ s + Gam @ tau
    rest_at = s[:n] + np.linalg.solve(Bf, M @ s[n:])
    return float(np.linalg.norm(rest_at)), law.report(periods, periods * T, ended)


def test_a_thrown_device_is_braked_to_rest_with_less_travel_than_friction_alone():
    for n, M, Bf, hand, d, rng in _devices(40, 11):
        direction = rng.standard_normal(n)
        v0 = direction / np.linalg.norm(direction) * rng.uniform(1.0, 30.0)  # [rad/s]
        B = brake_damping(M, RATE)
        # half the cases clamped from the start (the limit half the first torque's)
        limit = (math.inf if rng.uniform() < 0.5
                 else 0.5 * float(np.max(np.abs(B @ v0))))
        rest = brake_rest(0.5, M, Bf)
        travel, rep = _throw(M, Bf, d, v0, limit, rest)
        free, _ = _throw(M, Bf, d, v0, limit, rest, braking=False)
        # at rest, or out of time (a delay of 5 periods: the slowest pole 0.994, its
        # speed down ~0.994 a period, as in 1-D) slower than it came: what it carries on
        # with is counted in the travel (the coast after the zero torque)
        assert rep["ended"] in ("rest", "time") and rep["seconds"] <= BRAKE_MAX_S, rep
        assert rep["ended"] == "rest" or (np.max(np.abs(rep["v_end"]))
                                          < np.max(np.abs(rep["v_start"]))), rep
        # measured: travel / free at most 0.112 over 200 such devices (seed 11, the
        # worst at d = 5; python's loop of this test with _devices(200, 11))
        assert travel < free, (n, d, travel, free)
        # the slowest coast of friction alone, 1 / min eig(M^-1 B_f) [s]; where it is
        # long beside the braking's own time (d + 1/g periods) the braking takes a small
        # part of friction's travel, as in 1-D (tests/test_brake.py: at least 5 times less)
        tau_f = 1.0 / float(np.min(np.linalg.eigvals(np.linalg.solve(M, Bf)).real))
        if tau_f >= 20.0 * T * (d + 1 + 1.0 / BRAKE_GAIN) and math.isinf(limit):
            assert travel * 5.0 <= free, (n, d, travel, free)


def test_the_clamp_keeps_the_direction_and_the_1d_numbers():
    law = Brake(np.diag([2.0, 1.0]), 1.0, 0.0)
    law.observe([0.0, 0.0], None)
    law.observe([1.0, 1.5], 1.0)                 # v = (1, 1.5): -B v = (-2, -1.5)
    f = law.command()
    assert f[0] == -1.0 and f[1] == -0.75        # scaled by 1/2 (exact: powers of two)
    # 1-D: the clamp min(max(-B v, -lim), lim), the same floats
    rng = np.random.default_rng(3)
    for _ in range(200):
        B, lim = float(rng.uniform(0.1, 100)), float(rng.uniform(0.01, 10))
        x0, x1, dt = (float(v) for v in rng.uniform(-1, 1, 3))
        law = Brake(B, lim, 0.0)
        law.observe((x0,), None)
        law.observe((x1,), abs(dt))
        v = (x1 - x0) / abs(dt)
        assert float(law.command()[0]) == min(max(-B * v, -lim), lim)
    assert brake_damping(np.diag([1.0, -1.0]), RATE).tolist() == [[0.0, 0.0], [0.0, 0.0]]
    assert brake_damping(np.eye(2), math.nan).tolist() == [[0.0, 0.0], [0.0, 0.0]]

"""The loop's impulse responses (:mod:`hapsim.analysis.error_response`) are the compiled
recursion of :func:`hapsim.kernels.impulse.first_state_response`, kept per scene object.

The recursion is compared with numpy's matrix-vector steps written here (the code it
replaced) over random matrices and states, within the round-off of the two recursions
(:func:`tolerance.recurrence_tol`, derived); the responses a measurement asks for again
are the same array, read-only, and a new scene object is never given an older one's.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hapsim.kernels.impulse import first_state_response
from tolerance import recurrence_tol

pytestmark = pytest.mark.numerical


def _numpy_steps(A, s1, s2, n):
    out = np.zeros(n)
    s = s1.copy()
    for k in range(1, n):
        out[k] = s[0]
        s = A @ s + (s2 if k == 1 else 0.0)
    return out


@pytest.mark.parametrize("seed", range(12))
def test_the_compiled_recursion_is_numpys_within_its_round_off(seed):
    rng = np.random.default_rng(seed)
    p = int(rng.integers(1, 24))
    A = rng.normal(size=(p, p))
    # spectral radius drawn in [0.5, 1.02]: decaying, marginal and slowly growing loops
    A *= rng.uniform(0.5, 1.02) / max(abs(np.linalg.eigvals(A)).max(), 1e-300)
    s1, s2 = rng.normal(size=p), rng.normal(size=p) * rng.integers(0, 2)
    n = int(rng.integers(2, 600))
    got = first_state_response(A, s1, s2, n)
    want = _numpy_steps(A, s1, s2, n)
    assert got.shape == (n,) and got[0] == 0.0 and got[1] == s1[0]
    # the states' largest norm along the run; the two recursions' round-off each
    states = [s1, A @ s1 + s2]
    for _ in range(n - 2):
        states.append(A @ states[-1])
    scale = max(np.linalg.norm(s) for s in states)
    assert np.max(np.abs(got - want)) <= 2 * recurrence_tol(A, n, scale)


@pytest.mark.parametrize("n", [0, 1, 2])
def test_short_responses(n):
    A = np.eye(3)
    s = np.ones(3)
    assert np.array_equal(first_state_response(A, s, s, n), np.array([0.0, 1.0])[:n])


def test_a_response_asked_again_is_the_same_read_only_array_and_a_new_scene_its_own():
    from hapsim.analysis.error_response import force_error_response, sensor_error_response
    from hapsim.scene import load_scene
    sc = load_scene("configs/hapkit_serial.yaml")
    for f in (sensor_error_response, force_error_response):
        a = f(sc, 300)
        assert f(sc, 300) is a and not a.flags.writeable
        with pytest.raises(ValueError):
            a[1] = 0.0
        assert f(sc, 200) is not a and np.array_equal(f(sc, 200), a[:200])
        heavier = dataclasses.replace(sc, device=dataclasses.replace(
            sc.device, mass=2 * sc.device.mass))
        b = f(heavier, 300)
        assert b is not a and not np.array_equal(a, b)

"""Integrators of hapsim.kernels.schemes against closed forms, scipy's expm and the linear maps
of hapsim.bench.methods (each test compares the kernel with something computed otherwise)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import expm

from hapsim.analysis.virtual_network import network, virtual_blocks
from hapsim.bench.methods import oscillator_poles
from hapsim.bench.cost import oscillator_scene, string_scene
from hapsim.engine import Engine
from hapsim.errors import ConfigError
from hapsim.scene import parse_scene
from tolerance import expm_tol, measured, power_bound, recurrence_tol, rel_tol

pytestmark = pytest.mark.numerical

# Measured tolerances below: the worst over this module's cases with numba's host target
# and NUMBA_CPU_NAME=generic, OpenBLAS Haswell and Prescott kernels, margin 1000 (a wrong
# scheme moves a recursion coefficient by >= 1e-6 and a force by >= 1e-6 N).

SCHEMES = ("centred", "symplectic_euler", "exact")


def _fit_recursion(x):
    """Least-squares ``x[n+1] + c1 x[n] + c0 x[n-1] = 0``: the characteristic polynomial."""
    A = np.column_stack([x[1:-1], x[:-2]])
    c, *_ = np.linalg.lstsq(A, -x[2:], rcond=None)
    return c


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("rate,K,B", [(1000.0, 1000.0, 0.5), (500.0, 20000.0, 3.0),
                                      (20000.0, 5000.0, 10.0)])
def test_single_oscillator_poles_match_closed_form(scheme, rate, K, B):
    # the simulated positions obey the 2-term recursion whose roots are the scheme's poles
    sc = dataclasses.replace(oscillator_scene(rate, mass=0.1, K=K, B=B), integrator=scheme)
    _, x = Engine(sc).run(400, record=["bob"])
    c1, c0 = _fit_recursion(x[:, 0] / x[0, 0])
    z = oscillator_poles(scheme, 0.1, K, B, 1.0 / rate)
    # least-squares fit of 400 samples (measured 1.0e-15 at worst, absolute)
    assert c1 == pytest.approx(-(z[0] + z[1]).real, rel=0, abs=measured(1.0e-15, 1000))
    assert c0 == pytest.approx((z[0] * z[1]).real, rel=0, abs=measured(1.0e-15, 1000))


def test_schemes_differ_as_derived():
    # centred and symplectic Euler differ only by the damping: same poles when B = 0
    za = np.sort_complex(oscillator_poles("centred", 0.1, 1000.0, 0.0, 1e-3))
    zb = np.sort_complex(oscillator_poles("symplectic_euler", 0.1, 1000.0, 0.0, 1e-3))
    # each a quadratic's roots by formula (~6 roundings), condition |z| / |z1 - z2|
    cond = np.max(np.abs(za)) / abs(za[0] - za[1])
    assert np.allclose(za, zb, rtol=0, atol=2 * rel_tol(6, cond))
    zc = np.sort_complex(oscillator_poles("centred", 0.1, 1000.0, 2.0, 1e-3))
    zd = np.sort_complex(oscillator_poles("symplectic_euler", 0.1, 1000.0, 2.0, 1e-3))
    assert np.max(np.abs(zc - zd)) > 1e-4


@pytest.mark.parametrize("rate", [250.0, 1000.0, 20000.0])
def test_exact_oscillator_against_expm(rate):
    m, K, B, x0 = 0.1, 1000.0, 0.3, 0.01
    sc = dataclasses.replace(oscillator_scene(rate, mass=m, K=K, B=B), integrator="exact")
    eng = Engine(sc)
    _, x = eng.run(300, record=["bob"])
    A = np.array([[0.0, 1.0], [-K / m, -B / m]])
    T = 1.0 / rate
    ref = np.array([(expm(A * n * T) @ [x0, 0.0])[0] for n in range(301)])
    # measured: 3.3e-14 of x0 at worst (rate 250 Hz; expm of A n T up to |A n T| = 1.2e4,
    # where the cheap conditioning bound of tests/tolerance.py is far too pessimistic)
    assert np.max(np.abs(x[:, 0] - ref)) <= measured(3.3e-14, 1000) * x0


@pytest.mark.parametrize("N", [6, 12])          # plain loop and BLAS gemv paths
def test_exact_string_against_expm(N):
    sc = dataclasses.replace(string_scene(1000.0, n=N, B=0.01), integrator="exact")
    eng = Engine(sc)
    names = [f"s{i}" for i in range(1, N + 1)]
    _, x = eng.run(200, record=names)
    m, K, B = 0.01, 2000.0, 0.01
    L = 2 * np.eye(N) - np.eye(N, k=1) - np.eye(N, k=-1)
    A = np.block([[np.zeros((N, N)), np.eye(N)], [-K / m * L, -B / m * L]])
    s0 = np.concatenate([x[0], np.zeros(N)])
    P = expm(A * 1e-3)
    # both iterate P (the kernel its own copy of it): two recurrences' round-off and the
    # difference of the two P's (each expm_tol) carried over n steps
    grow = power_bound(P, 200)
    scale = np.linalg.norm(s0) * grow
    per_step = (2 * recurrence_tol(P, 1, scale)
                + 2 * expm_tol(A * 1e-3) * np.linalg.norm(P, 2) * grow * scale)
    s = s0.copy()
    for n in range(1, 201):
        s = P @ s
        assert np.max(np.abs(x[n] - s[:N])) <= n * per_step


def test_exact_conserves_continuous_energy():
    sc = dataclasses.replace(oscillator_scene(500.0, K=30000.0, B=0.0), integrator="exact")
    eng = Engine(sc)
    e0 = eng.energy()
    # measured 0 (generic 0): exact on both targets
    assert e0 == pytest.approx(0.5 * 30000.0 * 0.01 ** 2)
    eng.step(5000)
    # the exact map conserves it; round-off moves the state by recurrence_tol and P's own
    # error, and the energy (quadratic) by twice that relative to the amplitude
    m, K, T = 0.1, 30000.0, 1.0 / 500.0
    A = np.array([[0.0, 1.0], [-K / m, 0.0]])
    P = expm(A * T)
    # in the energy norm (x, v / w) the map is a rotation: relative errors stay relative
    w = np.sqrt(K / m)
    D = np.diag([1.0, 1.0 / w])
    Pn = D @ P @ np.linalg.inv(D)
    rel = (recurrence_tol(Pn, 5000, 1.0) + 5000 * expm_tol(A * T) * np.linalg.cond(D))
    assert eng.energy() == pytest.approx(e0, rel=2 * rel + rel * rel)


_CHAIN = """
rate_hz: 2000
integrator: {scheme}
masses:
  - {{name: hand, kind: port}}
  - {{name: a, kind: mass, mass: 0.02, x0: 0.001}}
  - {{name: b, kind: mass, mass: 0.05}}
  - {{name: g, kind: ground}}
links:
  - {{between: [hand, a], kind: spring_damper, stiffness: 3000, damping: 0.4}}
  - {{between: [a, b], kind: spring_damper, stiffness: 1500, damping: 0.1}}
  - {{between: [b, g], kind: spring_damper, stiffness: 800, damping: 2.0}}
device: {{mass: 0.1, friction: 0.5, delay: 1}}
"""


@pytest.mark.parametrize("scheme", SCHEMES)
def test_kernel_equals_linear_map_with_a_moving_port(scheme):
    # the kernels and hapsim.bench.methods (used for stability and advice) are one map
    sc = parse_scene(_CHAIN.format(scheme=scheme))
    eng = Engine(sc)
    net = network(sc)
    Av, bp, bpp, cx, cp, cpp = virtual_blocks(net, scheme, sc.period)
    x = eng.x[0].copy()
    X = np.array([x[1], x[2], x[1], x[2]]) if scheme == "centred" else \
        np.array([x[1], x[2], 0.0, 0.0])
    rng = np.random.default_rng(3)
    p_prev = 0.0
    eng.set_port_position(0.0, at_rest=True)
    for _ in range(300):
        p = float(rng.normal(0, 1e-3))
        f = eng.port_step(p)
        f_ref = cx @ X + cp * p + cpp * p_prev
        X = Av @ X + bp * p + bpp * p_prev
        p_prev = p
        # measured: 1.5e-13 N and 4.8e-17 m at worst (forces ~10 N, positions ~1 mm)
        assert f == pytest.approx(f_ref, rel=0, abs=measured(1.5e-13, 1000))
        assert np.allclose(eng.x[0].copy()[1:3], X[:2], rtol=0, atol=measured(4.8e-17, 1000))


def test_scene_integrator_key():
    base = "rate_hz: 1000\n{line}masses: [{{name: a, kind: ground}}, {{name: b, kind: mass, mass: 1}}]\n" \
           "links: [{{kind: contact, between: [a, b], stiffness: 10}}]\n"
    assert parse_scene(base.format(line="")).integrator == "centred"
    assert parse_scene(base.format(line="integrator: symplectic_euler\n")).integrator \
        == "symplectic_euler"
    with pytest.raises(ConfigError, match="centred, symplectic_euler, exact") as ei:
        parse_scene(base.format(line="integrator: rk4\n"))
    assert ei.value.key == "integrator"
    with pytest.raises(ConfigError) as ei:
        parse_scene(base.format(line="integrator: exact\n"))
    assert ei.value.key == "links[0].kind"

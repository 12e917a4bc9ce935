"""Stability where methods fail: every predicted boundary probed at 0.99x and 1.01x by
simulation (bounded inside, growing outside), the delayed THS loop closed on the daemon's
mock physics (exact ZOH / ideal plant, in process)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hapsim.analysis import LoopModel, spectral_radius, stability_limit
from hapsim.bench.cost import oscillator_scene
from hapsim.bench.methods import oscillator_limits, oscillator_poles, stability_margin
from hapsim.engine import Engine
from hapsim.scene import Device, Excitation, load_scene, parse_scene

M, X0 = 0.1, 0.01


def _envelope_ratio(x: np.ndarray) -> float:
    q = max(2, x.size // 10)
    return float(np.max(np.abs(x[-q:])) / np.max(np.abs(x[:q])))


def _simulate(scheme, rate, K, B, n):
    sc = dataclasses.replace(oscillator_scene(rate, mass=M, K=K, B=0.0), integrator=scheme)
    sc = sc.with_link("spring", stiffness=K, damping=B)   # B < 0 allowed here (active)
    _, x = Engine(sc).run(n, record=["bob"])
    return x[:, 0]


def _n_for(rho_out: float, growth: float = 8.0, cap: int = 200_000) -> int:
    return int(min(cap, max(200, math.ceil(growth / math.log(rho_out)))))


@pytest.mark.parametrize("scheme,B", [("centred", 0.0), ("centred", 4.0),
                                      ("symplectic_euler", 0.0), ("symplectic_euler", 4.0)])
def test_stiffness_limit_of_explicit_schemes(scheme, B):
    rate = 1000.0
    T = 1.0 / rate
    Kmax = oscillator_limits(scheme, M, T, B)["K_max"]
    expected = 4 * M / T ** 2 + (-2 if scheme == "centred" else 2) * B / T
    assert Kmax == pytest.approx(expected)
    rho_out = np.max(np.abs(oscillator_poles(scheme, M, 1.01 * Kmax, B, T)))
    n = _n_for(rho_out)
    inside = _simulate(scheme, rate, 0.99 * Kmax, B, n)
    outside = _simulate(scheme, rate, 1.01 * Kmax, B, n)
    assert np.all(np.isfinite(inside)) and np.max(np.abs(inside)) < 20 * X0
    assert _envelope_ratio(inside) <= 1.0 + 1e-9
    assert _envelope_ratio(outside) > 100.0


def test_damping_limit_of_centred_scheme():
    # with K fixed the centred scheme also bounds B: K < 4m/T^2 - 2B/T  <=>  B < (4m/T^2 - K) T/2
    rate, K = 1000.0, 100000.0
    T = 1.0 / rate
    Bmax = (4 * M / T ** 2 - K) * T / 2
    rho_out = np.max(np.abs(oscillator_poles("centred", M, K, 1.01 * Bmax, T)))
    n = _n_for(rho_out)
    assert _envelope_ratio(_simulate("centred", rate, K, 0.99 * Bmax, n)) < 1.0
    assert _envelope_ratio(_simulate("centred", rate, K, 1.01 * Bmax, n)) > 100.0
    # the symplectic Euler scheme (own damping implicit) is stable there, and far beyond
    assert _envelope_ratio(_simulate("symplectic_euler", rate, K, 10 * Bmax, n)) < 1.0


def test_exact_scheme_has_no_stiffness_limit():
    rate = 1000.0
    T = 1.0 / rate
    K = 100 * 4 * M / T ** 2                    # 100x the explicit schemes' limit
    x = _simulate("exact", rate, K, 0.0, 20000)
    assert np.max(np.abs(x)) <= X0 * (1 + 1e-9)
    assert np.max(np.abs(_simulate("exact", rate, K, 1.0, 20000)[-2000:])) < 1e-3 * X0
    # its only boundary is the continuous one: B = 0 (negative damping grows)
    assert _envelope_ratio(_simulate("exact", rate, 1000.0, -0.01, 20000)) > 2.0
    assert _envelope_ratio(_simulate("exact", rate, 1000.0, +0.01, 20000)) < 0.5


def _closed_loop(hold, d, K, B, rate, n, b0=0.5):
    """Wall scene closed on the daemon's mock physics with a d-sample force delay line."""
    from hapsim.daemon.mock import MockPhysics

    dev = Device(mass=M, friction=b0, delay=d, hold=hold)
    sc = parse_scene(f"rate_hz: {rate}\nmasses: [{{name: hand, kind: port}}, "
                     f"{{name: wall, kind: ground}}]\nlinks: [{{name: w, kind: spring_damper, "
                     f"between: [hand, wall], stiffness: {float(K)!r}, damping: {float(B)!r}}}]\n"
                     f"device: {{mass: {M}, friction: {b0}, delay: {d}, hold: {hold}}}\n")
    eng = Engine(sc)
    plant = MockPhysics(dev, rate, Excitation(x0=X0))
    eng.set_port_position(plant.sample(), at_rest=True)
    line = [0.0] * d
    xs = np.empty(n)
    for i in range(n):
        x = plant.sample()
        xs[i] = x
        f = eng.port_step(x)
        line.append(f)
        plant.advance(line.pop(0))
        if abs(x) > 1e3:
            return xs[:i + 1]
    return xs


@pytest.mark.parametrize("hold,d", [("zoh", 0), ("zoh", 1), ("zoh", 2),
                                    ("ideal", 1), ("ideal", 2)])
@pytest.mark.parametrize("B", [0.0, 1.0])
def test_delayed_loop_boundary_closed_on_mock(hold, d, B):
    rate = 1000.0
    loop = LoopModel(M, 0.5, rate, d, hold)
    Kmax = stability_limit(loop, B)
    assert 0 < Kmax < math.inf
    rho_out = spectral_radius(loop, 1.01 * Kmax, B)
    rho_in = spectral_radius(loop, 0.99 * Kmax, B)
    assert rho_in < 1.0 < rho_out
    n = _n_for(rho_out, growth=6.0, cap=60_000)
    inside = _closed_loop(hold, d, 0.99 * Kmax, B, rate, n)
    outside = _closed_loop(hold, d, 1.01 * Kmax, B, rate, n)
    assert _envelope_ratio(inside) < 1.0
    assert _envelope_ratio(outside) > 1.0
    # and the measured growth matches the predicted spectral radius to first order
    if outside.size == n:
        q = n // 10
        growth = np.log(np.max(np.abs(outside[-q:])) / np.max(np.abs(outside[q:2 * q]))) / (n - 2 * q)
        assert growth == pytest.approx(math.log(rho_out), rel=0.2)


def test_stability_margin_refuses_beyond_the_method_boundary():
    wall = load_scene("configs/wall.yaml")
    loop = LoopModel.from_device(wall.device, wall.rate_hz)
    B = wall.link("wall").damping
    Kmax = stability_limit(loop, B)
    ok_in = stability_margin(wall.with_link("wall", stiffness=0.99 * Kmax, damping=B))
    ok_out = stability_margin(wall.with_link("wall", stiffness=1.01 * Kmax, damping=B))
    assert ok_in.ok and ok_in.spectral_radius < 1
    assert not ok_out.ok and ok_out.spectral_radius > 1
    assert "UNSTABLE" in ok_out.limit_description
    ok, rho, text = ok_in                          # also a plain tuple
    assert ok and rho == ok_in.spectral_radius and "centred" in text


def test_stability_margin_depends_on_the_integrator():
    # a stiff virtual mass (no port): beyond the explicit limit, inside for exact
    T = 1e-3
    sc = oscillator_scene(1000.0, mass=M, K=1.01 * 4 * M / T ** 2, B=0.0)
    assert not stability_margin(sc).ok
    assert not stability_margin(dataclasses.replace(sc, integrator="symplectic_euler")).ok
    assert stability_margin(dataclasses.replace(sc, integrator="exact")).ok
    sc_in = oscillator_scene(1000.0, mass=M, K=0.99 * 4 * M / T ** 2, B=0.0)
    assert stability_margin(sc_in).ok

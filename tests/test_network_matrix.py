"""The one closed-loop builder (hapsim.analysis.network) and the integrator-aware check.

Expected values come from outside the code under test: centred eigenvalues recorded with
the previous, separate centred-only builder of scene_check (before it was deleted), the
closed-form characteristic quadratics of one oscillator (hapsim.kernels.schemes docstring,
Jury), ``scipy.linalg.expm`` of the continuous network written here, and the numba engine
run in the loop with a device simulated here.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from hapsim.analysis import check_scene, scene_state_matrix
from hapsim.analysis.pencil import pencil_poles
from hapsim.bench.methods import closed_loop_matrix, virtual_update_matrix
from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.scene import parse_scene
from tolerance import eig_tol, expm_tol, measured, rel_tol

pytestmark = pytest.mark.numerical

INTEGRATORS = ("centred", "symplectic_euler", "exact")

PORT_MASS_ZOH_D1 = """
rate_hz: 1000
integrator: {integ}
masses:
  - {{name: hand, kind: port}}
  - {{name: bob, kind: mass, mass: 0.05}}
  - {{name: top, kind: ground}}
links:
  - {{name: a, kind: spring_damper, between: [hand, bob], stiffness: 300, damping: 0.4}}
  - {{name: b, kind: spring_damper, between: [bob, top], stiffness: 100, damping: 0.1}}
device: {{mass: 0.1, friction: 0.5, delay: 1, hold: zoh}}
"""

PORT_MASS_IDEAL_D2 = """
rate_hz: 500
integrator: {integ}
masses:
  - {{name: hand, kind: port}}
  - {{name: bob, kind: mass, mass: 0.02}}
  - {{name: top, kind: ground}}
links:
  - {{name: a, kind: spring_damper, between: [bob, hand], stiffness: 800, damping: 0.2}}
  - {{name: b, kind: spring_damper, between: [top, bob], stiffness: 50, damping: 0.0}}
device: {{mass: 0.2, friction: 1.0, delay: 2, hold: ideal}}
"""

FREE_TWO_MASSES = """
rate_hz: 1000
integrator: {integ}
masses:
  - {{name: g, kind: ground}}
  - {{name: m1, kind: mass, mass: 0.1}}
  - {{name: m2, kind: mass, mass: 0.05}}
links:
  - {{kind: spring_damper, between: [m1, g], stiffness: 2000, damping: 0.3}}
  - {{kind: spring_damper, between: [m1, m2], stiffness: 1000, damping: 0.1}}
"""

# Recorded with the old centred-only scene_state_matrix (commit 5209071), sorted.
OLD_CENTRED = {
    "port_mass_zoh_d1": [
        (-0.043678877596809704, 0.0), (0.04621233867967971, 0.0),
        (0.9893833877396926, -0.10176220969880481), (0.9893833877396926, 0.10176220969880481),
        (0.997856121315214, -0.02386941206595255), (0.997856121315214, 0.02386941206595255)],
    "port_mass_ideal_d2": [
        (-0.052362885404495046, 0.0), (0.038068054430989824, 0.0),
        (0.9113760878472915, -0.4187144981637116), (0.9113760878472915, 0.4187144981637116),
        (0.9957962445140465, -0.028998115977863316), (0.9957962445140465, 0.028998115977863316)],
    "free_two_masses": [
        (0.9776666674895182, -0.19874839845595052), (0.9776666674895182, 0.19874839845595052),
        (0.9943333325104834, -0.09983968636095686), (0.9943333325104834, 0.09983968636095686)],
}
TEXTS = {"port_mass_zoh_d1": PORT_MASS_ZOH_D1, "port_mass_ideal_d2": PORT_MASS_IDEAL_D2,
         "free_two_masses": FREE_TWO_MASSES}


def scene(name, integ):
    return parse_scene(TEXTS[name].format(integ=integ))


def same_set(a, b, tol):
    a, b = np.sort_complex(np.asarray(a, complex)), np.sort_complex(np.asarray(b, complex))
    return a.size == b.size and float(np.max(np.abs(a - b))) < tol


@pytest.mark.parametrize("name", sorted(OLD_CENTRED))
def test_centred_equals_the_old_centred_builder(name):
    ref = [complex(*z) for z in OLD_CENTRED[name]]
    chk = check_scene(scene(name, "centred"))
    assert chk.integrator == "centred"
    # recorded on another CPU: its round-off and today's, each within the eigenvalue bound
    tol = 2 * eig_tol(scene_state_matrix(scene(name, "centred"))[0])
    assert same_set(chk.eigenvalues, ref, tol)
    # the integrator argument overrides the scene key
    assert same_set(check_scene(scene(name, "exact"), integrator="centred").eigenvalues, ref,
                    tol)


@pytest.mark.parametrize("name", sorted(OLD_CENTRED))
def test_the_three_integrators_give_different_poles(name):
    evs = {i: check_scene(scene(name, i)).eigenvalues for i in INTEGRATORS}
    for i in INTEGRATORS:
        assert check_scene(scene(name, i)).integrator == i
        for j in INTEGRATORS:
            if i < j:
                assert not same_set(evs[i], evs[j], 1e-5), (i, j)


def continuous_two_masses():
    """d/dt [x1, x2, v1, v2] of FREE_TWO_MASSES, written from the link law."""
    m = np.array([0.1, 0.05])
    K = np.array([[2000.0 + 1000.0, -1000.0], [-1000.0, 1000.0]])
    B = np.array([[0.3 + 0.1, -0.1], [-0.1, 0.1]])
    A = np.zeros((4, 4))
    A[:2, 2:] = np.eye(2)
    A[2:, :2] = -K / m[:, None]
    A[2:, 2:] = -B / m[:, None]
    return A


def test_exact_virtual_block_is_expm_of_the_continuous_network():
    T = 1e-3
    Ac = continuous_two_masses()
    sc = scene("free_two_masses", "exact")
    A, names = scene_state_matrix(sc)
    assert names == ["m1.x[n]", "m2.x[n]", "m1.v[n]", "m2.v[n]"]
    # two computations of expm(Ac T), each within expm_tol of it (normwise)
    P = expm(Ac * T)
    tol = 2 * expm_tol(Ac * T) * np.linalg.norm(P, 2)
    assert np.allclose(A, P, rtol=0, atol=tol)
    assert np.allclose(virtual_update_matrix(sc), P, rtol=0, atol=tol)
    # z = exp(s T): s to eig_tol(Ac), z moved by |z| T ds, plus exp's own rounding; against
    # the eigenvalues of A (its round-off and its entries' error tol)
    z = np.exp(np.linalg.eigvals(Ac) * T)
    dz = (np.max(np.abs(z)) * (T * eig_tol(Ac) + rel_tol(2)) + eig_tol(A, tol))
    assert same_set(check_scene(sc).eigenvalues, z, dz)


def one_mass(integ, K, B, m=0.1, rate=1000):
    return parse_scene(f"""
rate_hz: {rate}
integrator: {integ}
masses:
  - {{name: g, kind: ground}}
  - {{name: bob, kind: mass, mass: {m}}}
links:
  - {{kind: spring_damper, between: [bob, g], stiffness: {K}, damping: {B}}}
""")


@pytest.mark.parametrize("K,B", [(1000.0, 0.0), (3e5, 20.0), (1e5, 150.0)])
def test_one_oscillator_closed_forms(K, B):
    m, T = 0.1, 1e-3
    kap, bet = K * T * T / m, B * T / m
    polys = {"centred": [1.0, kap + bet - 2.0, 1.0 - bet],
             "symplectic_euler": [1.0 + bet, kap - bet - 2.0, 1.0]}
    ref = {k: np.roots(c) for k, c in polys.items()}
    s = np.roots([m, B, K]).astype(complex)
    ref["exact"] = np.exp(s * T)
    for integ in INTEGRATORS:
        sc = one_mass(integ, K, B)
        A = scene_state_matrix(sc)[0]
        # hapsim's eigenproblem and the reference's: the quadratic's roots (its
        # companion's bound) or exp(s T) (s to its companion's bound, times |z| T)
        from tolerance import roots_tol
        if integ == "exact":
            theirs = np.max(np.abs(ref[integ])) * (T * roots_tol([m, B, K]) + rel_tol(2))
        else:
            theirs = roots_tol(polys[integ])
        assert same_set(check_scene(sc).eigenvalues, ref[integ], eig_tol(A) + theirs)


def test_stiff_free_mass_centred_unstable_exact_stable():
    K = 1.01 * 4 * 0.1 / 1e-6
    assert not check_scene(one_mass("centred", K, 0)).stable
    assert not check_scene(one_mass("symplectic_euler", K, 0)).stable   # same undamped limit
    chk = check_scene(one_mass("exact", K, 0))
    A = scene_state_matrix(one_mass("exact", K, 0))[0]
    assert chk.stable and chk.spectral_radius == pytest.approx(1.0, rel=0, abs=eig_tol(A))


@pytest.mark.parametrize("integ,code", [("centred", 1), ("symplectic_euler", 1), ("exact", 0)])
def test_cli_stiff_free_mass(tmp_path, capsys, integ, code):
    K = 1.01 * 4 * 0.1 / 1e-6
    p = tmp_path / f"{integ}.yaml"
    p.write_text(f"""rate_hz: 1000
integrator: {integ}
masses:
  - {{name: g, kind: ground}}
  - {{name: bob, kind: mass, mass: 0.1}}
links:
  - {{kind: spring_damper, between: [bob, g], stiffness: {K}, damping: 0}}
""")
    assert main(["check", str(p)]) == code
    out = capsys.readouterr().out
    assert f"integrator {integ}" in out and f"with the {integ} integrator" in out
    assert ("UNSTABLE" in out) == (code == 1)
    assert main(["check", str(p), "--json"]) == code
    doc = json.loads(capsys.readouterr().out)
    assert doc["integrator"] == integ and doc["stable"] is (code == 0)


def engine_in_the_loop(sc, n, x0=1e-3):
    """The numba engine (the scene's integrator) closed on a device simulated here: exact
    ZOH of m x'' + b0 x' = u, delay line of d samples. Returns the device samples."""
    from hapsim.engine import Engine
    dev, T = sc.device, sc.period
    M = np.zeros((3, 3))
    M[:2, :2] = [[0.0, 1.0], [0.0, -dev.friction / dev.mass]]
    M[1, 2] = 1.0 / dev.mass
    E = expm(M * T)
    eng = Engine(sc)
    eng.set_port_position(x0, at_rest=True)
    state = np.array([x0, 0.0])
    forces = [0.0] * dev.delay
    out = np.empty(n)
    for i in range(n):
        out[i] = state[0]
        forces.append(eng.port_step(state[0]))
        state = E[:2, :2] @ state + E[:2, 2] * forces[-1 - dev.delay]
    return out


@pytest.mark.parametrize("integ", INTEGRATORS)
def test_engine_in_the_loop_rings_at_the_predicted_poles(integ):
    sc = scene("port_mass_zoh_d1", integ)
    chk = check_scene(sc)
    assert chk.stable
    ev = chk.eigenvalues[np.abs(chk.eigenvalues) > 0.5]
    assert ev.size == 4
    x = engine_in_the_loop(sc, 1500)[12:]     # the two fast real poles have died out
    found = pencil_poles(x, ev.size, offset=True)
    # a fit of 1488 samples: measured 1.9e-15 (OpenBLAS Haswell) and 2.2e-15 (Prescott)
    # relative at worst over the integrators, margin 1000 (a wrong pole is off by >= 1e-4)
    for z in ev:
        assert np.min(np.abs(found - z)) < measured(2.3e-15, 1000) * abs(z)


@pytest.mark.parametrize("integ", INTEGRATORS)
@pytest.mark.parametrize("name", sorted(TEXTS))
def test_bench_wrapper_is_the_same_matrix(name, integ):
    sc = scene(name, integ)
    A, names = scene_state_matrix(sc)
    assert len(names) == A.shape[0] == A.shape[1]
    assert np.array_equal(closed_loop_matrix(sc), A)
    assert np.array_equal(closed_loop_matrix(sc, integ), A)
    if sc.port is not None:
        assert names[-1] == ("bob.x[n-1]" if integ == "centred" else "bob.v[n]")
    # gain probe: every link's (K, B) doubled
    cal = {lk.name: (2 * lk.stiffness, 2 * lk.damping) for lk in sc.links}
    if len(cal) == len(sc.links):
        # doubling is exact in floating point; the rest is the same arithmetic in the same
        # order, up to the few roundings of a block's entry (rel_tol(4))
        assert np.allclose(closed_loop_matrix(sc, gain=2.0),
                           scene_state_matrix(sc, calibrated=cal)[0], rtol=rel_tol(4), atol=0)


def test_unknown_integrator_is_a_config_error():
    with pytest.raises(ConfigError, match="integrator"):
        scene_state_matrix(scene("free_two_masses", "centred"), integrator="rk4")


def test_analysis_does_not_import_bench():
    code = ("import sys, hapsim.analysis as a; from hapsim.scene import load_scene; "
            "a.check_scene(load_scene('configs/wall.yaml')); "
            "print([m for m in sys.modules if m.startswith('hapsim.bench')])")
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, PYTHONPATH=str(root))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=root, env=env).stdout.strip()
    assert out == "[]"

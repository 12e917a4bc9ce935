"""``hapsim stability --scene`` takes a 1-D scene as the case n = 1 of the per-direction
limit (issue 30: the same command for every dimension).

The 1-D path computes ``K_max`` with the 1-D exact method (:func:`hapsim.api.stability`,
whose result comes with a bracket certified in exact arithmetic); the check here is the
n-D method on the same loop as a 1x1 :class:`~hapsim.analysis.ths.MatrixLoop`
(:func:`hapsim.analysis.direction_limits.direction_limit`: the MIMO state matrix's
unit-circle crossings, another code path), which must fall inside that certified bracket.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from hapsim.analysis.direction_limits import direction_limit
from hapsim.analysis.ths import MatrixLoop
from hapsim.cli import main


def stability(path) -> tuple[int, dict | None, str]:
    """``hapsim stability --scene PATH --json`` in-process: (exit, JSON, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["stability", "--scene", str(path), "--json"])
    return code, (json.loads(out.getvalue()) if out.getvalue() else None), err.getvalue()


def wall(m, b0, rate, d, links) -> str:
    return (f"rate_hz: {rate}\nmasses:\n  - {{name: hand, kind: port}}\n"
            f"  - {{name: ground, kind: ground, x0: 0.0}}\n"
            f"  - {{name: bead, kind: mass, mass: 0.01, x0: 0.0}}\nlinks:\n{links}"
            f"device: {{mass: {m}, friction: {b0}, delay: {d}, hold: zoh, "
            f"force_limit: 10.0}}\n")


@pytest.mark.parametrize("seed", range(12))
def test_a_1d_scene_limit_is_the_n1_direction_limit(tmp_path, seed):
    rng = np.random.default_rng(seed)
    m, b0 = 10 ** rng.uniform(-2, 0.5), rng.uniform(0, 3)
    rate, d = float(rng.choice([250, 500, 1000, 2000, 4000])), int(rng.integers(0, 4))
    # two port links to the ground (a spring-damper and an engaged contact): their K and
    # B add up at the port
    K1, B1, K2, B2 = rng.uniform(10, 500), rng.uniform(0, 3), rng.uniform(10, 500), \
        rng.uniform(0, 2)
    links = (f"  - {{name: a, kind: spring_damper, between: [hand, ground], "
             f"stiffness: {K1}, damping: {B1}}}\n"
             f"  - {{name: c, kind: contact, between: [hand, ground], stiffness: {K2}, "
             f"damping: {B2}}}\n")
    p = tmp_path / "wall.yaml"
    p.write_text(wall(m, b0, rate, d, links))
    code, doc, err = stability(p)
    assert doc["dof"] == 1 and doc["port_damping"] == [[B1 + B2]]
    assert doc["port_stiffness_along"] == [K1 + K2]
    ref = direction_limit(MatrixLoop(mass=m, friction=b0, rate_hz=rate, delay=d, dof=1),
                          [1.0], [[B1 + B2]])
    st = doc["stability"]
    if ref == 0.0:
        assert code == 1 and doc["K_max"] == [0.0]
        return
    assert code == 0
    assert st["K_max_method"] == "certified", st
    lo, hi = st["K_max_interval"]
    # the bracket is certified in exact arithmetic; the n-D method's own error is its
    # Brent refinement (xtol 1e-15 rad on theta) and the round-off of -1/G there, both
    # far below the bracket's width (~1e-12 relative): inside it, no tolerance added
    assert lo <= ref <= hi, (lo, ref, hi)
    assert lo <= doc["K_max"][0] <= hi


def test_a_port_linked_to_a_moving_mass_states_no_limit(tmp_path):
    p = tmp_path / "bead.yaml"
    p.write_text(wall(0.1, 0.5, 1000, 1, "  - {name: s, kind: spring_damper, between: "
                      "[hand, bead], stiffness: 100.0, damping: 0.1}\n  - {name: g, kind: "
                      "spring_damper, between: [bead, ground], stiffness: 100.0, "
                      "damping: 0.1}\n"))
    code, doc, _ = stability(p)
    assert code == 1 and doc["K_max"] is None and doc["directions"] is None


def test_the_1d_json_has_the_2d_keys():
    _, d1, _ = stability("configs/wall.yaml")
    _, d2, _ = stability("configs/pantograph_spring.yaml")
    assert set(d2) <= set(d1)


def test_a_workspace_map_of_a_1d_device_is_refused_by_name():
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["stability", "--scene", "configs/wall.yaml", "--grid", "4"])
    assert code == 2 and "--grid: a 1-DoF device's mass is the same" in err.getvalue()


# -- several ports: each its own delay (issue 30 item 3) ---------------------------------

@pytest.mark.parametrize("seed", range(10))
def test_a_port_limit_with_its_own_delay_is_a_crossing(seed):
    """``direction_limit(..., delays=)`` over random two-port loops, the delays' whole
    parts equal (a rank-one change of the state matrix) or not (the Kronecker
    crossings): below the limit the coupled loop is stable at every sampled stiffness,
    just above it unstable."""
    from hapsim.analysis.loop import STABILITY_TOL
    from hapsim.analysis.ths import state_matrix
    rng = np.random.default_rng(100 + seed)
    m, b0 = rng.uniform(0.02, 0.3, 2), rng.uniform(0, 1, 2)
    d = [int(rng.integers(0, 3)) + float(rng.choice([0.0, 0.3, 0.725])) for _ in range(2)]
    delays = tuple(int(x) if x % 1 == 0 else x for x in d)
    loop = MatrixLoop(mass=np.diag(m), friction=np.diag(b0),
                      rate_hz=float(rng.choice([250, 1000])), delay=max(d))
    C = np.array([[1.0, -1.0], [-1.0, 1.0]])
    K0, B = rng.uniform(0, 50) * C, np.diag(rng.uniform(0, 1, 2)) + 0.05 * C
    e = np.eye(2)[seed % 2]
    k = direction_limit(loop, e, B, K0, delays=delays)
    assert k < np.inf

    def rho(kappa):
        A = state_matrix(loop, K0 + kappa * np.outer(e, e), B, delays=delays)
        return float(np.max(np.abs(np.linalg.eigvals(A))))
    if k == 0.0:                # the coupling alone is past its limit: no kappa helps
        assert all(rho(x) > 1 + STABILITY_TOL for x in (1e-6, 1.0, 10.0))
        return
    # 1e-4 steps off the crossing: the limit is refined to ~1e-10 (Brent on the spectral
    # radius or the scan's angle), and the radius moves by ~1e-5..1e-3 over 1e-4 of k
    # on these loops (measured), well beyond STABILITY_TOL = 1e-9
    assert all(rho(x) <= 1 + STABILITY_TOL for x in np.linspace(0, k * (1 - 1e-4), 40)[1:])
    assert rho(k * (1 + 1e-4)) > 1 + STABILITY_TOL


def _two_faders(tmp_path, spring_a: float):
    text = open("configs/two_faders.yaml").read()
    old = "between: [fader_a, anchor], stiffness: 15.0"
    assert old in text
    p = tmp_path / "faders.yaml"
    p.write_text(text.replace(old, f"between: [fader_a, anchor], stiffness: {spring_a!r}"))
    return p


def test_the_two_faders_limit_is_where_check_turns_unstable(tmp_path):
    """The limit along fader A is the stiffness of A's port spring at which ``hapsim
    check`` of the same scene turns from stable to unstable (the rest held)."""
    code, doc, _ = stability("configs/two_faders.yaml")
    assert code == 0 and doc["ports"] == ["fader_a", "fader_b"]
    _, d2, _ = stability("configs/pantograph_spring.yaml")
    assert set(d2) <= set(doc)
    k_a, along = doc["K_max"][0], doc["port_stiffness_along"][0]
    assert k_a > along           # the shipped scene is stable: within its limit
    for f, verdict in ((0.99, "stable"), (1.01, "unstable")):
        p = _two_faders(tmp_path, 15.0 + (f * k_a - along))
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            main(["check", str(p), "--json"])
        assert json.loads(out.getvalue())["verdict"] == verdict, f

"""hapsim run with --auto, and with scenes whose virtual masses use another integrator."""

from __future__ import annotations

import json

import pytest

from hapsim.analysis import render, LoopModel
from hapsim.bench.methods import stability_margin
from hapsim.cli import main
from hapsim.pipeline.runner import run_scene
from hapsim.errors import UnstableConfigError
from hapsim.scene import parse_scene

BOB = """
rate_hz: 1000
integrator: %s
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
  - {name: bob, kind: mass, mass: 0.05}
links:
  - {name: spring, kind: spring_damper, between: [hand, bob], stiffness: 300, damping: 0.5}
  - {name: anchor, kind: spring_damper, between: [bob, wall], stiffness: 200, damping: 0.2}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10}
excitation: {x0: 0.003}
"""


def test_auto_runs_at_the_advised_rate_and_is_felt_as_asked(capsys):
    code = main(["run", "configs/wall.yaml", "--auto", "--lockstep", "--json"])
    assert code == 0
    rep = json.loads(capsys.readouterr().out)
    adv = rep["advice"]
    assert rep["loop"]["rate_hz"] == adv["rate_hz"] < 1000.0
    # advise reads the wall's (K, B) as the felt pair asked for: k = K, b = B + b0
    # measured 1.1e-16 relative (generic 3.4e-16), margin 3e9
    assert rep["measured"]["k"] == pytest.approx(1000.0, rel=1e-6)
    # measured 7.4e-15 relative (generic 5.1e-15), margin 1e8
    assert rep["measured"]["b"] == pytest.approx(1.5 + 0.5, rel=1e-6)
    # independent: render the calibrated (K, B) at that rate
    v = rep["virtual"]
    r = render(LoopModel(0.1, 0.5, adv["rate_hz"], 1, "zoh"), v["K"], v["B"])
    # measured 2e-15 relative (generic 2e-15), margin 5e5
    assert r.k == pytest.approx(1000.0, rel=1e-9) and r.b == pytest.approx(2.0, rel=1e-9)


def test_auto_and_rate_are_exclusive(capsys):
    assert main(["run", "configs/wall.yaml", "--auto", "--rate", "500", "--lockstep"]) == 2
    assert "--auto chooses the rate" in capsys.readouterr().err


@pytest.mark.parametrize("integrator", ["centred", "symplectic_euler", "exact"])
def test_measured_equals_the_integrators_own_prediction(integrator):
    scene = parse_scene(BOB % integrator, "bob.yaml")
    rep = run_scene(scene, lockstep=True, transport="inprocess", duration=1.0)
    pred, meas = rep["predicted"], rep["measured"]
    assert pred["stable"] is True
    # measured 5.4e-13 relative (generic 4.6e-13), margin 2e6
    assert meas["k"] == pytest.approx(pred["k"], rel=1e-6)
    # measured 9.1e-12 relative (generic 8.7e-12), margin 1e5
    assert meas["b"] == pytest.approx(pred["b"], rel=1e-6)


def test_predictions_differ_between_integrators():
    preds = {i: run_scene(parse_scene(BOB % i), lockstep=True, transport="inprocess",
                          duration=0.5)["predicted"] for i in ("centred", "exact")}
    # the two differ by a measured 1.1e-3 relative (generic the same), margin 1100 over
    # this rel
    assert preds["centred"]["k"] != pytest.approx(preds["exact"]["k"], rel=1e-6)


def test_refusal_follows_the_integrators_limit():
    # a free virtual mass beyond the centred limit 4 m / T^2 (= 200000 N/m for 50 g at 1 kHz)
    stiff = (BOB % "centred").replace("stiffness: 200,", "stiffness: 205000,")
    assert not stability_margin(parse_scene(stiff)).ok
    with pytest.raises(UnstableConfigError):
        run_scene(parse_scene(stiff), lockstep=True, transport="inprocess", duration=0.2)
    # the exact integrator has no such limit for a passive network
    exact = stiff.replace("integrator: centred", "integrator: exact")
    assert stability_margin(parse_scene(exact)).ok


def _bob(integrator, k_at_bob):
    """BOB with the anchor set so that the links at 'bob' sum to ``k_at_bob`` [N/m]."""
    return parse_scene((BOB % integrator).replace("stiffness: 200,",
                                                  f"stiffness: {k_at_bob - 300.0!r},"),
                       "bob.yaml")


# closed-form limits at 'bob' (0.05 kg, B = 0.5 + 0.2 N s/m, 1 kHz): centred
# 4 m/T^2 - 2 B/T = 198600 N/m, symplectic Euler 4 m/T^2 + 2 B/T = 201400 N/m; the whole
# loop with the device agrees (bisection on the spectral radius: 198600.0035, 201400.0035)
K_CENTRED, K_SYMPLECTIC = 198600.0, 201400.0


def test_refusal_names_the_integrator_limit_not_the_port_link():
    """1.01 K_max of the centred scheme at the virtual mass: refused, and the message
    names the integrator, its limit and the ratio; the port link (K = 300 N/m, within its
    limit) is not blamed and 'raise B' (which lowers the centred limit) is not advised."""
    with pytest.raises(UnstableConfigError) as ei:
        run_scene(_bob("centred", 1.01 * K_CENTRED), lockstep=True, transport="inprocess",
                  duration=0.2, handle_signals=False)
    msg = str(ei.value)
    # measured 1.5e-16 relative (generic 1.5e-16), margin 6800
    assert ei.value.stiffness_limit == pytest.approx(K_CENTRED, rel=1e-12)
    assert ei.value.spectral_radius > 1
    for part in ("integrator centred", "K < 4 m/T^2 - 2 B/T", "T^2 lambda_max(M^-1 K)/4",
                 "Virtual mass 'bob'", "centred allows K < 198600 N/m", "K / K_max = 1.01",
                 "Lower the stiffness at 'bob' below 198600 N/m", "symplectic_euler",
                 "exact (no limit", "raise the rate above", "within their limit",
                 "--allow-unstable"):
        assert part in msg, part
    assert "raise B" not in msg and "beyond the stiffness limit" not in msg


def test_just_inside_the_integrator_limit_runs():
    rep = run_scene(_bob("centred", 0.99 * K_CENTRED), lockstep=True, transport="inprocess",
                    duration=0.2, handle_signals=False)
    assert rep["predicted"]["stable"] is True and rep["loop"]["ticks"] == 200
    assert rep["loop"]["stop_reason"] == "duration"


def test_between_centred_and_symplectic_limits():
    """K = 200000 N/m at 'bob': beyond the centred limit, within symplectic Euler's."""
    k = 0.5 * (K_CENTRED + K_SYMPLECTIC)
    with pytest.raises(UnstableConfigError, match=r"symplectic_euler \(K < 201400 N/m here: "
                                                  r"enough\)"):
        run_scene(_bob("centred", k), lockstep=True, transport="inprocess", duration=0.2,
                  handle_signals=False)
    rep = run_scene(_bob("symplectic_euler", k), lockstep=True, transport="inprocess",
                    duration=0.2, handle_signals=False)
    assert rep["predicted"]["stable"] is True and rep["loop"]["ticks"] == 200
    with pytest.raises(UnstableConfigError, match="symplectic_euler allows K < 201400 N/m"):
        run_scene(_bob("symplectic_euler", 1.01 * K_SYMPLECTIC), lockstep=True,
                  transport="inprocess", duration=0.2, handle_signals=False)


def test_port_link_refusal_advises_raising_b_only_where_it_helps():
    from test_daemon import wall_text
    with pytest.raises(UnstableConfigError) as ei:
        run_scene(parse_scene(wall_text(3000.0, 1.5)), lockstep=True, transport="inprocess",
                  handle_signals=False)
    msg = str(ei.value)
    assert "links at the port" in msg and "beyond the stiffness limit K_max = 1313" in msg
    assert "Lower K, raise B or raise the rate" in msg     # here K_max grows with B

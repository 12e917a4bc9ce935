"""hapsim run with --auto, and with scenes whose virtual masses use another integrator."""

from __future__ import annotations

import json

import pytest

from hapsim.analysis import render, LoopModel
from hapsim.bench.methods import stability_margin
from hapsim.cli import main
from hapsim.daemon.runner import run_scene
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
    assert rep["measured"]["k"] == pytest.approx(1000.0, rel=1e-6)
    assert rep["measured"]["b"] == pytest.approx(1.5 + 0.5, rel=1e-6)
    # independent: render the calibrated (K, B) at that rate
    v = rep["virtual"]
    r = render(LoopModel(0.1, 0.5, adv["rate_hz"], 1, "zoh"), v["K"], v["B"])
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
    assert meas["k"] == pytest.approx(pred["k"], rel=1e-6)
    assert meas["b"] == pytest.approx(pred["b"], rel=1e-6)


def test_predictions_differ_between_integrators():
    preds = {i: run_scene(parse_scene(BOB % i), lockstep=True, transport="inprocess",
                          duration=0.5)["predicted"] for i in ("centred", "exact")}
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

"""An emulated board's start-up spec: the scene's device and excitation sent as JSON to the
board's own process (:mod:`hapsim.emulated.driver_mock`, ``hapsim mock``) and read back as
the same dataclasses (:func:`hapsim.scene.device_from_dict`,
:func:`~hapsim.scene.excitation_from_dict`, one reader for both).

Before, the driver boards' reader took the hand back as a dict: read as a hand of mass 0,
it stopped the board at its start with a traceback, and ``hapsim run`` of any scene with a
``device.hand`` through the Haply, FireFader or Hapkit-sketch driver said only "read from
/dev/pts/N failed: [Errno 5] Input/output error".
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from hapsim.scene import Device, Excitation, Hand, Impulse
from hapsim.scene import device_from_dict, excitation_from_dict


def _value(rng, lo, hi):
    """A number or a range, as a scene gives a hand's fields."""
    a, b = sorted(rng.uniform(lo, hi, 2))
    return float(a) if rng.random() < 0.5 else (float(a), float(b))


def _random_device(rng):
    hand = None
    if rng.random() < 0.7:
        hand = Hand(mass=_value(rng, 1e-3, 0.5), damping=_value(rng, 0.0, 2.0),
                    grip_stiffness=(math.inf if rng.random() < 0.3
                                    else _value(rng, 10.0, 5000.0)),
                    grip_damping=_value(rng, 0.0, 5.0), stiffness=_value(rng, 0.0, 100.0))
    return Device(mass=float(rng.uniform(1e-3, 1.0)), friction=float(rng.uniform(0, 2)),
                  delay=int(rng.integers(0, 4)) if rng.random() < 0.7
                  else float(rng.uniform(0.1, 3)),
                  force_limit=math.inf if rng.random() < 0.3 else float(rng.uniform(0.1, 20)),
                  position_resolution=float(rng.choice([0.0, rng.uniform(1e-6, 1e-3)])),
                  coulomb=float(rng.uniform(0, 0.1)), noise=float(rng.uniform(0, 1e-5)),
                  hand=hand, protocol_options=None if rng.random() < 0.5 else {"axis": 1})


def _sent(obj) -> dict:
    """What the board's process reads: the dataclass as JSON (an infinite force limit as
    null, as the board's spawner writes it)."""
    d = dataclasses.asdict(obj)
    if "force_limit" in d and not math.isfinite(d["force_limit"]):
        d["force_limit"] = None
    return json.loads(json.dumps(d))


def test_a_device_and_an_excitation_come_back_as_they_were_sent():
    rng = np.random.default_rng(20261129)
    hands = 0
    for _ in range(200):
        dev = _random_device(rng)
        hands += dev.hand is not None
        back = device_from_dict(_sent(dev))
        assert back == dev
        assert (back.hand is None) == (dev.hand is None)
        if dev.hand is not None:
            assert isinstance(back.hand, Hand) and back.hand.rigid == dev.hand.rigid
        exc = Excitation(x0=float(rng.uniform(-0.01, 0.01)), v0=float(rng.uniform(-1, 1)),
                         impulse=None if rng.random() < 0.5 else
                         Impulse(float(rng.uniform(-1, 1)), 0.01, 0.005))
        assert excitation_from_dict({**_sent(exc), "extra": 1}) == exc
    assert hands > 100


def test_the_haply_joint_with_a_hand_is_measured_through_its_board():
    """The shipped Haply joint with a hand on it, through the board's bytes (lockstep by
    name: the maths, not the timing): the board models the hand, and the measured pair
    is the prediction with the hand (before: the board stopped at its start)."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import parse_scene
    text = open("configs/haply.yaml").read().replace(
        "  force_limit: 0.12 ",
        "  hand: {mass: 0.0005, grip_stiffness: 5.0, grip_damping: 0.002}\n"
        "  force_limit: 0.12 ")
    rep = run_scene(parse_scene(text), driver="haply", handle_signals=False, rt_priority=0,
                    lockstep=True)
    assert rep["verdict"] == "within", rep["reason"]
    # the hand moves the felt pair (0.4948 N m/rad against the joint alone's 0.5007) by
    # more than the stated interval: a board without it could not have matched
    from hapsim.analysis.prediction import predict
    from hapsim.scene import load_scene
    alone = predict(load_scene("configs/haply.yaml"))["k"]
    assert abs(rep["predicted"]["k"] - alone) > rep["measured"]["k_interval"]


def test_a_board_that_cannot_start_says_why_in_one_line(capsys):
    """A board whose device its model refuses (a hand of mass 0) says so in one line on
    the terminal the host shares and exits 2, before it touches its port; before, a
    traceback."""
    from hapsim.emulated.driver_mock import main
    dev = dataclasses.asdict(Device(mass=0.001, friction=0.001,
                                    hand=Hand(mass=0.0, grip_stiffness=5.0)))
    spec = {"device": dev, "excitation": dataclasses.asdict(Excitation()), "driver": "haply"}
    assert main(["--fd", "-1", "--spec", json.dumps(spec), "--rate", "1000"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("hapsim: the emulated haply board cannot start: ConfigError: ")


def test_a_mock_option_the_board_does_not_take_is_refused_naming_those_it_does(capsys):
    """``hapsim identify --mock-option KEY=VALUE`` on every driver's board: a key its
    model does not take is refused before the board starts (exit 2), naming the keys it
    takes, among them every key of the driver's own ``mock_hardware``; before, the board
    stopped at its start and the host said only that its port was gone."""
    from hapsim.cli import main
    from hapsim.drivers import DEFAULT, DRIVERS, get_driver
    for driver in set(DRIVERS) - {DEFAULT}:
        assert main(["identify", "--driver", driver, "--lockstep",
                     "--mock-option", "bogus=1"]) == 2
        err = capsys.readouterr().err
        assert f"bogus: not an option of the {driver} board's model; valid: " in err, err
        named = err.split("valid: ")[1].split()
        assert set(get_driver(driver).mock_hardware()) <= {k.rstrip(",") for k in named}

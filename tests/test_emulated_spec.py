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


def _numeric_options(cls):
    """A board model's numeric keyword options (not its bools, strings or ``seed``)."""
    import inspect
    return [n for n, p in inspect.signature(cls.__init__).parameters.items()
            if p.kind is p.KEYWORD_ONLY and n != "seed"
            and any(t in str(p.annotation) for t in ("float", "int"))
            and "bool" not in str(p.annotation)]


def test_every_numeric_board_option_refuses_a_non_finite_value_by_name():
    """Each board model (:data:`hapsim.emulated.driver_mock.MOCKS`), each of its numeric
    options, each of NaN, +inf, -inf and a word: the model refuses it where it is built,
    naming the option's key; before, ``cpr=0`` or ``full_scale=nan`` started a board that
    divided by it, or never moved, in its own process (a traceback, then the host's "does
    not answer" or "hardly moved")."""
    from hapsim.emulated.driver_mock import MOCKS, build_board
    from hapsim.errors import ConfigError
    dev, exc = Device(mass=0.001, friction=0.001), Excitation()
    for driver, cls in MOCKS.items():
        names = _numeric_options(cls)
        assert len(names) >= 3, (driver, names)        # the helper still finds them
        for name in names:
            for bad in (math.nan, math.inf, -math.inf, "many"):
                try:
                    build_board(driver, dev, exc, 1000.0, options={name: bad})
                except ConfigError as e:
                    assert e.key == name, (driver, name, bad, e.key, str(e))
                else:
                    raise AssertionError(f"{driver} board took {name}={bad!r}")


def test_a_board_option_out_of_range_is_refused_before_its_process_starts(monkeypatch):
    """The embedded board (:class:`hapsim.emulated.driver_mock.EmbeddedDriverMock`)
    checks its options by building its model in the caller's process: a count of zero
    per revolution, a full scale of zero or below, a force limit of zero are refused with
    their key, and no child process is started."""
    import pytest

    from hapsim.emulated import driver_mock
    from hapsim.errors import ConfigError
    started = []
    monkeypatch.setattr(driver_mock.EmbeddedDriverMock, "start",
                        lambda self, *a, **k: started.append(a))
    dev, exc = Device(mass=0.001, friction=0.001), Excitation()
    for driver, key, bad in (("haply", "cpr", 0), ("haply", "cpr", -4096),
                             ("haply", "resolution", 0), ("firefader", "full_scale", 0.0),
                             ("firefader", "full_scale", -1.0),
                             ("firefader", "metres_per_count", 0.0),
                             ("firefader", "boot_s", -0.5),
                             ("hapkit-serial", "force_limit", 0.0)):
        with pytest.raises(ConfigError) as info:
            driver_mock.EmbeddedDriverMock(driver, dev, exc, 1000.0,
                                           options={"clock": "lockstep", key: bad})
        assert info.value.key == key and "must be a finite number" in str(info.value)
    assert not started


def test_identify_refuses_a_mock_option_out_of_range_in_one_line(capsys):
    """``hapsim identify --driver haply --mock-option cpr=0``: exit 2 and one line naming
    the key and its range; before, a traceback from the board's process and "the Haply
    board does not answer its writes"."""
    from hapsim.cli import main
    assert main(["identify", "--driver", "haply", "--lockstep",
                 "--mock-option", "cpr=0"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "does not answer" not in err
    assert "cpr: must be a finite number > 0 [counts per revolution], got 0" in err, err


class _Link:
    """A link whose board answers every write with one reply the decoder finds out of
    reach (``reach``) or with nothing."""

    def __init__(self, dec, reach: bool):
        self.dec, self.reach = dec, reach

    def write(self, data):
        if self.reach:
            self.dec.stats["unreachable"] += 1

    def read(self, timeout):
        return b""


class _Decoder:
    def __init__(self):
        self.stats = {"unreachable": 0, "desync": 0, "lone": 0}

    def feed(self, data):
        return []


def test_a_board_whose_replies_are_out_of_reach_is_not_said_to_be_silent():
    """:class:`hapsim.drivers.exchange.Exchange`: a board that answers every write with
    a reading no motion reaches (an encoder that counts more per revolution than the
    driver's resolution says) ends the exchange saying it answers and naming the
    resolution; a silent board still "does not answer its writes". Before, both were
    said to be silent (``cpr=1e9`` on the Haply mock: 55 of 86 replies out of reach)."""
    import pytest

    from hapsim.drivers.exchange import Exchange
    from hapsim.errors import DeviceError
    for reach in (True, False):
        dec = _Decoder()

        class Drv:
            def decoder(self):
                return dec

        ex = Exchange(Drv(), _Link(dec, reach), 1000.0, False, 0.0, max_missing=4)
        with pytest.raises(DeviceError) as info:
            for _ in range(6):
                ex.reply(b"\0")
        msg = str(info.value)
        if reach:
            assert msg.startswith("the board answers, but 5 of its replies") and \
                "--protocol-option resolution=COUNTS" in msg, msg
        else:
            assert "does not answer its writes" in msg, msg


def test_a_mock_option_with_a_port_is_refused(capsys):
    """``--mock-option`` describes the embedded board; with ``--port`` the device is the
    one on the port: refused by its flag before the port is opened (before: taken and
    ignored)."""
    from hapsim.cli import main
    assert main(["identify", "--driver", "haply", "--port", "/dev/nonexistent",
                 "--mock-option", "cpr=4000"]) == 2
    err = capsys.readouterr().err
    assert "--mock-option: the embedded board's hardware" in err and "cannot open" not in err

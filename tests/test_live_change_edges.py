"""The live changes' edges a fuzz of every address with hostile arguments found (stop 92):
a master gain of 1e300 taken (inf frames on the sound card), extra arguments dropped and the
change taken, a huge integer raising out of the controller, a telemetry subscription whose
rate 0 raised out of the OSC handler and whose port 70000 was taken and then raised in the
sample loop, and the view's page messages that ended the page's connection. Each class is
tested over every address and value, through the controller the OSC server and the view
both call."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest

from hapsim.analysis.prediction import prepare_scene
from hapsim.audio.control import Controller, ControllerND
from hapsim.audio.messages import (ADDRESSES, MAX_GAIN, USAGE, Refused, gain_arg, no_args,
                                   numbers, telemetry_args)
from hapsim.engine import Engine
from hapsim.scene.reader import load_scene, load_scene_nd

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

#: Values a sender may put in any argument position.
HOSTILE = [math.nan, math.inf, -math.inf, -1.0, 0.0, 1e300, -1e300, 1e-300, 10 ** 400,
           2 ** 63 - 1, True, "word", "", None, [1.0], {"a": 1}]


def _controllers():
    sc = prepare_scene(load_scene(str(CONFIGS / "wall.yaml")))[0]
    yield "wall", Controller(sc, Engine(sc), ramp_s=0.01, background=False), "wall", None
    nd = load_scene_nd(str(CONFIGS / "pantograph_wall.yaml"))
    yield ("pantograph_wall", ControllerND(nd, Engine(nd), ramp_s=0.01, background=False),
           "wall", None)


@pytest.mark.parametrize("which", ["wall", "pantograph_wall"])
def test_no_hostile_argument_raises_out_of_the_controller(which):
    """Every change address, every argument position, every hostile value: the
    controller answers ``(ok, reason or (ramp, k, b))`` and raises nothing (before: an
    int beyond the float range raised OverflowError out of ``request``). A refusal is a
    sentence; an acceptance has a finite ramp."""
    name, ctl, link, _ = next((c for c in _controllers() if c[0] == which))
    changes = [a for a in ADDRESSES if a not in ("/hapsim/felt", "/hapsim/loop",
                                                 "/hapsim/telemetry")]
    valid = {"/hapsim/link/stiffness": [link, 900.0], "/hapsim/link/damping": [link, 1.0],
             "/hapsim/link/kb": [link, 900.0, 1.0], "/hapsim/link/target": [link, 900.0, 1.0],
             "/hapsim/mass": ["x", 0.1], "/hapsim/gain": [1.0], "/hapsim/pause": [],
             "/hapsim/resume": []}
    tried = 0
    for address in changes:
        base = valid[address]
        for i, bad in itertools.product(range(len(base) + 1), HOSTILE):
            args = list(base)
            if i < len(base):
                args[i] = bad
            else:
                args.append(bad)            # one too many
            ok, info = ctl.request(address, *args)
            if ok:
                assert math.isfinite(info[0]) and info[0] >= 0, (address, args, info)
            else:
                assert isinstance(info, str) and info, (address, args)
            tried += 1
    assert tried > 300


@pytest.mark.parametrize("address", sorted(USAGE))
def test_an_extra_argument_is_refused_with_the_usage(address):
    """One argument more than an address takes is refused, naming the usage (before:
    dropped, and the change taken)."""
    sc = prepare_scene(load_scene(str(CONFIGS / "wall.yaml")))[0]
    ctl = Controller(sc, Engine(sc), ramp_s=0.01, background=False)
    args = {"/hapsim/link/stiffness": ["wall", 900.0], "/hapsim/link/damping": ["wall", 1.0],
            "/hapsim/link/kb": ["wall", 900.0, 1.0], "/hapsim/link/target": ["wall", 900.0,
                                                                             1.0],
            "/hapsim/mass": ["wall", 0.1], "/hapsim/gain": [1.0], "/hapsim/pause": [],
            "/hapsim/resume": []}.get(address)
    if args is None:                        # the queries: answered by the server
        with pytest.raises(Refused):
            no_args([1], address)
        return
    ok, reason = ctl.request(address, *args, 1.5)
    assert not ok and ("given" in reason or "no argument" in reason), reason


def test_the_gain_is_a_volume_within_its_bound():
    """``/hapsim/gain``: [0, MAX_GAIN] taken, anything else refused with the range
    (before: -1 and 1e300 were taken; 1e300 put inf frames on the sound card)."""
    for g in (0.0, 1.0, 0.5, MAX_GAIN):
        assert gain_arg([g]) == g
    for g in (-1.0, -1e-9, MAX_GAIN * 1.001, 1e300, math.inf, math.nan, 10 ** 400):
        with pytest.raises(Refused) as info:
            gain_arg([g])
        assert "gain" in str(info.value)
    with pytest.raises(Refused):
        numbers([1.0, 2.0], 1, "gain", "/hapsim/gain")


@pytest.mark.parametrize("args, says", [
    (["127.0.0.1"], "expected"), (["127.0.0.1", 9000, 50.0, 1], "expected"),
    ([9000, "127.0.0.1"], "expected"), (["", 9000], "expected"),
    (["127.0.0.1", 0], "port"), (["127.0.0.1", 70000], "port"),
    (["127.0.0.1", 9000.5], "port"), (["127.0.0.1", True], "port"),
    (["127.0.0.1", math.nan], "port"), (["127.0.0.1", 9000, 0.0], "rate_hz"),
    (["127.0.0.1", 9000, -1.0], "rate_hz"), (["127.0.0.1", 9000, math.inf], "rate_hz"),
    (["127.0.0.1", 9000, "x"], "rate_hz"), (["127.0.0.1", 9000, 1e300], "rate_hz")])
def test_a_telemetry_subscription_is_checked_before_it_is_taken(args, says):
    """``/hapsim/telemetry HOST PORT [RATE_HZ]``: a port outside 1-65535, a rate that is
    not a finite number > 0 or a missing host refused with the usage (before: rate 0
    raised out of the handler, -1 sent every sample, port 70000 was taken and raised in
    the sample loop)."""
    with pytest.raises(Refused) as info:
        telemetry_args(args, 1000.0)
    assert says in str(info.value)
    assert telemetry_args(["127.0.0.1", 9000], 1000.0) == ("127.0.0.1", 9000, 20)
    assert telemetry_args(["localhost", 9000.0, 1000.0], 1000.0) == ("localhost", 9000, 1)


def test_a_subscriber_the_loop_cannot_reach_never_stops_the_loop():
    """:func:`hapsim.audio.osc.send_telemetry` to a client whose port the socket refuses
    (a subscription made before the check): nothing raised into the sample loop."""
    from types import SimpleNamespace

    from hapsim.audio.osc import send_telemetry

    class Client:
        def send_message(self, address, values):
            raise OverflowError("getsockaddrarg: port must be 0-65535.")
    send_telemetry({"client": Client(), "every": 1}, 0.0, 0.0, 0.0,
                   SimpleNamespace(felt={"k": 1.0, "b": 2.0}))


@pytest.mark.parametrize("req", [[1, 2], "x", 5, None,
                                 {"op": "request", "address": "/hapsim/gain", "args": 5},
                                 {"op": "request", "address": "/hapsim/link/stiffness",
                                  "args": "wall"},
                                 {"op": "request", "address": "/hapsim/link/stiffness",
                                  "args": ["wall", 10 ** 400]},
                                 {"op": "nonsense"}])
def test_a_page_message_of_the_wrong_shape_is_answered_not_raised(req):
    """The live view's page requests that are no ``{op, address, args}`` object: a reply
    with ``ok`` False and a reason (before: an AttributeError, a TypeError or an
    OverflowError ended the page's connection; a word for ``args`` was split into its
    letters)."""
    from hapsim.view.server import ViewServer
    sc = prepare_scene(load_scene(str(CONFIGS / "wall.yaml")))[0]
    fake = ViewServer.__new__(ViewServer)
    fake.ctl = Controller(sc, Engine(sc), ramp_s=0.01, background=False)
    out = ViewServer._answer(fake, req)
    assert out["ok"] is False and out["reason"], out
    assert "no link 'w'" not in out["reason"]


@pytest.mark.parametrize("scene, link", [("wall", "wall"), ("string", "seg1")])
def test_a_negative_virtual_damping_is_refused_as_the_scene_file_refuses_it(scene, link):
    """``/hapsim/link/damping LINK -B`` and ``/hapsim/link/kb LINK K -B`` on a 1-D scene:
    refused, as the scene file and the 2-D/3-D controller refuse a negative damping
    (before: taken); a target's calibration may still give one."""
    sc = prepare_scene(load_scene(str(CONFIGS / f"{scene}.yaml")))[0]
    ctl = Controller(sc, Engine(sc), ramp_s=0.01, background=False)
    lk = sc.link(link)
    for address, args in (("/hapsim/link/damping", [link, -1e-4]),
                          ("/hapsim/link/kb", [link, lk.stiffness, -0.01])):
        ok, reason = ctl.request(address, *args)
        assert not ok and "damping must be >= 0" in reason, reason
    ok, info = ctl.request("/hapsim/link/damping", link, lk.damping)
    assert ok, info

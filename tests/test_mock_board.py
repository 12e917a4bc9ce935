"""``hapsim mock --scene SCENE`` for a device that speaks a driver's protocol: the emulated
board served alone on a pty (hapsim.commands.mock_board), reset for each host as an
Arduino is when a host opens its port (BoardPerHost), and its refusals.

The reset's account is checked in-process on the board's own wall clock (simulated
times, no pty): a host after a reset meets, byte for byte and at the same instants
relative to the reset, what the first host met on the board the mock started with. It
failed before the board's pass times were put on serving's clock (``ready_at``): serve
answered a reset board's records early, the loop's delay changed, and a FireFader run
said "differs" of its own device. One run end to end over the pty, on the wall clock."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest

from hapsim.commands.mock_board import BoardPerHost
from hapsim.drivers import get_driver
from hapsim.drivers.firefader import encode_packet
from hapsim.emulated.driver_mock import MOCKS
from hapsim.scene import load_scene
from inproc import hapsim_main
from test_mock_persistent import ROOT, hapsim
from tolerance import rel_tol

FIREFADER = os.path.join(ROOT, "configs", "firefader.yaml")
#: Every time the reset test compares is under this [s] (hosts at 2.5 s and ~6.5 s on
#: serving's clock, 120 periods of 4 ms each).
T_SPAN = 10.0


def _make():
    sc = load_scene(FIREFADER)
    hw = get_driver("firefader").mock_hardware()
    return lambda: MOCKS["firefader"](sc.device, sc.rate_hz, sc.excitation, seed=0,
                                      clock="wall", **hw)


def _host(dev, start: float, rng, n: int = 120, T: float = 4e-3):
    """A host's packets from ``start`` [s] on serving's clock: a write each period at a
    random lateness (0-1 ms), idle calls between them as serve makes; the board's bytes
    and its pass times (``ready_at``) relative to ``start``."""
    out = []
    last = start
    for k in range(n):
        t = start + k * T + float(rng.uniform(0.0, 1e-3))
        for s in np.arange(last + 0.02, t, 0.02):          # serve's idle polls
            dev.idle(float(s - last))
        f = int(rng.integers(-60, 60))
        pk = encode_packet(f, 0)
        got = dev.feed(pk, t, writes=[b"", pk])
        out.append((got, dev.ready_at - start))
        last = t
    return out


def test_a_host_after_a_reset_meets_what_the_first_host_met():
    """Host 1 comes 2.5 s after the board started; it leaves, silent 1.5 s (the reset at
    NEW_HOST_S), host 2 comes 2.5 s after the reset with the same packets at the same
    lateness: its records and the instants the board answers them, relative to its
    arrival, are the first host's exactly (the reset board's clock put on serving's)."""
    make = _make()
    dev = BoardPerHost(make)
    # the first host, 2.5 s after the board started
    for s in np.arange(0.02, 2.5, 0.02):
        dev.idle(float(s))
    first = _host(dev, 2.5, np.random.default_rng(1))
    end = dev._last                             # the host's last bytes
    # gone: serve's idle polls (every 20 ms of silence) until the reset, then the fresh
    # board's silence
    t = end
    while t < end + 1.0 + 2.5:
        t += 0.02
        dev.idle(t - end)
    reset_at = dev._born
    assert dev.hosts == 1
    assert end + BoardPerHost.NEW_HOST_S <= reset_at <= end + BoardPerHost.NEW_HOST_S + 0.02
    second = _host(dev, reset_at + 2.5, np.random.default_rng(1))
    assert dev.hosts == 2
    assert [g for g, _ in second] == [g for g, _ in first]
    # the same pass times on clocks offset by the reset, each the end of a chain of
    # roundings of times under T_SPAN: the board's time (now - born), its pass's
    # arithmetic (the pass start, the ADC's and the reply's delays: 4), the offset put
    # back (+ born) and the arrival taken off (- start): 8 roundings, absolute error
    # rel_tol(8) * T_SPAN on each side
    tol = 2 * rel_tol(8) * T_SPAN
    assert [r for _, r in second] == pytest.approx([r for _, r in first], rel=0, abs=tol)
    # the second host's ready times, in serving's time, are after its bytes (none early)
    assert all(r > 0 for _, r in second)


def test_the_counters_are_the_last_hosts_after_a_reset():
    """After the reset that follows the last host, the board's report (serve reads it
    from the proxy) is the last host's board's, not the fresh one's zeros."""
    dev = BoardPerHost(_make())
    _host(dev, 1.0, np.random.default_rng(2), n=40)
    served = dev.commands()
    assert served > 0
    dev.idle(1.2)                               # gone: reset
    assert dev._fresh and dev.commands() == served


def _haply_scene(path, x0, options=None):
    """configs/haply.yaml with its joint let go at ``x0`` [rad], its ``protocol_options``
    ``options`` (None: none), written to ``path``."""
    import yaml
    scene = yaml.safe_load(open(os.path.join(ROOT, "configs", "haply.yaml")))
    scene["excitation"]["x0"] = x0
    if options is not None:
        scene["device"]["protocol_options"] = options
    path.write_text(yaml.safe_dump(scene))
    return str(path)


def test_the_haply_boards_refusal_names_what_it_then_serves(tmp_path):
    """A Haply scene without the set-up's arming angle is refused by ``hapsim mock``
    (a host on the port arms the encoder at ``offset_deg`` only when the scene says it);
    the refusal names the options to add, and those options, pasted into the scene as
    they are printed, are served, for the shipped scene's start (0.2 rad) and random
    ones (before: the message printed 11.4592 for a 0.2 rad start, and the scene given
    that was refused again). (The shipped scene names none: a host embedding the board
    arms it at the excitation's start, wherever the scene's x0 is edited to.)"""
    import argparse

    import yaml

    from hapsim.commands.mock_board import _board
    from hapsim.errors import ConfigError

    def served(path):
        return _board(argparse.Namespace(scene=path, lockstep=False, seed=0,
                                         amplitude=None))
    rng = np.random.default_rng(92)
    for i, x0 in enumerate([0.2, *rng.uniform(-1.0, 1.0, 12)]):
        x0 = float(x0)
        with pytest.raises(ConfigError) as info:
            served(_haply_scene(tmp_path / f"bare{i}.yaml", x0))
        text = str(info.value)
        assert info.value.key == "device.protocol_options", text
        named = yaml.safe_load(text[text.index("{"):text.index("}") + 1])
        assert set(named) == {"offset_deg"}, text
        assert served(_haply_scene(tmp_path / f"armed{i}.yaml", x0, named))[1] == 1000.0


@pytest.mark.parametrize("args, key, words", [
    (["--scene", "configs/firefader.yaml", "--faults", "drop=0.1"], "--faults",
     "does not take --faults"),
    (["--scene", "configs/firefader.yaml", "--amplitude", "0.001"], "--amplitude",
     "excitation section"),
    (["--scene", "configs/two_faders.yaml", "--amplitude", "0.5"], "--amplitude",
     "quarter of the faders' workspace"),
])
def test_what_a_board_cannot_serve_is_refused_in_one_line(args, key, words):
    code, out, err = hapsim_main(["mock", *args], cwd=ROOT)
    assert code == 2 and out == "", (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and key in lines[0] and words in lines[0], err


def test_two_faders_served_alone_measure_over_the_port(tmp_path):
    """The two-terminal flow with the FireFader's two faders: ``hapsim mock --scene
    configs/two_faders.yaml`` on its own wall clock, ``hapsim run ... --port PORT``: the
    run ends by its duration or the host's own lateness, says before it starts what the
    pots cannot state, never "differs", and the mock ends cleanly on Ctrl-C with the
    host's commands in its report."""
    report = str(tmp_path / "board.json")
    mock = hapsim("mock", "--scene", "configs/two_faders.yaml", "--report", report)
    try:
        line = mock.stdout.readline()
        assert line.startswith("PORT /dev/"), line
        code, out, err = hapsim_main(["run", "configs/two_faders.yaml", "--port",
                                      line.split()[1], "--json"], cwd=ROOT)
        assert code == 0, err
        rep = json.loads(out)
        assert rep["verdict"] != "differs" and "predicted before the run" in err
        assert rep["realtime"]["stop"] == "end" or rep["realtime"]["stop"].startswith(
            ("host late", "safety:")), rep["realtime"]
    finally:
        mock.send_signal(signal.SIGINT)
        _, merr = mock.communicate(timeout=20)
    assert mock.returncode == 0 and "Traceback" not in merr, merr
    assert "1 host(s) served" in merr
    with open(report) as fh:
        assert json.load(fh)["packets"] > 0

"""The run's options are built once: ``hapsim run``'s parser -> :func:`run_options` ->
:class:`RunOptions`, which :func:`run_scene` takes (keyword changes on top)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from hapsim.cli import build_parser
from hapsim.commands.run import _announce, run_options
from hapsim.daemon.runner import RunOptions, run_scene
from hapsim.errors import ConfigError
from hapsim.scene import load_scene

WALL = str(Path(__file__).resolve().parents[1] / "configs" / "wall.yaml")


def _parse(*argv):
    return build_parser("run").parse_args(["run", WALL, *argv])


def test_command_line_defaults_are_the_options_defaults():
    """No option has one default in the parser and another in RunOptions."""
    got = run_options(_parse(), load_scene(WALL))
    want = RunOptions()
    for f in dataclasses.fields(RunOptions):
        if f.name == "on_start":
            assert got.on_start is _announce
        elif f.name == "loop":      # 'auto': run() chooses compiled or python before the run
            assert got.loop == "auto"
        else:
            assert getattr(got, f.name) == getattr(want, f.name), f.name


def test_every_command_line_option_reaches_its_field():
    argv = ["--port", "/dev/null", "--baud", "9600", "--duration", "2.5", "--rate", "2000",
            "--lockstep", "--host-clocked", "--loop", "python", "--telemetry", "t.npz",
            "--allow-unstable", "--rt-priority", "3", "--seed", "7", "--faults", "drop=0.1",
            "--fault-seed", "5", "--no-reconnect", "--lost-timeout", "0.2",
            "--reconnect-attempts", "2", "--reconnect-time", "1.5", "--driver", "haply",
            "--osc", "0", "--osc-ramp", "0.2", "--sound", "jack", "--jack-server", "srv"]
    o = run_options(_parse(*argv), load_scene(WALL), embedded="E")
    assert (o.port, o.baud, o.duration, o.rate_hz) == ("/dev/null", 9600, 2.5, 2000.0)
    assert o.lockstep and o.host_clocked and o.allow_unstable and o.loop == "python"
    assert (o.telemetry, o.rt_priority, o.seed, o.faults, o.fault_seed) == (
        "t.npz", 3, 7, "drop=0.1", 5)
    assert o.reconnect is False and o.lost_timeout == 0.2
    assert (o.reconnect_attempts, o.reconnect_time) == (2, 1.5)
    assert (o.driver, o.osc, o.osc_ramp, o.sound, o.jack_server) == ("haply", 0, 0.2, "jack",
                                                                     "srv")
    assert o.embedded == "E"
    assert run_options(_parse("--driver", "framed"), load_scene(WALL)).driver is None


def test_run_scene_checks_a_copy_with_the_changes():
    """``run_scene(scene, opts, **changes)`` leaves ``opts`` as it was; a change that is no
    option is a TypeError, a bad value the checked ConfigError naming the option."""
    opts = RunOptions(lockstep=True)
    scene = load_scene(WALL)
    with pytest.raises(ConfigError, match="unknown transport 'bogus'"):
        run_scene(scene, opts, transport="bogus")
    assert opts == RunOptions(lockstep=True)          # transport still unresolved, no plan
    with pytest.raises(TypeError):
        run_scene(scene, opts, no_such_option=1)

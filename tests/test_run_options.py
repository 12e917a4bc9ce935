"""The run's options are declared once (:class:`RunOptions`' fields): ``hapsim run``'s
parser is generated from them and :meth:`RunOptions.from_args` builds them back, which
:func:`run_scene` takes (keyword changes on top)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from hapsim.cli import build_parser
from hapsim.pipeline.options import command_line_fields
from hapsim.pipeline.runner import RunOptions, run_scene
from hapsim.errors import ConfigError
from hapsim.scene import load_scene

WALL = str(Path(__file__).resolve().parents[1] / "configs" / "wall.yaml")


def _parse(*argv):
    return build_parser("run").parse_args(["run", WALL, *argv])


def test_command_line_defaults_are_the_options_defaults():
    """No option has one default in the parser and another in RunOptions."""
    got = RunOptions.from_args(_parse())
    want = RunOptions()
    for f in dataclasses.fields(RunOptions):
        if f.name == "loop":      # 'auto': run() chooses compiled or python before the run
            assert got.loop == "auto"
        else:
            assert getattr(got, f.name) == getattr(want, f.name), f.name


def test_every_option_of_the_parser_is_one_declared_field():
    """The parser's run options are exactly the declared fields, by their flags (the
    command adds its own: the scene, --auto, --tolerance, --device, --amplitude, --json,
    the Falcon's --firmware and --packets, the Haply 2DIY's --generation, and --help-all,
    which prints every option where --help prints the common ones)."""
    import argparse
    sub = next(a for a in build_parser("run")._actions
               if isinstance(a, argparse._SubParsersAction))
    parser = sub.choices["run"]
    dests = {a.dest for a in parser._actions}
    fields = {f.name for f in command_line_fields()}
    assert fields <= dests
    assert dests - fields == {"help", "help_all", "scene", "auto", "tolerance", "device",
                              "amplitude", "json", "firmware", "packets", "generation"}
    flags = {a.dest: a.option_strings for a in parser._actions}
    for f in command_line_fields():
        assert flags[f.name] == [f.metadata["cli"]["flag"]], f.name
    # in the declarations' order, the command's own options beside the ones they go with
    order = [a.dest for a in parser._actions]
    assert [d for d in order if d in fields] == [f.name for f in command_line_fields()]
    assert order.index("auto") == order.index("seed") + 1
    assert order.index("device") == order.index("driver") + 1


def test_every_command_line_option_reaches_its_field():
    argv = ["--port", "/dev/null", "--baud", "9600", "--duration", "2.5", "--rate", "2000",
            "--lockstep", "--host-clocked", "--loop", "python", "--telemetry", "t.npz",
            "--allow-unstable", "--rt-priority", "3", "--seed", "7", "--faults", "drop=0.1",
            "--fault-seed", "5", "--no-reconnect", "--lost-timeout", "0.2",
            "--reconnect-attempts", "2", "--reconnect-time", "1.5", "--driver", "haply",
            "--osc", "0", "--osc-ramp", "0.2", "--sound", "jack", "--jack-server", "srv"]
    o = RunOptions.from_args(_parse(*argv), embedded="E")
    assert (o.port, o.baud, o.duration, o.rate_hz) == ("/dev/null", 9600, 2.5, 2000.0)
    assert o.lockstep and o.host_clocked and o.allow_unstable and o.loop == "python"
    assert (o.telemetry, o.rt_priority, o.seed, o.faults, o.fault_seed) == (
        "t.npz", 3, 7, "drop=0.1", 5)
    assert o.reconnect is False and o.lost_timeout == 0.2
    assert (o.reconnect_attempts, o.reconnect_time) == (2, 1.5)
    assert (o.driver, o.osc, o.osc_ramp, o.sound, o.jack_server) == ("haply", 0, 0.2, "jack",
                                                                     "srv")
    assert o.embedded == "E"


@pytest.mark.parametrize("argv, key", [
    (["--rate", "0"], "--rate"), (["--rate", "nan"], "--rate"), (["--rate", "1e12"], "--rate"),
    (["--duration", "-1"], "--duration"), (["--lost-timeout", "0"], "--lost-timeout"),
    (["--reconnect-attempts", "-1"], "--reconnect-attempts"),
    (["--reconnect-time", "inf"], "--reconnect-time"), (["--faults", "nosuch=1"], "--faults"),
    (["--osc", "70000"], "--osc"), (["--osc", "-1"], "--osc"),
    (["--osc-ramp", "-0.1"], "--osc-ramp"), (["--osc-ramp", "nan"], "--osc-ramp"),
    (["--baud", "0"], "--baud"), (["--rt-priority", "100"], "--rt-priority"),
    (["--rt-priority", "-1"], "--rt-priority")])
def test_a_bad_value_is_refused_by_its_declaration_from_both_doors(argv, key):
    """The same check, keyed by the flag, from the command line and from a program."""
    with pytest.raises(ConfigError) as cli:
        RunOptions.from_args(_parse(*argv))
    assert cli.value.key == key
    name = next(f.name for f in command_line_fields() if f.metadata["cli"]["flag"] == argv[0])
    value = getattr(_parse(*argv), name)
    with pytest.raises(ConfigError) as prog:
        RunOptions(**{name: value}).check()
    assert prog.value.key == key and str(prog.value) == str(cli.value)


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


@pytest.mark.parametrize("transport", ["inprocess", "sim"])
def test_a_driver_with_an_in_process_transport_is_refused_naming_the_valid_ones(transport):
    """The in-process transports run hapsim's own mock; a driver's board is reached over a
    port. Every driver asked for one is refused before any work, with the valid choices
    (it was an AttributeError after the whole run: the run had gone to the driver's pty and
    looked for an in-process mock's account)."""
    from hapsim.drivers import DEFAULT, DRIVERS
    assert len(DRIVERS) >= 4                # framed, firefader, haply, hapkit-serial
    for name in DRIVERS:
        if name == DEFAULT:
            continue                # hapsim's own protocol: the in-process mock is its own
        with pytest.raises(ConfigError, match="valid with a driver: pty, serial") as err:
            RunOptions(driver=name, transport=transport,
                       lockstep=transport == "inprocess").check()
        assert err.value.key == "transport"


def test_the_command_prints_what_the_api_returns(monkeypatch, capsys):
    """``hapsim run`` is :func:`hapsim.api.run` with its command line's options: the JSON it
    prints is the API's report, its text the report's ``text()``, its exit code the
    report's; a device lost beyond recovery is said after the report."""
    import json

    from hapsim import api
    from hapsim.cli import main
    from hapsim.pipeline import runner, startup
    from hapsim.errors import DeviceError
    got = {}
    canned = api.run(WALL, lockstep=True, transport="inprocess").to_dict()

    def run_scene(scene, options=None, **kw):
        got["options"] = dataclasses.replace(options, **kw)
        if got.get("lose"):
            exc = DeviceError("gone")
            exc.report = {**canned, "exit_code": 1,
                          "error": {"type": "DeviceError", "message": "gone"}}
            raise exc
        return {**canned, "exit_code": 0}

    calls = []
    real_run = api.run
    monkeypatch.setattr(api, "run", lambda *a, **k: calls.append(a) or real_run(*a, **k))
    monkeypatch.setattr(runner, "run_scene", run_scene)
    monkeypatch.setattr(startup, "start_embedded_mock", lambda *a, **k: None)
    assert main(["run", WALL, "--lockstep", "--duration", "0.5", "--json"]) == 0
    out = capsys.readouterr().out
    assert len(calls) == 1 and json.loads(out) == json.loads(json.dumps(canned))
    o = got["options"]
    # the scene's protocol as named ("framed"): RunOptions.check, inside run_scene, stores
    # hapsim's own protocol as driver None, once
    assert (o.lockstep, o.duration, o.protocol, o.handle_signals) == (True, 0.5, "framed", True)
    assert o.check().driver is None
    assert o.loop in ("compiled", "python")       # 'auto' resolved by the command
    got["lose"] = True
    assert main(["run", WALL, "--lockstep"]) == 1
    cap = capsys.readouterr()
    assert cap.out.strip() == api.RunReport.from_dict(
        {**canned, "error": {"type": "DeviceError", "message": "gone"}}).text()
    assert cap.err.rstrip().endswith("hapsim run: DeviceError: gone")


@pytest.mark.parametrize("scene, argv, key, says", [
    ("wall.yaml", ["--tolerance", "0.5"], "--tolerance", "goes with --auto"),
    ("pantograph_spring.yaml", ["--tolerance", "0.5"], "--tolerance", "does not take"),
    ("wall.yaml", ["--no-reconnect", "--reconnect-time", "3"], "--reconnect-time",
     "--no-reconnect ends the run at a loss"),
    ("wall.yaml", ["--no-reconnect", "--reconnect-attempts", "2"], "--reconnect-attempts",
     "--no-reconnect ends the run at a loss"),
    ("firefader.yaml", ["--frames", "compact"], "--frames", "the firefader protocol's"),
    ("wall.yaml", ["--driver", "haply", "--frames", "full"], "--frames",
     "the haply protocol's"),
    ("wall.yaml", ["--jack-server", "x"], "--jack-server", "without --sound no sound"),
    ("audio_string.yaml", ["--sound", "sounddevice", "--jack-server", "x"],
     "--jack-server", "--sound sounddevice has none"),
    ("wall.yaml", ["--osc-ramp", "0.2"], "--osc-ramp", "neither is given"),
    ("wall.yaml", ["--fault-seed", "3"], "--fault-seed", "none is given")])
def test_an_option_that_would_act_on_nothing_is_refused_by_its_flag(capsys, scene, argv,
                                                                    key, says):
    """An option whose effect another option or the protocol rules out is refused, by
    its flag, before the run starts (exit 2): --tolerance without --auto (the rate
    advice's tolerance, not the verdict's), a recovery's limits with --no-reconnect, the
    framed protocol's --frames through a driver, a JACK server without JACK's sound, a
    ramp of the changes with no --osc or --view to bring any, a fault seed without
    faults. Before, each was taken and ignored."""
    from hapsim.cli import main
    path = str(Path(WALL).parent / scene)
    assert main(["run", path, "--lockstep", *argv]) == 2
    err = capsys.readouterr().err
    assert f"error: {key}: " in err and says in err, err


def test_the_options_that_act_together_still_run(capsys):
    """Their valid company: --auto --tolerance; --reconnect-time without
    --no-reconnect; --frames over the framed protocol."""
    from hapsim.cli import main
    for argv in (["--auto", "--tolerance", "0.05"], ["--reconnect-time", "3"],
                 ["--frames", "full"], ["--fault-seed", "3", "--faults", "dup=0.01"],
                 ["--osc-ramp", "0.2", "--osc", "0"]):
        assert main(["run", WALL, "--lockstep", "--duration", "0.2", *argv]) == 0, argv
        capsys.readouterr()


def test_play_refuses_a_jack_server_without_jacks_sound(capsys):
    """``hapsim play --jack-server NAME`` with ``--sound none`` or ``sounddevice``:
    refused by its flag before anything plays (before: taken and ignored)."""
    from hapsim.cli import main
    path = str(Path(WALL).parent / "string.yaml")
    for sound in ("none", "sounddevice"):
        assert main(["play", path, "--sound", sound, "--jack-server", "x",
                     "--duration", "0.2"]) == 2
        err = capsys.readouterr().err
        assert "--jack-server: names the JACK server" in err and sound in err, err


def test_play_refuses_a_ramp_with_nothing_to_ramp(capsys):
    """``hapsim play --ramp S`` (and :func:`hapsim.play`'s ``ramp``) with neither ``--osc``
    nor ``--view``: no change can come in, so the ramp would act on nothing; refused by
    its flag before anything plays (before: taken and ignored). With ``--osc`` it plays,
    and without ``--ramp`` the default ramp is taken silently."""
    import hapsim
    from hapsim.cli import main
    from hapsim.errors import ConfigError
    base = ["play", WALL, "--sound", "none", "--lockstep", "--duration", "0.05"]
    assert main([*base, "--ramp", "0.2"]) == 2
    err = capsys.readouterr().err
    assert "--ramp: ramps the changes that come in through --osc or --view" in err, err
    with pytest.raises(ConfigError) as info:
        hapsim.play(WALL, sound="none", lockstep=True, duration=0.05, ramp=0.2)
    assert info.value.key == "--ramp"
    assert main(base) == 0 and main([*base, "--ramp", "0.2", "--osc", "0"]) == 0
    capsys.readouterr()


def test_mock_refuses_a_fault_seed_without_faults(capsys):
    """``hapsim mock --fault-seed N`` without ``--faults``, for a 1-D scene, a 2-D one
    and a driver's board: refused by its flag before a port is opened (exit 2)."""
    from hapsim.cli import main
    for scene in ("wall.yaml", "pantograph_wall.yaml", "firefader.yaml"):
        path = str(Path(WALL).parent / scene)
        assert main(["mock", "--scene", path, "--fault-seed", "3"]) == 2, scene
        cap = capsys.readouterr()
        assert "PORT" not in cap.out and "error: --fault-seed: " in cap.err, (scene, cap)


@pytest.mark.parametrize("field", [f.name for f in command_line_fields()])
def test_a_value_of_the_wrong_kind_is_refused_by_the_fields_flag(field):
    """Every command-line field of :class:`RunOptions` given a value its flag cannot
    give (a list where a number or a text goes, a dict, a number for a text, a text for
    a flag): a ConfigError keyed by the flag at the check, before anything starts
    (before: a list for ``rate_hz`` or a number for ``telemetry`` was a TypeError in
    the run, a number for ``faults`` an AttributeError)."""
    meta = next(f for f in command_line_fields() if f.name == field).metadata["cli"]
    for value in ([1, 2], {"a": 1}, 2.5, "x"):
        is_number = hasattr(meta["type"], "check")
        if (is_number and value == 2.5) or (not is_number and meta["action"] is None
                                             and value == "x"):
            continue                    # (the kind it takes: its own checks apply)
        with pytest.raises(ConfigError) as info:
            RunOptions(**{field: value}).check()
        assert info.value.key == meta["flag"], (field, value, info.value.key)

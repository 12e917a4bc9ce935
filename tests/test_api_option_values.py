"""The API and the command line refuse a bad value with the same message.

Every numeric option a command shares with its :mod:`hapsim.api` function (and every
field of :class:`~hapsim.analysis.loop.LoopModel` behind ``--mass --friction --rate
--delay``) is declared once, in :data:`hapsim.option_values.API_OPTIONS`; the class of
values outside each declared range (below, above, not finite, not whole) is tried through
both doors: ``hapsim COMMAND ... --json`` and the function."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import pytest

from hapsim import api
from hapsim.analysis.loop import MAX_DELAY, LoopModel
from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.option_values import API_OPTIONS, Number, declared

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
WALL = str(CONFIGS / "wall.yaml")
LOOP = ["--mass", "0.1", "--rate", "1000"]

#: Each declared function: the command line before the option (a valid rest), and the
#: function called with one keyword changed.
DOORS = {
    "loop": (["render", "--mass", "0.1", "--rate", "1000", "--K", "1"],
             lambda **kw: LoopModel(**{"mass": 0.1, "rate_hz": 1000.0, **kw})),
    "render": (["render", *LOOP, "--K", "1"],
               lambda **kw: api.render(LoopModel(0.1), **{"K": 1.0, **kw})),
    "calibrate": (["calibrate", *LOOP, "--k", "100", "--b", "1"],
                  lambda **kw: api.calibrate(LoopModel(0.1), **{"k": 100.0, "b": 1.0, **kw})),
    "stability": (["stability", *LOOP], lambda **kw: api.stability(LoopModel(0.1), **kw)),
    "family": (["family", WALL], lambda **kw: api.family(WALL, **kw)),
    "identify": (["identify"], lambda **kw: (
        api.calibrate_scale(None, None, kw["added_mass"], None) if "added_mass" in kw
        else api.identify(**kw))),
    "run_nd": (["run", str(CONFIGS / "pantograph_wall.yaml"), "--lockstep"],
               lambda **kw: api.run_nd(str(CONFIGS / "pantograph_wall.yaml"), **kw)),
    "play": (["play", WALL, "--sound", "none", "--lockstep"],
             lambda **kw: api.play(WALL, sound="none", lockstep=True, **kw)),
}


def _bad_values(n: Number) -> list:
    """Values outside ``n``'s range: just past each bound, far past it, not finite, and
    (for an integer) not whole."""
    out = [math.nan, math.inf, -math.inf]
    if n.low is not None:
        out += [n.low if n.open_low else n.low - 1, n.low - 1e6]
    if n.high is not None:
        out += [n.high if n.open_high else n.high + 1, n.high + 1e6]
    if n.kind is int:
        mid = (n.low or 0) + 0.5
        if n.ok(math.floor(mid)):
            out.append(mid)
    return out


CASES = [(fn, name, v) for fn, table in API_OPTIONS.items() for name, (_, n) in table.items()
         for v in _bad_values(n)]


def _cli(argv: list) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main(argv + ["--json"])
    assert code == 2, (argv, out.getvalue())
    return json.loads(out.getvalue())["error"]


def _typed(v) -> str:
    """``v`` as a user types it (``repr`` of a float: ``nan``, ``inf``, ``-1.0``)."""
    return repr(float(v)) if isinstance(v, float) else str(v)


def test_every_command_option_of_the_table_is_its_declaration():
    """The parsers take these options' types from the table (not a copy of the range)."""
    import argparse

    from hapsim.cli import build_parser
    for fn, (argv, _) in DOORS.items():
        parser = build_parser(argv[0])
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        actions = {o: a for a in sub.choices[argv[0]]._actions for o in a.option_strings}
        for name, (flag, n) in API_OPTIONS[fn].items():
            assert actions[flag].type is declared(fn, name), (fn, flag)
    assert declared("loop", "delay").high == MAX_DELAY     # the analysis's limit


@pytest.mark.parametrize("fn, name, value", CASES,
                         ids=[f"{f}-{n}-{v!r}" for f, n, v in CASES])
def test_a_bad_value_gets_the_same_message_through_both_doors(fn, name, value):
    flag, _ = API_OPTIONS[fn][name]
    argv, call = DOORS[fn]
    err = _cli([*argv, f"{flag}={_typed(value)}"])
    with pytest.raises(ConfigError) as prog:
        call(**{name: value})
    assert err["key"] == flag
    if fn == "loop":      # the model keys by its field, the command by the flag
        assert prog.value.key == name and prog.value.reason in err["message"]
        assert err["message"].endswith(f"{flag}: {prog.value.reason}")
    else:
        assert prog.value.key == flag
        assert err["message"] == f"hapsim {argv[0]}: error: {prog.value}"


@pytest.mark.parametrize("value", ["2", True, None.__class__, [1]])
def test_a_value_that_is_no_number_is_refused_with_the_range(value):
    """From a program, a string, a bool or another object is a ConfigError naming the
    range, not a TypeError from the comparison."""
    with pytest.raises(ConfigError, match=r"--grid: must be an integer >= 2"):
        api.family(WALL, grid=value)


def test_an_unknown_driver_gets_the_same_reason_through_both_doors():
    """``hapsim identify --driver`` and :func:`hapsim.api.identify`'s ``driver`` refuse an
    unregistered name by the registry (:func:`hapsim.drivers.family`): the same reason,
    listing every registered 1-D driver, keyed by the flag and by the keyword."""
    from hapsim.drivers import DRIVERS
    err = _cli(["identify", "--driver", "nope"])
    with pytest.raises(ConfigError) as prog:
        api.identify(driver="nope")
    assert err["key"] == "--driver" and prog.value.key == "driver"
    assert prog.value.reason == f"unknown driver 'nope'; valid: {', '.join(DRIVERS)}"
    assert err["message"].endswith(f"--driver: {prog.value.reason}")


#: Values a program may pass where a number is meant: none is one.
NOT_NUMBERS = [None, "x", [1.0, 2.0], {"kind": "velocity_filter"}, True]


@pytest.mark.parametrize("value", NOT_NUMBERS, ids=repr)
@pytest.mark.parametrize("fn, args, at", [("render", (1000.0, 1.0), 0),
                                          ("render", (1000.0, 1.0), 1),
                                          ("calibrate", (1000.0, 1.0), 0),
                                          ("calibrate", (1000.0, 1.0), 1),
                                          ("stability", (1.0,), 0)])
def test_the_loop_functions_refuse_what_is_no_number_by_its_key(fn, args, at, value):
    """``render``, ``calibrate``, ``stability`` with None, a word, a list, a mapping or a
    bool where (K, B) or (k, b) go: a ConfigError keyed by the flag (before: a TypeError
    from ``float()`` for None and a list)."""
    loop = LoopModel(mass=0.1, friction=0.5)
    args = list(args)
    args[at] = value
    with pytest.raises(ConfigError) as info:
        getattr(api, fn)(loop, *args)
    assert info.value.key in ("--K", "--B", "--k", "--b"), info.value.key


@pytest.mark.parametrize("value", NOT_NUMBERS + [math.nan], ids=repr)
@pytest.mark.parametrize("name", ["mass", "friction", "rate_hz", "delay", "hand_mass",
                                  "hand_damping", "grip_stiffness", "grip_damping",
                                  "stiffness"])
def test_a_loop_model_refuses_what_is_no_number_by_its_field(name, value):
    """Every numeric field of :class:`LoopModel` against the same values and NaN: a
    ConfigError keyed by the field, at construction (before: a grip stiffness of NaN
    made the hand rigid, of a word a ValueError later)."""
    with pytest.raises(ConfigError) as info:
        LoopModel(**{"mass": 0.1, "friction": 0.5, name: value})
    assert info.value.key == name, (info.value.key, str(info.value))


@pytest.mark.parametrize("value", [1.0, "velocity_filter", [1, 2], True])
def test_a_loop_models_correction_is_a_correction_or_its_mapping(value):
    """``correction``: a Correction or its mapping; anything else refused by its key
    (before: taken, then an AttributeError in every analysis); the mapping is read."""
    with pytest.raises(ConfigError) as info:
        LoopModel(mass=0.1, friction=0.5, correction=value)
    assert info.value.key == "correction"
    loop = LoopModel(mass=0.1, friction=0.5,
                     correction={"kind": "velocity_filter", "cutoff_hz": 100.0})
    assert loop.correction.kind == "velocity_filter"
    assert api.render(loop, 1000.0, 1.0).k > 0


@pytest.mark.parametrize("hold", [None, 1, ["zoh"], "ZOH"], ids=repr)
def test_a_hold_that_is_no_holds_name_is_refused_in_every_dimension(hold):
    """``hold`` not one of the names (an array compared with them was a ValueError from
    numpy's truth value, a list a TypeError): a ConfigError keyed ``hold``, in 1-D
    (:class:`LoopModel`) and n-D (:class:`~hapsim.analysis.ths.matrix_loop.MatrixLoop`)."""
    import numpy as np

    from hapsim.analysis.ths.matrix_loop import MatrixLoop
    for value in (hold, np.array(["zoh", "ideal"])):
        with pytest.raises(ConfigError) as info:
            LoopModel(mass=0.1, friction=0.5, hold=value)
        assert info.value.key == "hold"
        with pytest.raises(ConfigError) as info:
            MatrixLoop(mass=np.eye(2) * 0.1, friction=np.eye(2) * 0.5, hold=value)
        assert info.value.key == "hold"


@pytest.mark.parametrize("key, value, flag", [
    ("device", 1.0, "device"), ("device", {"mass": 0.1}, "device"),
    ("lockstep", "x", "--lockstep"), ("hand", 2.5, "--hand"),
    ("driver_options", "x", "--protocol-option"), ("mock_options", [1], "--mock-option"),
    ("rt_priority", "x", "--rt-priority"), ("rt_priority", 100, "--rt-priority")])
def test_identify_refuses_a_keyword_of_the_wrong_kind_before_it_starts(key, value, flag):
    """:func:`hapsim.api.identify` with a device that is no Device, a flag that is no
    bool, options that are no mapping, a priority that is no whole number in 0..99: a
    ConfigError keyed by the command's flag, before the embedded mock starts (before: a
    TypeError from ``dataclasses.asdict``; the rest taken: ``lockstep="x"`` as True,
    ``rt_priority="x"`` passed on)."""
    with pytest.raises(ConfigError) as info:
        api.identify(**{"lockstep": True, "duration": 0.5, key: value})
    assert info.value.key == flag, (info.value.key, str(info.value))


@pytest.mark.parametrize("key, flag", [("grid", "--grid"), ("certify", "--certify-boxes"),
                                       ("seed", "--seed")])
def test_family_requires_the_numbers_that_have_defaults(key, flag):
    """``family(scene, grid=None)`` (or ``certify``, ``seed``): refused by the flag with
    the range (before: a TypeError from ``int()`` or a comparison with None); ``samples``
    None still means the grid."""
    scene = api.load_scene(str(CONFIGS / "hand_wall.yaml"))
    with pytest.raises(ConfigError) as info:
        api.family(scene, **{key: None})
    assert info.value.key == flag


def test_simulate_refuses_a_progress_that_is_no_function():
    """``simulate(scene, steps, progress="x")``: refused by its key before the first
    sample (before: a TypeError in the middle of the run)."""
    with pytest.raises(ConfigError) as info:
        api.simulate(WALL, 10, progress="x")
    assert info.value.key == "progress"


@pytest.mark.parametrize("value", [1.0, None, [1, 2], {"a": 1}], ids=repr)
def test_a_scene_that_is_no_scene_is_refused_by_its_key(value):
    """``check_nd``, ``modes_nd``, ``run`` and ``family`` given a number, None, a list
    or a mapping for the scene: a ConfigError keyed ``scene`` (before: an AttributeError
    deep in the analysis)."""
    for call in (lambda: api.check_nd(value), lambda: api.modes_nd(value),
                 lambda: api.run(value, lockstep=True),
                 lambda: api.family(value)):
        with pytest.raises(ConfigError) as info:
            call()
        assert info.value.key == "scene", str(info.value)


def test_run_refuses_options_that_are_no_run_options_and_n_d_wants_an_amplitude():
    """``run(scene, options="x")``: keyed ``options`` (a TypeError from
    ``dataclasses.replace``); ``run_nd(scene, None)``: keyed ``--amplitude`` (a
    TypeError from ``float()``); ``check_nd`` with a progress that is no function."""
    with pytest.raises(ConfigError) as info:
        api.run(WALL, options="x")
    assert info.value.key == "options"
    nd = str(CONFIGS / "pantograph_spring.yaml")
    with pytest.raises(ConfigError) as info:
        api.run_nd(nd, None)
    assert info.value.key == "--amplitude"
    with pytest.raises(ConfigError) as info:
        api.check_nd(nd, progress="x")
    assert info.value.key == "progress"

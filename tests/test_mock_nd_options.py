"""``hapsim mock --scene`` on a 2-D or 3-D scene: every option of ``hapsim mock`` is either
taken by the n-D mock or refused by name with exit 2 (never accepted and ignored)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from hapsim.cli import build_parser, main
from hapsim.commands.mock import FIRMWARE_TAKES, TAKES, TICKS

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
SCENES = [CONFIGS / "pantograph_wall.yaml"]


def _mock_options():
    """(flag, dest, a value to give or None for a switch) of every ``hapsim mock`` option."""
    parser = build_parser("mock")
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = []
    for act in sub.choices["mock"]._actions:
        if not act.option_strings or isinstance(act, argparse._HelpAction):
            continue
        flag = max(act.option_strings, key=len)
        if act.nargs == 0:
            value = None
        elif act.choices:
            value = [c for c in act.choices if c != act.default][0]
        elif act.type is not None:          # a number (int, float or a checked range)
            value = "3"
        else:
            value = "x"
        out.append((flag, act.dest, value))
    return out


OPTIONS = _mock_options()


def test_the_option_list_is_the_parser_s():
    """The enumeration sees the options the n-D mock takes and the ones it refuses (a new
    ``hapsim mock`` option lands in one of the two tests below by construction)."""
    dests = {d for _, d, _ in OPTIONS}
    assert TAKES - {"scene"} <= dests
    assert {"seed", "fault_seed", "faults", "tick", "firmware", "link"} <= dests


@pytest.mark.parametrize("flag,dest,value",
                         [o for o in OPTIONS if o[1] not in TAKES | {"firmware"}],
                         ids=lambda o: str(o))
def test_an_option_not_taken_is_refused_by_name(flag, dest, value, capsys, monkeypatch):
    """Given on a 2-D scene, an option the n-D mock does not take exits 2 before any pty
    is opened, its flag named on stderr."""
    from hapsim.commands import mock as mock_cmd

    def served(*a, **k):
        raise AssertionError(f"{flag} accepted: the mock opened its pty")
    monkeypatch.setattr(mock_cmd, "_new_pty", served)
    argv = ["mock", "--scene", str(SCENES[0]), flag] + ([] if value is None else [value])
    assert main(argv) == 2
    err = capsys.readouterr()
    # the n-D mock's refusal (not argparse's, nor a range check's)
    assert f"does not take {flag}" in err.err and "PORT" not in err.out


@pytest.mark.parametrize("tick", ["compiled"])
def test_a_tick_not_taken_is_refused(tick, capsys, monkeypatch):
    """``--tick`` is taken with the Python ticks only (what the n-D mock runs)."""
    from hapsim.commands import mock as mock_cmd
    monkeypatch.setattr(mock_cmd, "_new_pty", None)
    assert tick not in TICKS
    assert main(["mock", "--scene", str(SCENES[0]), "--tick", tick]) == 2
    assert "--tick" in capsys.readouterr().err


def test_the_refusal_reads_the_namespace_not_a_list():
    """:func:`hapsim.commands.mock.refuse_untaken` refuses any destination outside
    :data:`TAKES` that was given, and passes the taken ones and the ones not given."""
    from hapsim.commands.mock import refuse_untaken
    from hapsim.errors import ConfigError
    given = {d: 1 for d in TAKES} | {"tick": "python", "func": print, "command": "mock",
                                      "seed": None, "firmware": False}
    refuse_untaken(argparse.Namespace(**given))
    with pytest.raises(ConfigError, match="--some-new-option"):
        refuse_untaken(argparse.Namespace(**given, some_new_option=0))


@pytest.mark.parametrize("flag,dest,value",
                         [o for o in OPTIONS if o[1] not in FIRMWARE_TAKES],
                         ids=lambda o: str(o))
def test_an_option_the_emulated_pantograph_does_not_take_is_refused(flag, dest, value, capsys):
    """``--firmware`` on a 2-D scene selects the emulated Hapkit pantograph
    (:func:`hapsim.commands.mock.run_pantograph_firmware`): any other option given
    exits 2, named, before anything is built or opened."""
    argv = ["mock", "--scene", str(SCENES[0]), "--firmware", "--lockstep", flag]
    argv += [] if value is None else [value]
    assert main(argv) == 2
    err = capsys.readouterr()
    assert f"does not take {flag}" in err.err and "PORT" not in err.out


def test_options_at_their_defaults_are_not_refused():
    """``hapsim mock --scene <2-D scene>`` with nothing else, and with ``--firmware
    --lockstep``, is not refused: an option at its parser default (a new option's 0.0,
    say) was not given (a ``--spin-us`` default of 0.0 once made every 2-D mock refuse)."""
    from hapsim.commands.mock import refuse_untaken, refuse_untaken_firmware
    parser = build_parser("mock")
    args = parser.parse_args(["mock", "--scene", str(SCENES[0])])
    refuse_untaken(args)
    args = parser.parse_args(["mock", "--scene", str(SCENES[0]), "--firmware", "--lockstep"])
    args.rt_priority = 0                    # what hapsim mock sets in lockstep
    refuse_untaken_firmware(args)

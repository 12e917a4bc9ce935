"""Faults with a lockstep mock (:meth:`hapsim.emulated.faults.FaultPlan.lockstep_refusal`).

A lockstep mock ticks on the host's FORCE and has no clock of its own. Before, ``hapsim
run --lockstep --faults drop=0.05`` (or corrupt, garbage, reorder, their ``rx.`` twins)
ran for 10 s and said the device was lost: the STATE the host waited for was gone and the
mock waited for the FORCE answering it. ``reset@100``, ``stall@...``, ``vanish@...`` and
every fault drawn per tick never fired (``injected: {}``), the run said "within" as if
none had been asked; a 2-D or 3-D lockstep run took ``--faults`` and ignored them all.
Now the faults a lockstep mock can take (a frame repeated or delayed; ``nohello``) run,
and the others are refused before anything starts, naming them and what takes them.
"""

from __future__ import annotations

import pytest

from hapsim.emulated.faults import FAULT_NAMES, LOCKSTEP_FAULTS, parse_faults
from hapsim.errors import ConfigError

WALL = "configs/wall.yaml"


def _specs():
    """Every fault name at a rate (or alone: ``nohello``) and every schedulable one at a
    tick, with whether a lockstep mock takes it."""
    out = []
    for name in FAULT_NAMES:
        if name == "nohello":
            out.append(("nohello", True))
            continue
        out.append((f"{name}=0.05", name in LOCKSTEP_FAULTS))
        out.append((f"{name}@100", False))
    return out


@pytest.mark.parametrize("spec, takes", _specs(), ids=[s for s, _ in _specs()])
def test_a_lockstep_mock_takes_exactly_the_faults_it_can_fire(spec, takes):
    """The rule over every fault: a rate of a repeat or a delay, or ``nohello``, is
    taken; anything else, and anything at a tick, is refused by name with the faults a
    lockstep mock takes; a mock on its own clock takes them all."""
    plan = parse_faults(spec, 0)
    why = plan.lockstep_refusal()
    assert (why is None) == takes, (spec, why)
    if not takes:
        assert why.startswith(spec.replace("=0.05", "") + ": not with a lockstep mock")
        assert "dup=RATE, spike=RATE, rx.dup=RATE, rx.spike=RATE, nohello" in why


@pytest.mark.parametrize("spec", ["drop=0.05", "reset@100", "rx.corrupt=0.01,dup=0.05"])
def test_a_1d_lockstep_run_refuses_what_its_mock_cannot_take_before_it_starts(spec):
    """Through :func:`hapsim.pipeline.runner.run_scene` (``hapsim run``'s pipeline):
    refused at the options' check, keyed ``--faults``, with nothing started."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    with pytest.raises(ConfigError) as info:
        run_scene(load_scene(WALL), lockstep=True, faults=spec, duration=0.3,
                  handle_signals=False)
    assert info.value.key == "--faults" and "not with a lockstep mock" in str(info.value)


@pytest.mark.parametrize("spec", [f"{n}=0.05" for n in LOCKSTEP_FAULTS])
def test_the_faults_a_lockstep_mock_takes_fire_and_the_run_ends(spec):
    """Each fault a lockstep mock takes is injected (counted) in a 1-D lockstep run over
    the embedded mock, which ends at its duration (no loss, no 10 s wait) with the
    verdict of the same run without faults: a repeated frame is stale, a delayed one
    comes later, neither changes a lockstep record."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    rep = run_scene(load_scene(WALL), lockstep=True, faults=spec, duration=0.3,
                    handle_signals=False)
    assert rep["exit_code"] == 0
    assert rep["loop"]["lost"] == 0 and rep["loop"]["ticks"] == 300
    plan = rep["loop"]["fault_plan"]
    assert plan["injected"].get(spec.split("=")[0], 0) > 0, plan
    assert rep["verdict"] == "within", rep["reason"]


def test_an_n_d_lockstep_run_refuses_faults_it_would_ignore():
    """A 2-D scene's lockstep run closes its loop in process: ``faults`` is refused
    (keyed by the field through the API), where it was taken and ignored."""
    from hapsim import load_scene
    from hapsim.api import run
    with pytest.raises(ConfigError) as info:
        run(load_scene("configs/pantograph_spring.yaml"), lockstep=True, faults="dup=0.05")
    assert info.value.key == "faults" and "no wire to fault" in str(info.value)

"""A real-time 2DIY run (``hapsim run SCENE --driver haply``) says before its loop what its
records cannot state, and never states it (issue 31 item 4): the prediction is the same
records' verdict in lockstep (:func:`hapsim.emulated.haply2_lockstep.measure_felt_haply2`,
the emulated board on its lockstep clock, named), its excluded statements passed to the
real-time verdict (:func:`hapsim.commands.run_haply2.prediction_haply2`).
"""

from __future__ import annotations

import json
from pathlib import Path

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _pre(statements, reason="r"):
    return {"statements": [{"name": n, "verdict": v, "reason": f"why {n}"}
                           for n, v in statements],
            "not_stated": [n for n, v in statements if v == "not measurable"],
            "reason": reason}


def test_the_prediction_excludes_what_the_lockstep_records_do_not_state():
    """Every statement the lockstep records do not make is excluded with one reason and
    named, with its own reason, in the sentence; nothing excluded: no sentence; nothing
    stated: "not measurable"."""
    from hapsim.commands.run_haply2 import prediction_haply2
    ex, said = prediction_haply2(_pre([("felt stiffness", "within"),
                                       ("felt damping", "not measurable")]), 1e-4)
    assert list(ex) == ["felt damping"]
    assert said.startswith("felt matrices partly measurable, predicted before the run")
    assert "not stated: felt damping: felt damping: why felt damping" in said
    ex, said = prediction_haply2(_pre([("felt stiffness", "differs")]), 1e-4)
    assert ex == {} and said is None
    ex, said = prediction_haply2(_pre([("felt stiffness", "not measurable"),
                                       ("felt damping", "not measurable")]), 1e-4)
    assert set(ex) == {"felt stiffness", "felt damping"}
    assert said.startswith("felt matrices not measurable, predicted before the run")


def test_hapsim_run_says_first_and_never_states_what_it_excluded(capsys):
    """configs/pantograph_wall.yaml through the emulated 2DIY in real time (its own clock)
    at a start of 0.01 mm (a fortieth of the default, too small for the damping: at
    0.1 mm the rounding's term states it, :mod:`hapsim.analysis.wire_rounding`): exit 0;
    on stderr, before the report, the damping's statements the lockstep records
    do not make, with their reasons; the run's JSON repeats the sentence and states none
    of them ("not measurable"), whatever the host's timing did to its records (exit 1
    only where it made the joints leave the envelope: a safety stop, as every run's)."""
    from hapsim.cli import main
    code = main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--driver", "haply",
                 "--amplitude", "1e-5", "--json"])
    cap = capsys.readouterr()
    assert code == int(any(v >= 0 for v in json.loads(cap.out)["left"])), cap.out
    said = [x for x in cap.err.splitlines() if "predicted before the run" in x]
    assert len(said) == 1 and "not stated: felt damping" in said[0], cap.err
    out = json.loads(cap.out)
    assert said[0].split(": ", 2)[2].startswith(out["stated_before_run"])
    excluded = out["not_stated_before_run"]
    assert "felt damping" in excluded
    for st in out["statements"]:
        if st["name"] in excluded:
            assert st["verdict"] == "not measurable", st
    assert out["verdict"] in ("partly within", "not measurable"), out["reason"]

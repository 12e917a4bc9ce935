"""One verdict in every dimension's ``run --json`` (issue 30: "1-D ``run --json`` puts the
verdict under ``measured``, n-D at the top level"): a 1-D report now has, at its top level,
the keys a 2-D/3-D report has there — ``verdict`` ("within", "differs", "not measurable"),
``within`` (True, False, None) and ``reason`` — read from the 1-D measurement's own
sentence (:func:`hapsim.pipeline.report.verdict_summary`), which stays under ``measured``.
"""

from __future__ import annotations

import dataclasses

import pytest

from hapsim.api import RunReport
from hapsim.api import RunReportND
from hapsim.pipeline.report import verdict_summary

#: Every sentence the 1-D measurement can end on, with the verdict it is (the writers:
#: hapsim/analysis/measurement.py, hapsim/pipeline/runner.py timing_verdict,
#: hapsim/host/link_verdict.py, hapsim/audio/journal.py, an identification's error).
CASES = [
    ({"within": True, "verdict": "measured = predicted within the stated uncertainty"},
     "within", True),
    ({"within": False, "verdict": "measured differs from predicted by more than the "
                                  "stated uncertainty"}, "differs", False),
    # not measurable sets within False in 1-D: the word must not read it as "differs"
    ({"within": False, "comparable": False,
      "verdict": "not measurable: the host missed its deadline in 90 of 1000 ticks"},
     "not measurable", None),
    ({"verdict": "not comparable: contact 'pluck' opens at sample 37"},
     "not measurable", None),
    ({"error": "not identified: the device hardly moved"}, "not measurable", None),
    ({}, "not measurable", None),
]


@pytest.mark.parametrize("measured, word, within", CASES)
def test_the_top_level_verdict_is_the_measurements(measured, word, within):
    v = verdict_summary(measured)
    assert (v["verdict"], v["within"]) == (word, within)
    assert v["reason"] == (measured.get("verdict") or measured.get("error")
                           or "nothing was measured")


def test_both_reports_carry_the_same_verdict_keys():
    """The three keys are fields of both dimensions' reports, always written (a "not
    measurable" has ``within`` null in both, never a missing key)."""
    keys = {"verdict", "within", "reason"}
    for cls in (RunReport, RunReportND):
        names = {f.name for f in dataclasses.fields(cls)}
        assert keys <= names, cls
        assert not keys & set(cls._OPTIONAL), cls


def test_a_1d_run_report_has_them(shipped_lockstep_run):
    """A 1-D lockstep run of configs/wall.yaml, in process: the keys at the top level of
    ``--json`` (``RunReport.to_dict``) agree with ``measured``."""
    from pathlib import Path
    rep, _ = shipped_lockstep_run(Path(__file__).resolve().parents[1] / "configs" / "wall.yaml")
    rep.pop("exit_code")
    d = RunReport.from_dict(rep).to_dict()
    assert (d["verdict"], d["within"]) == ("within", True)
    assert d["reason"] == d["measured"]["verdict"]

"""``tools/driver_timing.py``'s summary of the felt statements (what the docs' driver table
reads through its macros): per driver and loss, the runs that stated each felt matrix and
the ranges of their deviation, of the uncertainty stated, of the wire's term and of the
estimated samples, recomputed from the runs alone (``--resummarize``)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _tool():
    """tools/driver_timing.py as a module (its sibling tools/provenance.py importable)."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        spec = importlib.util.spec_from_file_location("driver_timing",
                                                      ROOT / "tools" / "driver_timing.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(ROOT / "tools"))
    return mod


def _row(seed, dev, unc, wire, estimated, loss=0.005):
    return {"driver": "haply2", "loss": loss, "seed": seed, "verdict": "partly within",
            "deviation": {"felt_stiffness": dev[0], "felt_damping": dev[1]},
            "uncertainty": {"felt_stiffness": unc[0], "felt_damping": unc[1]},
            "wire_term": {"felt_stiffness": wire[0], "felt_damping": wire[1]},
            "estimated": estimated, "resyncs": 1, "excursion_true": 0.01}


def test_the_felt_ranges_are_the_runs_own(tmp_path):
    """Three runs: the damping stated in one only, one wire term infinite (nothing stated
    there: left out of the range), and a 1-D row without felt figures, which adds no
    felt key. The ranges are the runs' own minima and maxima, exactly (no arithmetic on
    them); ``--resummarize`` writes the same summary back from the file's runs."""
    t = _tool()
    rows = [_row(1, (0.002, 0.01), (0.05, None), (0.02, 0.4), 200),
            _row(2, (0.001, 0.03), (0.07, 0.6), (0.03, float("inf")), 310),
            _row(3, (0.004, 0.02), (0.04, None), (0.01, 0.9), 250),
            {"driver": "firefader", "loss": 0.005, "seed": 1, "verdict": "within",
             "resyncs": 0}]
    s = t.summarize(rows)
    h = s["haply2 0.005"]
    assert h["stated_k"] == 3 and h["stated_b"] == 1
    assert h["dev_k"] == [0.001, 0.004] and h["unc_k"] == [0.04, 0.07]
    assert h["dev_b"] == [0.03, 0.03] and h["unc_b"] == [0.6, 0.6]
    assert h["wire_k"] == [0.01, 0.03] and h["wire_b"] == [0.4, 0.9]
    assert h["estimated"] == [200, 310]
    assert not {"stated_k", "dev_k", "estimated"} & set(s["firefader 0.005"])
    path = tmp_path / "timing.json"
    path.write_text(json.dumps({"runs": rows, "summary": {}}))
    assert t.resummarize(str(path)) == json.loads(json.dumps(s))
    assert json.loads(path.read_text())["summary"] == json.loads(json.dumps(s))

"""tools/suite_time.py's timeline of a run (docs/testing.md, 'Where the wall clock went'):
over random runs laid out worker by worker, it finds the start-up, each worker's time in
tests and idle end, and each group's chain, as the layout made them."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from suite_time import REPO, _asked_json, timeline  # noqa: E402


def _run(rng):
    """A run laid out by hand: each worker starts after a start-up and runs its tests back
    to back (gaps of up to 0.1 s between them); some tests carry a group, all of a group on
    one worker. Returns the --cpu-time-json content and what the layout decided."""
    t0 = 1.7e9 + float(rng.uniform(0, 1e6))
    start_up = float(rng.uniform(1, 60))
    tests, want = {}, {"workers": {}, "groups": {}}
    for w in range(int(rng.integers(1, 5))):
        name = f"gw{w}"
        t = t0 + start_up + float(rng.uniform(0, 2))
        first, busy = t, 0.0
        group = f"g{w}" if rng.random() < 0.7 else None
        for i in range(int(rng.integers(1, 40))):
            wall = float(rng.exponential(3.0))
            nodeid = f"tests/test_{w}.py::test_{i}"
            if group is not None and i < 5:
                nodeid += f"@{group}"
                g = want["groups"].setdefault(group, {"start": t, "wall": 0.0, "n": 0})
                g["wall"] += wall
                g["n"] += 1
                g["end"] = t + wall
            tests[nodeid] = {"wall": wall, "cpu": 0.0, "children": 0.0, "worker": name,
                             "end": t + wall}
            busy += wall
            t += wall + float(rng.uniform(0, 0.1))
        want["workers"][name] = {"first": first - t0, "last": tests[nodeid]["end"] - t0,
                                 "busy": busy, "n": i + 1}
    last = max(w["last"] for w in want["workers"].values())
    first = min(w["first"] for w in want["workers"].values())
    run = {"session_start": t0, "session_end": t0 + last + 2.5, "tests": tests,
           "load": [0, 0, 0], "session_wall": last + 2.5}
    return run, want, first, last


@pytest.mark.parametrize("seed", range(20))
def test_the_timeline_is_the_runs_layout(seed):
    """Start-up, tests and after; per worker its tests, seconds in tests, first start,
    last end and idle end (the run's last end minus its own); per group its worker, tests,
    seconds and span. The tool rounds to 0.1 s: compared within half of that."""
    rng = np.random.default_rng(seed)
    run, want, first, last = _run(rng)
    tl = timeline(run)
    # derived: the tool rounds to 0.1 s (error <= 0.05) after subtracting epoch times of
    # ~1.7e9 s (binary64 spacing 2.4e-7 s), hence 0.05 + 1e-6
    half = 0.05 + 1e-6
    assert tl["start_up_s"] == pytest.approx(first, abs=half)
    assert tl["tests_s"] == pytest.approx(last - first, abs=half)
    assert tl["after_s"] == pytest.approx(2.5, abs=half)
    assert set(tl["workers"]) == set(want["workers"])
    for name, w in want["workers"].items():
        got = tl["workers"][name]
        assert got["tests"] == w["n"]
        assert got["busy_s"] == pytest.approx(w["busy"], abs=half)
        assert got["first_start_s"] == pytest.approx(w["first"], abs=half)
        assert got["last_end_s"] == pytest.approx(w["last"], abs=half)
        assert got["idle_end_s"] == pytest.approx(last - w["last"], abs=half)
    assert set(tl["groups"]) == set(want["groups"])
    for name, g in want["groups"].items():
        got = tl["groups"][name]
        assert got["worker"] == f"gw{name[1:]}" and got["tests"] == g["n"]
        assert got["wall_s"] == pytest.approx(g["wall"], abs=half)
        assert got["start_s"] == pytest.approx(g["start"] - run["session_start"], abs=half)
        assert got["end_s"] == pytest.approx(g["end"] - run["session_start"], abs=half)


def test_a_run_without_end_times_has_no_timeline():
    """A --cpu-time-json of a suite that did not record end times (before 2026-11-24's
    sixth pass) gives None, not a timeline made up from nothing."""
    assert timeline({"tests": {"t.py::a": {"wall": 1.0, "cpu": 0.5, "children": 0.0,
                                             "worker": "gw0"}}}) is None
    assert timeline({"tests": {}}) is None


def test_the_figures_are_read_where_the_pytest_arguments_put_them():
    """``-- --cpu-time-json=X`` (or ``--cpu-time-json X``; the last one counts, as in
    pytest) is where the summary reads the run's figures, relative to the repository
    where pytest runs; without it, None (the tool's own temporary file)."""
    assert _asked_json(["-p", "no:cacheprovider"]) is None
    assert _asked_json(["--cpu-time-json=a.json"]) == str(REPO / "a.json")
    assert _asked_json(["--cpu-time-json", "/x/b.json", "--cpu-time-json=c.json"]) == \
        str(REPO / "c.json")
    assert _asked_json(["--cpu-time-json=/x/b.json"]) == "/x/b.json"

"""A run whose device left its workspace, or whose board was re-synchronised more than the
stated bound, never says "within" (issue 29 item 2; hapsim.daemon.link_verdict)."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.daemon import link_verdict as lv


def test_the_rule_over_random_runs():
    """Random runs (length, rate, re-synchronisations, safety stop, a framed or a driver
    link, the measurement's own verdict): "within" survives exactly when the measurement
    said it, no safety stop ended the run and the re-synchronisations stay within the
    bound, computed here independently (blind share 10 % of the run at 2 ms each:
    50 a second, floored, at least 1); the link fails the run (exit 1) exactly when they
    exceed it."""
    rng = np.random.default_rng(29)
    seen = {"failed": 0, "stopped": 0, "kept": 0}
    for _ in range(2000):
        rate = float(rng.choice([250.0, 500.0, 1000.0, 2000.0]))
        ticks = int(rng.integers(0, 6000))
        framed = rng.random() < 0.2
        resyncs = int(rng.integers(0, 3 * (ticks / rate) * 50 + 3))
        stop = bool(rng.random() < 0.3)
        within = bool(rng.random() < 0.7)
        loop = {"ticks": ticks, "rate_hz": rate, "safety_stop": stop,
                "stop_reason": "safety: position 0.2 m beyond +-0.1 m" if stop else "duration",
                "driver": None if framed else {"resyncs": resyncs}}
        measured = {"within": within, "verdict": "measured = predicted" if within else "differs"}
        failed = lv.link_verdict(measured, loop)
        bound = max(1, (50 * ticks) // int(rate))      # exact integer arithmetic
        over = (not framed) and resyncs > bound
        assert failed == over
        assert measured["within"] == (within and not stop and not over)
        if stop or over:
            assert measured["verdict"].startswith("not measurable")
        seen["failed"] += over
        seen["stopped"] += stop
        seen["kept"] += measured["within"]
    assert min(seen.values()) > 100           # every case drawn, many times


@pytest.mark.parametrize("ticks,rate,bound", [(0, 1000.0, 1), (2800, 1000.0, 140),
                                              (350, 1000.0, 17), (250, 250.0, 50),
                                              (10, 1000.0, 1)])
def test_resync_bound_is_the_stated_rate_over_the_run(ticks, rate, bound):
    """50 a second of run, floored, at least 1 (0.35 s at 1 kHz is 17; 0.01 s 1)."""
    assert lv.MAX_RESYNCS_PER_S == pytest.approx(lv.BLIND_SHARE / lv.RESYNC_BLIND_S)
    assert lv.resync_bound(ticks, rate) == bound


def test_a_run_over_the_bound_says_not_measurable_and_exits_1(monkeypatch):
    """The rule is the run's: the Haply M3's byte-exact mock, stepped in lockstep by name
    (the verdict's wiring, not timing), with host bytes lost so that the board is
    re-synchronised; with the bound lowered to one for the run, its report says "not
    measurable" with the count and the bound, and its exit code is 1."""
    from hapsim.daemon.runner import run_scene
    from hapsim.scene import load_scene
    monkeypatch.setattr(lv, "MAX_RESYNCS_PER_S", 1e-9)
    rep = run_scene(load_scene("configs/haply.yaml"), driver="haply", duration=0.6,
                    lockstep=True, handle_signals=False, rt_priority=0,
                    driver_faults={"drop_tx": 1 / 20, "seed": 3})
    resyncs = rep["loop"]["driver"]["resyncs"]
    assert resyncs > 1, rep["loop"]["driver"]
    m = rep["measured"]
    assert m["within"] is False and m["verdict"].startswith("not measurable")
    assert f"re-synchronised {resyncs} times" in m["verdict"]
    assert m["link"] == {"resyncs": resyncs, "resync_bound": 1, "reason": m["link"]["reason"]}
    assert rep["exit_code"] == 1

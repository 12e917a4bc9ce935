"""A run whose device left its workspace, or whose board was re-synchronised more than the
stated bound, never says "within" (issue 29 item 2; hapsim.host.link_verdict)."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.host import link_verdict as lv
from tolerance import rel_tol


def test_the_rule_over_random_runs():
    """Random runs (length, rate, re-synchronisations, safety stop, a framed or a driver
    link, the measurement's own verdict): "within" survives exactly when the measurement
    said it, no safety stop that left the workspace (position, speed, energy; a stop on
    the host's force clamp alone keeps the measured verdict) ended the run and the
    re-synchronisations stay within the bound, computed here independently (blind share 10 % of the run at 2 ms each:
    50 a second, floored, at least 1); the link fails the run (exit 1) exactly when they
    exceed it."""
    rng = np.random.default_rng(29)
    seen = {"failed": 0, "stopped": 0, "clamped": 0, "kept": 0}
    for _ in range(2000):
        rate = float(rng.choice([250.0, 500.0, 1000.0, 2000.0]))
        ticks = int(rng.integers(0, 6000))
        framed = rng.random() < 0.2
        resyncs = int(rng.integers(0, 3 * (ticks / rate) * 50 + 3))
        stop = bool(rng.random() < 0.3)
        clamp = stop and bool(rng.random() < 0.4)
        within = bool(rng.random() < 0.7)
        reason = rng.choice(["safety: position 0.2 m beyond +-0.1 m",
                             "safety: velocity 3 m/s beyond +-2 m/s",
                             "safety: the scene gave the hand 2 J more than the 0 J it "
                             "stored at its start, beyond the energy limit 1 J"])
        if clamp:
            reason = "safety: force at the limit 10 N in 50 of the last 100 samples"
        loop = {"ticks": ticks, "rate_hz": rate, "safety_stop": stop,
                "stop_reason": str(reason) if stop else "duration",
                "driver": None if framed else {"resyncs": resyncs}}
        measured = {"within": within, "verdict": "measured = predicted" if within else "differs"}
        failed = lv.link_verdict(measured, loop)
        bound = max(1, (50 * ticks) // int(rate))      # exact integer arithmetic
        over = (not framed) and resyncs > bound
        assert failed == over
        left = stop and not clamp
        assert measured["within"] == (within and not left and not over)
        if left or over:
            assert measured["verdict"].startswith("not measurable")
        seen["failed"] += over
        seen["stopped"] += left
        seen["clamped"] += clamp
        seen["kept"] += measured["within"]
    assert min(seen.values()) > 100           # every case drawn, many times


@pytest.mark.parametrize("ticks,rate,bound", [(0, 1000.0, 1), (2800, 1000.0, 140),
                                              (350, 1000.0, 17), (250, 250.0, 50),
                                              (10, 1000.0, 1)])
def test_resync_bound_is_the_stated_rate_over_the_run(ticks, rate, bound):
    """50 a second of run, floored, at least 1 (0.35 s at 1 kHz is 17; 0.01 s 1)."""
    # one division each side: derived rel_tol(2)
    assert lv.MAX_RESYNCS_PER_S == pytest.approx(lv.BLIND_SHARE / lv.RESYNC_BLIND_S,
                                                 rel=rel_tol(2))
    assert lv.resync_bound(ticks, rate) == bound


def test_a_run_over_the_bound_says_not_measurable_and_exits_1(monkeypatch):
    """The rule is the run's: the Haply M3's byte-exact mock, stepped in lockstep by name
    (the verdict's wiring, not timing), with host bytes lost so that the board is
    re-synchronised; with the bound lowered to one for the run, its report says "not
    measurable" with the count and the bound, and its exit code is 1."""
    from hapsim.pipeline.runner import run_scene
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


def test_the_clamp_stop_is_the_loops_own_reason():
    """The stop the rule keeps is the one the loop writes: safety_reason's clamp text
    begins with CLAMP_STOP, its position stop does not."""
    from hapsim.host.loop import safety_reason
    clamp = safety_reason(50, 50, 100, 10.0, 0.0, 0.1, 0.0, 1.0, 0.0, 1.0)
    away = safety_reason(0, 50, 100, 10.0, 0.2, 0.1, 0.0, 1.0, 0.0, 1.0)
    assert clamp.startswith(lv.CLAMP_STOP) and not away.startswith(lv.CLAMP_STOP)
    assert not lv.left_workspace({"safety_stop": True, "stop_reason": clamp})
    assert lv.left_workspace({"safety_stop": True, "stop_reason": away})


def test_a_safety_stop_s_verdict_names_its_own_cause():
    """Each safety stop the loops write withdraws "within" with its own cause: only a
    position bound says the device left its workspace (the lateness guard's stop and a
    driver's lateness stop said so too, before 2026-11-29); the clamp withdraws nothing."""
    from hapsim.host.loop import safety_reason
    from hapsim.kernels.late_growth import LateGrowth, late_growth_reason
    guard = LateGrowth(((0.0, 1.0),), 1.0, 5, 1)
    stops = {
        safety_reason(0, 50, 100, 10.0, 0.2, 0.1, 0.0, 1.0, 0.0, 1.0):
            "the device left its workspace",
        safety_reason(0, 50, 100, 10.0, 0.0, 0.1, 3.0, 1.0, 0.0, 1.0):
            "the device passed its speed limit",
        safety_reason(0, 50, 100, 10.0, 0.0, 0.1, 0.0, 1.0, 2.0, 1.0):
            "the scene gave the hand more energy than its limit",
        safety_reason(0, 50, 100, 10.0, 0.0, 0.1, 0.0, 1.0, 0.0, 1.0, 0.0, 0.8, guard, 1e-3):
            "the device held the host's forces longer than the scene's delay",
        late_growth_reason(0.8, guard, 1e-3):
            "the device held the host's forces longer than the scene's delay",
        "safety: the host was 61 ms late over its last 100 ticks: it cannot hold 1000 Hz":
            "the host fell behind the device's rate",
        "safety: non-finite position or force": "a position or force was not finite",
    }
    for reason, cause in stops.items():
        m = {"within": True, "verdict": "within"}
        lv.link_verdict(m, {"safety_stop": True, "stop_reason": reason, "ticks": 100,
                            "rate_hz": 1000.0})
        assert m["within"] is False and m["verdict"].startswith("not measurable"), reason
        assert f"({reason}): {cause}, the record" in m["verdict"], m["verdict"]
        assert ("workspace" in m["verdict"]) == reason.startswith("safety: position")
    clamp = safety_reason(50, 50, 100, 10.0, 0.0, 0.1, 0.0, 1.0, 0.0, 1.0)
    m = {"within": True, "verdict": "within"}
    lv.link_verdict(m, {"safety_stop": True, "stop_reason": clamp, "ticks": 100,
                        "rate_hz": 1000.0})
    assert m["within"] is True and m["link"]["reason"] is None

"""A felt pair far weaker than its record (:data:`hapsim.analysis.measurement.
ROUNDOFF_FREE_RATIO`): the verdict's round-off floor grows with the ratio of the record's
amplitude to the pair's.

An over-damped wall (the spring-damper's own damping ratio above 1) at a delay of 2-3
periods has one complex pair, a delay mode at a fifth of the sample rate, which the
excitation barely moves: 1.5e5 times weaker than the record in the fuzz's case. A
lockstep record is exact but for round-off, which is absolute (eps times the record's
largest amplitude): the pair was measured 9.5e-10 relative off in k and 1.1e-9 in b,
and the floor of 1e-9 said "differs" of the matching device (1 of 150 random loops of a
verdict fuzz). Tested here: that case, and random over-damped walls, matching and with
30 % more mass hidden in the device.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import hapsim.pipeline.runner as runner
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.measurement import ROUNDOFF_FLOOR, ROUNDOFF_FREE_RATIO
from hapsim.analysis.stability import stability_limit
from hapsim.scene import parse_scene

YAML = """rate_hz: {rate}
masses:
  - {{name: handle, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: spring, kind: spring_damper, between: [handle, wall], stiffness: {K!r},
     damping: {B!r}}}
device: {{mass: {m!r}, friction: {b0!r}, delay: {d}, hold: zoh, force_limit: 1000.0}}
excitation: {{x0: 0.005}}
"""

#: The fuzz's case: m, b0, rate, d, K, B.
FOUND = (0.0830715170771672, 1.925276273042024, 500, 3, 37.137427171910154,
         2.127994765024682)


def _run(case, monkeypatch, hidden: float = 1.0) -> dict:
    """The lockstep run (in process) of ``case``, the mock's device mass ``hidden`` times
    the scene's."""
    m, b0, rate, d, K, B = case
    sc = parse_scene(YAML.format(rate=rate, K=K, B=B, m=m, b0=b0, d=d))
    mock = runner.MockDevice

    def hiding(dev, *a, **k):
        return mock(dataclasses.replace(dev, mass=hidden * dev.mass), *a, **k)
    monkeypatch.setattr(runner, "MockDevice", hiding)
    return runner.run_scene(sc, transport="inprocess", lockstep=True, handle_signals=False)


def _over_damped(seed: int):
    """A random over-damped wall at a delay of 2 or 3 whose only complex pair is a delay
    mode (redrawn until so)."""
    rng = np.random.default_rng(seed)
    while True:
        m = float(10 ** rng.uniform(-1.7, 0.0))
        b0 = float(rng.uniform(0.5, 3.0))
        rate = float(rng.choice([250.0, 500.0, 1000.0]))
        d = int(rng.integers(2, 4))
        B = float(rng.uniform(0.5, 5.0))
        K = float(rng.uniform(0.05, 0.3)) * stability_limit(
            LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d, hold="zoh"), B)
        if K > 0 and (B + b0) / (2.0 * np.sqrt(K * m)) > 1.2:
            return m, b0, rate, d, K, B


def test_the_fuzz_case_is_within_and_its_floor_is_the_ratios(monkeypatch):
    rep = _run(FOUND, monkeypatch)
    ms, pr = rep["measured"], rep["predicted"]
    ratio = ms["record_amplitude"] / ms["amplitude"]
    assert ratio > 1e5, ratio                      # the pair 1e5 times weaker: the class
    assert ms["verdict"].startswith("measured = predicted"), ms["verdict"]
    # the floor: ROUNDOFF_FLOOR times the ratio over ROUNDOFF_FREE_RATIO (exact: the
    # verdict's own operations, in its order)
    assert ms["k_interval"] >= ROUNDOFF_FLOOR * (ratio / ROUNDOFF_FREE_RATIO) * abs(pr["k"])
    # and the pair is the predicted one (a delay mode far above the spring's own)
    assert pr["f0_hz"] > 0.2 * 500 and pr["k"] > 1000 * FOUND[4]


#: Draws of :func:`_over_damped` whose pair is 8e4 to 1.1e5 times weaker than the record
#: (11, 17, 58, of seeds 0-59; the rest 9 to 105 times) and two ordinary ones.
SEEDS = [11, 17, 58, 0, 3]


@pytest.mark.parametrize("seed", SEEDS)
def test_over_damped_walls_matching_within_and_heavier_differs(seed, monkeypatch):
    case = _over_damped(seed)
    ms = _run(case, monkeypatch)["measured"]
    assert not ms["verdict"].startswith("measured differs"), (case, ms["verdict"])
    hid = _run(case, monkeypatch, hidden=1.3)["measured"]
    assert not hid["verdict"].startswith("measured = predicted"), (case, hid["verdict"])

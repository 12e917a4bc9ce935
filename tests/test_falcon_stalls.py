"""A host stall in the Falcon's loop (issue 29 item 2): the firmware, on its own clock,
holds the last command over it; the run counts it and, on a paced (real) Falcon, says
"degraded" with the stall, never "ok". The emulated Falcon here steps one period per
packet (lockstep, named so in each test): what is tested is the host's account."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyftdi")       # the [falcon] extra; in [test] too: CI has it

from hapsim.pipeline import falcon_run as fr  # noqa: E402
from hapsim.scene_nd import load_scene_nd  # noqa: E402

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
IMAGE = bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8))


def _run(stall_at, stall_s, paced, samples=120):
    sc = load_scene_nd(CONFIGS / "delta_sphere.yaml")
    link, dev, chip = fr.emulated_falcon(sc, IMAGE, clock="lockstep")   # by name
    calls = [0, False]
    real = link.exchange

    def exchange(*a, **k):
        if calls[1]:
            calls[0] += 1
            if calls[0] in stall_at:
                time.sleep(stall_s)            # the host descheduled
        return real(*a, **k)
    link.exchange = exchange
    try:
        return fr.run_falcon(sc, link, IMAGE, samples, timeout=0.002, paced=paced,
                             before_loop=lambda: calls.__setitem__(1, True)), sc
    finally:
        link.close()


@pytest.mark.parametrize("seed", [1, 2])
def test_host_stalls_are_counted_and_a_paced_falcon_is_degraded_lockstep(seed):
    """Random stalls of 3 to 10 periods at random packets: each counted (a gap of more
    than HELD_PERIODS periods), the longest at least the stall injected, and the verdict
    of a paced run "degraded" naming the stall; an unpaced run (the emulator, one period
    per packet) counts them and stays "ok"."""
    rng = np.random.default_rng(seed)
    at = set(int(a) for a in rng.choice(np.arange(10, 100), 3, replace=False))
    sc = load_scene_nd(CONFIGS / "delta_sphere.yaml")
    stall = float(rng.uniform(3, 10)) / sc.rate_hz
    res, _ = _run(at, stall, paced=True)
    assert res["stalls"] >= len(at) and res["held_max_s"] >= stall
    assert res["verdict"] == "degraded" and "host stalled" in res["reason"]
    res, _ = _run(at, stall, paced=False)
    assert res["stalls"] >= len(at) and res["verdict"] == "ok", res["reason"]

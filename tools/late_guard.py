"""How the host loop's lateness guard (``hapsim/kernels/late_growth.py``) acts on random
walls and hosts too late for them (docs/reliability.md, "The lateness guard").

Each case is a spring-damper wall (mass, friction, K, B drawn at random, K around the
stability limit at the hold's mean delay) on the framed mock on a virtual clock
(:class:`hapsim.emulated.links.SimTransport`, the device on its own time), and a host that
is away ``G`` periods after each answer (a descheduled process): the device holds each
force ``G`` ticks. Every case runs twice, without the guard and with it. The run without
says what the loop does: it reaches a safety bound (the clamp, 0.1 m: "ran away"), or its
last 0.3 s are below half its first ("decayed"), or neither in 6 s ("slow"). For the runs
that ran away this prints where the guarded run stopped (time, why) and the largest
excursion of the handle in units of its start ``x0``; for those that decayed, whether the
guard stopped any (it must not). Deterministic (seeded, simulated time).

``--rates`` prints instead, for a few walls and uniform holds, the loop's growth a period
as a record without the guard measures it (the slope of its envelope's log, the largest
|x| of each 0.4 s, over up to 10 s) beside the guard's frozen estimate ``g(G) / G``.

Usage::

    python tools/late_guard.py                     # seeds 1-4, 20 cases each
    python tools/late_guard.py --seeds 7 8 --cases 14
    python tools/late_guard.py --rates
"""

from __future__ import annotations

import argparse
import math

import numpy as np

import firmware_protocol as fp
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.stability import stability_limit
from hapsim.emulated.faults import parse_faults
from hapsim.emulated.links import SimTransport
from hapsim.emulated.mock import MockDevice
from hapsim.engine import Engine
from hapsim.host.loop import HostLoop, LoopConfig
from hapsim.host.telemetry import Telemetry
from hapsim.pipeline.render_latency import late_growth
from hapsim.scene import parse_scene

LIMIT = 10.0        # force limit [N]
X0 = 0.005          # the handle's start [m]
WATCHDOG_S = 0.05   # the device's watchdog [s]
SECONDS = 6.0       # each run's length [s of the device's time]


def wall(K, B, mass=0.1, friction=0.5) -> str:
    """A 1 kHz spring-damper wall at the port, d = 1, the handle starting at ``X0``."""
    return f"""
rate_hz: 1000
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K}, damping: {B}}}
device: {{mass: {mass}, friction: {friction}, delay: 1, hold: zoh, force_limit: {LIMIT}}}
excitation: {{x0: {X0}}}
"""


class AwayHost(SimTransport):
    """The host is away ``away_us`` of virtual time after each FORCE it sends (the device
    ticks on, holding that force; its STATEs wait in the port, and the next answer goes to
    the newest)."""

    def __init__(self, *a, away_us: int = 0, **kw):
        super().__init__(*a, **kw)
        self.away_us = int(away_us)

    def send(self, msg):
        super().send(msg)
        if self.away_us and isinstance(msg, fp.Force):
            self.sleep(self.away_us * 1e-6)


def run(text: str, away_us: int, guard: bool, n: int = 3000):
    """The host loop on the mock, the host away ``away_us`` after each answer, with or
    without the guard; ``(LoopResult, Telemetry)``."""
    scene = parse_scene(text)
    mock = MockDevice(scene.device, scene.excitation, native_rate_hz=1000.0, lockstep=False)
    tr = AwayHost(mock, parse_faults("", 1), away_us=away_us)
    tel = Telemetry(n)
    cfg = LoopConfig(rate_hz=1000.0, n_samples=n, delay=1, force_limit=LIMIT,
                     watchdog_us=int(WATCHDOG_S * 1e6), position_bound=0.1,
                     brake_damping=25.0, brake_rest=1e-3,
                     late_growth=late_growth(scene, WATCHDOG_S) if guard else None)
    res = HostLoop(Engine(scene), tr, cfg, tel).run()
    return res, tel


def envelope(tel, lo: float, hi: float) -> float:
    """Largest |x| [m] of the rows whose device time is in [lo, hi) [s] (NaN: none)."""
    cols = tel.columns()
    t, x = cols["time"], cols["position"]
    sel = (t >= lo) & (t < hi)
    return float(np.max(np.abs(x[sel]))) if np.any(sel) else math.nan


def guard_stop(res) -> bool:
    """Whether the run ended on the lateness guard."""
    return bool(res.safety_stop) and "too late for the scene's loop" in res.stop_reason


def case(rng) -> dict:
    """One random case, both runs: ``G``, the scene's text, ``kind`` ("ran away",
    "decayed", "slow"), and the two runs' results and telemetries."""
    m, b, B = rng.uniform(0.05, 0.3), rng.uniform(0.2, 2.0), rng.uniform(0.3, 3.0)
    G = int(rng.integers(2, 31))
    Kl = stability_limit(LoopModel(mass=m, friction=b, rate_hz=1000.0, delay=1 + G / 2,
                                   hold="zoh"), B)
    text = wall(Kl * rng.uniform(0.5, 2.2), B, m, b)
    n = int(SECONDS / (G * 1e-3))
    off, t_off = run(text, G * 1000, False, n)
    on, t_on = run(text, G * 1000, True, n)
    t_end = float(t_off.columns()["time"][-1])
    first, last = envelope(t_off, 0.0, 0.3), envelope(t_off, t_end - 0.3, t_end + 1.0)
    kind = ("ran away" if off.safety_stop else "decayed" if last < 0.5 * first else "slow")
    return {"G": G, "text": text, "kind": kind, "off": off, "t_off": t_off, "on": on,
            "t_on": t_on}


#: ``--rates``' walls [N/m] (B = 1.5 N s/m, 0.1 kg on 0.5 N s/m) and holds [periods].
RATE_CASES = ((1000.0, 2), (300.0, 8), (300.0, 10), (300.0, 12), (150.0, 18), (150.0, 22),
              (150.0, 24), (150.0, 26))


def rates() -> None:
    """Print the measured and estimated growth a period of :data:`RATE_CASES`."""
    from hapsim.kernels.late_growth import hold_growth
    print("K [N/m]  hold  measured [1e-3/period]  frozen estimate  record")
    for K, G in RATE_CASES:
        text = wall(K, 1.5)
        res, tel = run(text, G * 1000, False, int(10.0 / (G * 1e-3)))
        cols = tel.columns()
        t, x = cols["time"], np.abs(cols["position"])
        edges = np.arange(0.5, t[-1] - 0.4, 0.4)
        env = np.array([x[(t >= a) & (t < a + 0.4)].max() for a in edges])
        slope = np.polyfit(edges, np.log(env), 1)[0] * 1e-3
        g = late_growth(parse_scene(text), WATCHDOG_S)
        est = hold_growth(G, g.array()[0], g.step) / G      # (a wall: one mode)
        print(f"{K:7.0f}  {G:4d}  {slope * 1e3:+22.3f}  {est * 1e3:+15.3f}"
              f"  {t[-1]:.1f} s, {res.stop_reason.split(' in ')[0]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--cases", type=int, default=20, help="cases per seed")
    ap.add_argument("--rates", action="store_true",
                    help="the measured and estimated growth of uniform holds instead")
    a = ap.parse_args(argv)
    if a.rates:
        rates()
        return 0
    counts = {"ran away": 0, "decayed": 0, "slow": 0}
    worst, wrong, others = 0.0, 0, 0
    for seed in a.seeds:
        rng = np.random.default_rng(seed)
        for _ in range(a.cases):
            c = case(rng)
            counts[c["kind"]] += 1
            on, off = c["on"], c["off"]
            ratio = float(np.max(np.abs(c["t_on"].columns()["position"]))) / X0
            t_on = float(c["t_on"].columns()["time"][-1])
            t_off = float(c["t_off"].columns()["time"][-1])
            if c["kind"] == "ran away":
                worst = max(worst, ratio)
                others += not guard_stop(on)
                print(f"seed {seed} G {c['G']:2d}: ran away at {t_off:.2f} s "
                      f"({off.stop_reason.split(':')[1].strip()[:20]}); guarded: "
                      f"{'the guard' if guard_stop(on) else on.stop_reason[:34]} at "
                      f"{t_on:.2f} s, the handle within {ratio:.2f} x0")
            elif c["kind"] == "decayed" and on.stop_reason != "duration":
                wrong += 1
                print(f"seed {seed} G {c['G']:2d}: decayed, yet guarded: {on.stop_reason}")
    print(f"cases: {counts['ran away']} ran away, {counts['decayed']} decayed, "
          f"{counts['slow']} neither in {SECONDS:g} s")
    print(f"ran away: every guarded run stopped sooner ({others} on another bound first); "
          f"the handle within {worst:.2f} x0 at most")
    print(f"decayed: {wrong} stopped by the guard")
    return 1 if wrong else 0


if __name__ == "__main__":
    raise SystemExit(main())

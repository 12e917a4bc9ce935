"""How the host loop's lateness guard (``hapsim/kernels/late_growth.py``) acts on random
walls and hosts too late for them (docs/reliability.md, "The lateness guard").

Each case is a spring-damper wall (mass, friction, K, B drawn at random, K around the
stability limit at the hold's mean delay) on the framed mock on a virtual clock
(:class:`hapsim.emulated.links.SimTransport`, the device on its own time), and a host that
is away ``G`` periods after each answer (a descheduled process): the device holds each
force ``G`` ticks; or (``--family "two masses"``) a two-mode loop and a host stalled so
now and then (:func:`case`). Every case runs twice, without the guard and with it. The run
without says what the loop does: it reaches a safety bound (the clamp, 0.1 m: "ran
away"), or it never goes above its first 0.3 s and its last 0.3 s are below half of them
("decayed"), or neither in 6 s ("other": it grew for a while, or slowly). For the runs
that ran away this prints where the guarded run stopped (time, why) and the largest
excursion of the handle in units of its start ``x0``; for those that decayed, whether the
guard stopped any (it must not). Deterministic (seeded, simulated time).

``--family n-D`` draws 2-D and 3-D loops instead (:func:`nd_case`: a cartesian device on
a spring-damper, stable on time; a link that holds some of the device's frames 3-12 ms),
each measured over the port as ``hapsim run`` measures a 2-D or 3-D scene
(:func:`hapsim.pipeline.felt_port.measure_felt_port`, its records' safety
:mod:`hapsim.pipeline.record_guard`), without the lateness guard and with it (the
position bound, 20 a, on both): "ran away" reached the bound, "decayed" had every
record's last 60 rows below half its first 60.

``--rates`` prints instead, for a few walls and uniform holds, the loop's growth a period
as a record without the guard measures it (the slope of its envelope's log, the largest
|x| of each 0.4 s, over up to 10 s) beside the guard's frozen estimate ``g(G) / G``.

Usage::

    python tools/late_guard.py                     # seeds 1-4, 20 cases each
    python tools/late_guard.py --seeds 7 8 --cases 14
    python tools/late_guard.py --family "late link" --seeds 1 2 --cases 20
    python tools/late_guard.py --family n-D --seeds 11 12 13 14 15 --cases 16
    python tools/late_guard.py --rates
    python tools/late_guard.py --plot docs/late_guard.png

``--plot FIG.png`` draws one case instead (needs matplotlib, ``pip install
'hapsim[plot]'``): the reliability tests' wall (1000 N/m, B 1.5 N s/m; 0.1 kg on
0.5 N s/m), stable at its own delay only, and a host away 4 periods after each answer:
the handle's position without the guard and with it.
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
from hapsim.analysis.late_growth import late_growth
from hapsim.scene import parse_scene, parse_scene_nd

LIMIT = 10.0        # force limit [N]
X0 = 0.005          # the handle's start [m]
WATCHDOG_S = 0.05   # the device's watchdog [s]
SECONDS = 6.0       # each run's length [s of the device's time]
FAST_S = 2.0        # a loop that ran away within this [s] grew well above the slack


def wall(K, B, mass=0.1, friction=0.5, x0=X0) -> str:
    """A 1 kHz spring-damper wall at the port, d = 1, the handle starting at ``x0``."""
    return f"""
rate_hz: 1000
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K}, damping: {B}}}
device: {{mass: {mass}, friction: {friction}, delay: 1, hold: zoh, force_limit: {LIMIT}}}
excitation: {{x0: {x0}}}
"""


def two_masses(K1, B1, M2, K2, B2, mass=0.1, friction=0.5) -> str:
    """The handle on a virtual mass ``M2`` (spring-damper ``K1``, ``B1``), held to ground
    by another (``K2``, ``B2``): a loop of two modes, the handle starting at ``X0``."""
    return f"""
rate_hz: 1000
masses:
  - {{name: hand, kind: port}}
  - {{name: m2, kind: mass, mass: {M2}}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: a, kind: spring_damper, between: [hand, m2], stiffness: {K1}, damping: {B1}}}
  - {{name: b, kind: spring_damper, between: [m2, wall], stiffness: {K2}, damping: {B2}}}
device: {{mass: {mass}, friction: {friction}, delay: 1, hold: zoh, force_limit: {LIMIT}}}
excitation: {{x0: {X0}}}
"""


class AwayHost(SimTransport):
    """The host is away ``away_us`` of virtual time after a FORCE it sends: after each
    one, or (``chance`` < 1) after each with that chance, drawn from ``seed`` (a loaded
    host's stalls now and then). The device ticks on, holding that force; its STATEs wait
    in the port, and the next answer goes to the newest."""

    def __init__(self, *a, away_us: int = 0, chance: float = 1.0, seed: int = 0, **kw):
        super().__init__(*a, **kw)
        self.away_us = int(away_us)
        self.chance = float(chance)
        self.rng = np.random.default_rng(seed)

    def send(self, msg):
        super().send(msg)
        if (self.away_us and isinstance(msg, fp.Force)
                and (self.chance >= 1.0 or self.rng.random() < self.chance)):
            self.sleep(self.away_us * 1e-6)


def run(text: str, away_us: int, guard: bool, n: int = 3000, chance: float = 1.0,
        seed: int = 0, rest: float = 1e-3, faults: str = ""):
    """The host loop on the mock, the host away ``away_us`` after each answer (or after
    each with ``chance``), with or without the guard (its rest speed ``rest`` [m/s], the
    braking's), the link's ``faults`` (:mod:`hapsim.emulated.faults`, seeded with
    ``seed``); ``(LoopResult, Telemetry)``, the transport (its ``mock``, its ``sent``
    messages) as the result's ``transport``."""
    scene = parse_scene(text)
    mock = MockDevice(scene.device, scene.excitation, native_rate_hz=1000.0, lockstep=False)
    tr = AwayHost(mock, parse_faults(faults, seed), away_us=away_us, chance=chance, seed=seed)
    tr.sent = []
    tel = Telemetry(n)
    cfg = LoopConfig(rate_hz=1000.0, n_samples=n, delay=1, force_limit=LIMIT,
                     watchdog_us=int(WATCHDOG_S * 1e6), position_bound=0.1,
                     brake_damping=25.0, brake_rest=rest,
                     late_growth=late_growth(scene, WATCHDOG_S) if guard else None)
    res = HostLoop(Engine(scene), tr, cfg, tel).run()
    res.transport = tr
    return res, tel


def coast_rest(mock, seconds: float = 5.0) -> float:
    """Where the mock's handle comes to rest [m] from where the run left it (a STOP or the
    end disarms the mock and freezes its physics), on its friction alone: zero force for
    ``seconds``."""
    ph = mock.physics
    for _ in range(int(seconds * 1000)):
        ph.advance(0.0)
    return float(ph.x)


def open_hold(res, tel, d: int = 1) -> int:
    """Ticks the device had held the FORCE its last STATE names beyond the on-time one
    (``named_delay - d``; 0 on time, -1 if it names none)."""
    from hapsim.kernels.ticks import named_delay
    cols = tel.columns()
    lag = named_delay(int(cols["seq"][-1]), int(cols["force_seq"][-1]),
                      int(cols["status"][-1]), True)
    return lag - d if lag >= 0 else -1


def envelope(tel, lo: float, hi: float) -> float:
    """Largest |x| [m] of the rows whose device time is in [lo, hi) [s] (NaN: none)."""
    cols = tel.columns()
    t, x = cols["time"], cols["position"]
    sel = (t >= lo) & (t < hi)
    return float(np.max(np.abs(x[sel]))) if np.any(sel) else math.nan


def guard_stop(res) -> bool:
    """Whether the run ended on the lateness guard."""
    return bool(res.safety_stop) and "too late for the scene's loop" in res.stop_reason


def case(rng, family: str = "wall") -> dict:
    """One random case, both runs: ``G``, ``chance``, the scene's text, ``kind`` ("ran
    away", "decayed", "other": module notes), and the two runs' results and telemetries.

    ``family`` "wall": a spring-damper wall, the host away ``G`` periods after every
    answer. "two masses": the handle on a virtual mass held to ground (two modes; drawn
    again until the loop is stable on time), the host away ``G`` periods after an answer
    with a chance of 2-40 %: stalls now and then, of a mode that may decay on time much
    faster than the other. "late link": a wall stable on time (0.2-0.9 of its stiffness
    limit at d = 1), the host never away, and a link that holds the device's frames
    (``spike``, 5-50 % of them held 6-40 ms, in order): answers late for as long as a
    hold lasts, and a hold that may never end (``docs/reliability.md``, "A hold that
    never ends"); ``G`` is then 0 and ``faults`` the link's."""
    from hapsim.analysis.prediction import predict
    m, b = rng.uniform(0.05, 0.3), rng.uniform(0.2, 2.0)
    G = int(rng.integers(2, 31))
    chance = 1.0
    faults = ""
    if family == "late link":
        B = rng.uniform(0.3, 3.0)
        Kl = stability_limit(LoopModel(mass=m, friction=b, rate_hz=1000.0, delay=1,
                                       hold="zoh"), B)
        text = wall(Kl * rng.uniform(0.2, 0.9), B, m, b)
        G = 0
        faults = f"spike={rng.uniform(0.05, 0.5):.3f}:{rng.uniform(6.0, 40.0):.1f}ms"
    elif family == "wall":
        B = rng.uniform(0.3, 3.0)
        Kl = stability_limit(LoopModel(mass=m, friction=b, rate_hz=1000.0,
                                       delay=1 + G / 2, hold="zoh"), B)
        text = wall(Kl * rng.uniform(0.5, 2.2), B, m, b)
    else:
        chance = float(rng.uniform(0.02, 0.4))
        while True:
            text = two_masses(rng.uniform(50.0, 3000.0), rng.uniform(0.0, 3.0),
                              rng.uniform(0.01, 0.5), rng.uniform(50.0, 3000.0),
                              10.0 ** rng.uniform(-3.0, 0.5), m, b)
            if predict(parse_scene(text), limit=False)["stable"]:
                break
    n = int(SECONDS / (1e-3 * (1.0 + chance * G))) if G else 3000
    seed = int(rng.integers(1 << 31))
    off, t_off = run(text, G * 1000, False, n, chance, seed, faults=faults)
    on, t_on = run(text, G * 1000, True, n, chance, seed, faults=faults)
    t_end = float(t_off.columns()["time"][-1])
    first, last = envelope(t_off, 0.0, 0.3), envelope(t_off, t_end - 0.3, t_end + 1.0)
    peak = max((envelope(t_off, t, t + 0.3) for t in np.arange(0.3, t_end, 0.3)), default=0.0)
    kind = ("ran away" if off.safety_stop
            else "decayed" if last < 0.5 * first and peak <= first else "other")
    return {"G": G, "chance": chance, "faults": faults, "text": text, "kind": kind,
            "off": off, "t_off": t_off, "on": on, "t_on": t_on}


#: ``--rates``' walls: K [N/m], the hold [periods], and B [N s/m], mass [kg] and friction
#: [N s/m] (the last, seed 4's 25th wall: the estimate's largest error seen).
RATE_CASES = ((1000.0, 2, 1.5, 0.1, 0.5), (300.0, 8, 1.5, 0.1, 0.5), (300.0, 10, 1.5, 0.1, 0.5),
              (300.0, 12, 1.5, 0.1, 0.5), (150.0, 18, 1.5, 0.1, 0.5), (150.0, 22, 1.5, 0.1, 0.5),
              (150.0, 24, 1.5, 0.1, 0.5), (150.0, 26, 1.5, 0.1, 0.5),
              (230.80895809897262, 25, 2.6874022394058095, 0.09268245486156872,
               0.598432987740417))


def rates() -> None:
    """Print the measured and estimated growth a period of :data:`RATE_CASES` (the
    estimate without the guard's slack)."""
    from hapsim.kernels.late_growth import LATE_GROWTH_SLACK, hold_growth
    print("K [N/m]  hold  measured [1e-3/period]  frozen estimate  record")
    for K, G, B, m, b in RATE_CASES:
        text = wall(K, B, m, b)
        res, tel = run(text, G * 1000, False, int(10.0 / (G * 1e-3)))
        cols = tel.columns()
        t, x = cols["time"], np.abs(cols["position"])
        edges = np.arange(0.5, t[-1] - 0.4, 0.4)
        env = np.array([x[(t >= a) & (t < a + 0.4)].max() for a in edges])
        slope = np.polyfit(edges, np.log(env), 1)[0] * 1e-3
        g = late_growth(parse_scene(text), WATCHDOG_S)
        # (a wall: one mode)
        est = hold_growth(G, g.array()[0], g.step) / G + LATE_GROWTH_SLACK * 1e-3
        print(f"{K:7.0f}  {G:4d}  {slope * 1e3:+22.3f}  {est * 1e3:+15.3f}"
              f"  {t[-1]:.1f} s, {res.stop_reason.split(' in ')[0]}")


def plot(path: str) -> None:
    """Draw the ``--plot`` case (module notes) to ``path``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    text = wall(1000.0, 1.5)
    off, t_off = run(text, 4000, False, 400)
    on, t_on = run(text, 4000, True, 400)
    fig, ax = plt.subplots(figsize=(7.0, 3.4))
    for tel, res, label in ((t_off, off, "without the guard"),
                            (t_on, on, "with the guard")):
        cols = tel.columns()
        stop = ("the guard's stop, then the braking" if guard_stop(res)
                else "the clamp's stop" if "force at the limit" in res.stop_reason
                else res.stop_reason)
        ax.plot(cols["time"] * 1e3, cols["position"] * 1e3,
                label=f"{label}: {stop} at {cols['time'][-1] * 1e3:.0f} ms")
    ax.axhline(0.0, color="0.7", lw=0.8)
    ax.set_xlabel("device time [ms]")
    ax.set_ylabel("handle position [mm]")
    ax.set_title("1000 N/m wall, d = 1, host away 4 periods after each answer")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def late_link(seeds, cases: int) -> int:
    """``--family "late link"``: per case that ran to a bound without the guard, where
    each run stopped, how long the device had held the FORCE it last named, what the
    braking did, and where the handle came to rest on its friction (:func:`coast_rest`);
    then the counts. 1 when a guarded run sent a braking FORCE the device could not take
    (its last STATE named a FORCE more than ``d + IGNORED_TICKS`` ticks old) or ended
    later than the unguarded one."""
    from hapsim.braking import IGNORED_TICKS
    n = nearer = same = farther = inside = braked_ignored = later = decayed_stopped = 0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        for _ in range(cases):
            c = case(rng, "late link")
            on, off = c["on"], c["off"]
            if c["kind"] == "decayed" and on.stop_reason != "duration":
                decayed_stopped += 1
            if c["kind"] != "ran away":
                continue
            n += 1
            r_off = abs(coast_rest(off.transport.mock))
            r_on = abs(coast_rest(on.transport.mock))
            held = open_hold(on, c["t_on"])
            later += on.samples > off.samples
            if held > IGNORED_TICKS:
                inside += 1
                braked_ignored += bool(on.brake.get("periods"))
            nearer += r_on < r_off - 1e-6
            same += abs(r_on - r_off) <= 1e-6
            farther += r_on > r_off + 1e-6
            t_on = float(c["t_on"].columns()["time"][-1])
            t_off = float(c["t_off"].columns()["time"][-1])
            print(f"seed {seed} {c['faults']:22s}: without the guard "
                  f"{off.stop_reason.split(':')[1].strip()[:18]:18s} at {t_off:.3f} s, rest "
                  f"{r_off * 1e3:7.1f} mm; guarded: "
                  f"{'the guard' if guard_stop(on) else on.stop_reason[8:26]:18s} at "
                  f"{t_on:.3f} s, held {held:3d} ticks, braking "
                  f"{on.brake.get('ended', '-')}, rest {r_on * 1e3:7.1f} mm")
    print(f"ran away without the guard: {n}; guarded, {inside} stopped inside a hold longer "
          f"than d + {IGNORED_TICKS} ticks ({braked_ignored} of them sent braking FORCEs); "
          f"{later} ended later than without")
    print(f"the handle's rest on its friction, guarded against not: {nearer} nearer, "
          f"{same} the same (the device's watchdog had zeroed the force before either "
          f"stop), {farther} farther")
    print(f"decayed without the guard, yet stopped by it: {decayed_stopped}")
    return 1 if braked_ignored or later else 0


#: The n-D records' amplitude [m] (a hand's, not the mock's 1e-8 default: the guard
#: stops only a handle faster than the braking's rest speed).
ND_A = 0.002


def nd_text(n, m, b0, K, B, d, brake=True) -> str:
    """A cartesian n-D scene (diagonal mass [kg] and friction [N s/m]) on a
    spring-damper (K [N/m], B [N s/m]) to the origin, delay ``d`` periods, at 1 kHz."""
    z = "[" + ", ".join(["0.0"] * n) + "]"
    vec = "[{}]".format
    return (f"dimension: {n}\nrate_hz: 1000\nmasses:\n  - {{name: hand, kind: port}}\n"
            f"  - {{name: c, kind: ground, x0: {z}}}\nlinks:\n"
            f"  - {{name: s, kind: spring_damper, between: [hand, c], stiffness: {K:.9g}, "
            f"damping: {B:.9g}}}\ndevice: {{kind: cartesian, "
            f"mass: {vec(', '.join(f'{float(x):.9g}' for x in m))}, "
            f"friction: {vec(', '.join(f'{float(x):.9g}' for x in b0))}, position: {z}, "
            f"delay: {d}}}\n" + ("" if brake else "safety: {brake: false}\n"))


def nd_case(rng):
    """A random 2-D or 3-D loop stable on time (``(scene, faults, fault_seed)``), and a
    link holding some of the device's frames 3-12 ms (half the cases milder: at most
    10 % held, at most 6 ms)."""
    from hapsim.analysis.scene_check import closed_loop_nd
    while True:
        n = int(rng.integers(2, 4))
        sc = parse_scene_nd(nd_text(n, rng.uniform(0.05, 0.3, n), rng.uniform(0.1, 1.5, n),
                                    rng.uniform(200, 4000), rng.uniform(0.0, 4.0),
                                    int(rng.integers(1, 3))), "<case>")
        if max(abs(np.linalg.eigvals(closed_loop_nd(sc)[0]))) < 1.0:
            break
    mild = rng.random() < 0.5
    p = rng.uniform(0.02, 0.1) if mild else rng.uniform(0.02, 0.5)
    G = rng.uniform(3, 6) if mild else rng.uniform(3, 12)
    return sc, f"spike={p:.3f}:{G:.1f}ms", int(rng.integers(1, 1000))


def nd_measure(sc, faults, seed, guard):
    """The n-D measurement over the n-axis mock on a virtual clock (faults seeded; None:
    a link that holds nothing): ``(result, transport)``, every message sent kept in
    ``transport.sent``."""
    from hapsim.emulated.mock import MockDeviceND
    from hapsim.pipeline.felt_port import measure_felt_port
    tr = SimTransport(MockDeviceND(sc, lockstep=False, amplitude=ND_A),
                      parse_faults(faults, seed) if faults else None)
    tr.sent = []
    return measure_felt_port(tr, sc, amplitude=ND_A, late_guard=guard), tr


def nd_kind(res) -> str:
    """"ran away" (a safety stop), "decayed" (every record's, after the one from rest,
    largest distance from rest over its last 60 rows below half that of its first 60)
    or "other"."""
    if res["stop"].startswith("safety"):
        return "ran away"
    env = []
    for m in res["moved"][1:]:
        r = np.linalg.norm(m, axis=1)
        env.append(r[-60:].max() / r[:60].max())
    return "decayed" if max(env) < 0.5 else "other"


def stopped_at(res) -> tuple:
    """(record, row) where an n-D measurement stopped: its first start not wholly
    recorded."""
    return next(((j, r) for j, r in enumerate(res["rows"]) if r < res["samples"]),
                (len(res["rows"]), 0))


def late_stop(res) -> bool:
    """An n-D measurement stopped by the lateness guard."""
    return res["stop"].startswith("safety: the host's FORCEs came too late")


def n_d(seeds, cases: int) -> int:
    """``--family n-D``: the counts, and each case the guard stopped that did not run
    away. 1 when a guarded run stopped later than without, or stopped one that
    decayed."""
    seen = {"ran away": 0, "decayed": 0, "other": 0}
    sooner = later = decayed_stopped = other_stopped = 0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        for _ in range(cases):
            sc, faults, fseed = nd_case(rng)
            off, on = nd_measure(sc, faults, fseed, False)[0], nd_measure(sc, faults, fseed,
                                                                          True)[0]
            kind = nd_kind(off)
            seen[kind] += 1
            if kind == "ran away":
                later += stopped_at(on) > stopped_at(off)
                sooner += late_stop(on) and stopped_at(on) < stopped_at(off)
            elif on["stop"] != "end":
                decayed_stopped += kind == "decayed"
                other_stopped += kind == "other"
                print(f"seed {seed} {sc.dimension}-D {faults}: {kind}, stopped by the guard "
                      f"at record {stopped_at(on)[0]} (rows {off['rows']} without)")
    print(f"cases: {seen['ran away']} ran away, {seen['decayed']} decayed, {seen['other']} "
          f"neither ({other_stopped} of them stopped by the guard)")
    print(f"ran away: {sooner} stopped sooner by the guard, {later} later")
    print(f"decayed: {decayed_stopped} stopped by the guard")
    return 1 if later or decayed_stopped else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--cases", type=int, default=20, help="cases per seed")
    ap.add_argument("--family", choices=("wall", "two masses", "late link", "n-D"),
                    default="wall",
                    help="the scenes and hosts drawn (module notes of case())")
    ap.add_argument("--rates", action="store_true",
                    help="the measured and estimated growth of uniform holds instead")
    ap.add_argument("--plot", metavar="FIG.png",
                    help="draw one case, without the guard and with it, instead")
    a = ap.parse_args(argv)
    if a.plot:
        plot(a.plot)
        return 0
    if a.rates:
        rates()
        return 0
    if a.family == "late link":
        return late_link(a.seeds, a.cases)
    if a.family == "n-D":
        return n_d(a.seeds, a.cases)
    counts = {"ran away": 0, "decayed": 0, "other": 0}
    worst, wrong, others, later, slow_stopped = 0.0, 0, 0, 0, 0
    fast, fast_guarded, fast_worst = 0, 0, 0.0     # ran away within FAST_S
    for seed in a.seeds:
        rng = np.random.default_rng(seed)
        for _ in range(a.cases):
            c = case(rng, a.family)
            counts[c["kind"]] += 1
            on, off = c["on"], c["off"]
            ratio = float(np.max(np.abs(c["t_on"].columns()["position"]))) / X0
            t_on = float(c["t_on"].columns()["time"][-1])
            t_off = float(c["t_off"].columns()["time"][-1])
            host = (f"G {c['G']:2d}" + (f" at {c['chance']:.0%}" if c["chance"] < 1 else ""))
            if c["kind"] == "ran away":
                worst = max(worst, ratio)
                others += not guard_stop(on)
                later += not (on.safety_stop and on.samples < off.samples)
                if t_off < FAST_S:
                    fast += 1
                    fast_guarded += guard_stop(on) and on.samples < off.samples
                    fast_worst = max(fast_worst, ratio)
                print(f"seed {seed} {host}: ran away at {t_off:.2f} s "
                      f"({off.stop_reason.split(':')[1].strip()[:20]}); guarded: "
                      f"{'the guard' if guard_stop(on) else on.stop_reason[:34]} at "
                      f"{t_on:.2f} s, the handle within {ratio:.2f} x0")
            elif c["kind"] == "decayed" and on.stop_reason != "duration":
                wrong += 1
                print(f"seed {seed} {host}: {c['kind']}, yet guarded: {on.stop_reason}")
            elif c["kind"] == "other":
                slow_stopped += guard_stop(on)
    print(f"cases: {counts['ran away']} ran away, {counts['decayed']} decayed, "
          f"{counts['other']} neither in {SECONDS:g} s (grew for a while, or slowly: "
          f"{slow_stopped} of them stopped by the guard)")
    print(f"ran away: {counts['ran away'] - later} guarded runs stopped sooner ({others} on "
          f"another bound), {later} not; the handle within {worst:.2f} x0 at most")
    print(f"ran away within {FAST_S:g} s: {fast_guarded} of {fast} stopped sooner by the guard, "
          f"the handle within {fast_worst:.2f} x0 at most")
    print(f"decayed: {wrong} stopped by the guard")
    return 1 if wrong or later else 0


if __name__ == "__main__":
    raise SystemExit(main())

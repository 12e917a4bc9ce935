"""How a request-reply driver's missing replies move a 1-D loop's stability: the closed loop
as a switched linear system over the host's patterns of fresh, estimated and skipped ticks.

Usage::

    python tools/estimate_patterns.py [SCENE] [--damping B [B ...]] [--period-max L]
                                      [--json FILE]

A request-reply board (the Haply M3, the Hapkit sketch, the FireFader's ``.ino``) answers
each command; where an answer is overdue the host loop steps the engine with the position
extrapolated linearly from the last two records, at most ``ESTIMATED_MAX`` = 2 ticks in a
row, then skips ticks (the engine not stepped, the last force written again) until a record
comes (:mod:`hapsim.host.host_clock`). ``hapsim check`` predicts the loop with every reading
on time. This program (its model in :mod:`hapsim.analysis.missing_replies`) builds the
closed loop's state matrix for each kind of tick (exact
zero-order hold of ``m x'' + b0 x' = f``, Florens et al. Sec. 6; the virtual spring-damper
``f = -K r - B (r - r_prev) / T`` on the reading ``r``; ``d`` periods of delay), multiplies
them over every periodic pattern of missing replies up to ``--period-max`` ticks, and prints
the largest growth per tick (the spectral radius of the pattern's product to the power
``1 / L``: a lower bound of the switched system's joint spectral radius, Jungers 2009, Sec.
1.2) under three rules for a missing reply: today's linear extrapolation, the last record
held (the reading a period late), and a skip from the first missing reply.

The model with every reading on time reproduces ``hapsim.analysis.stability`` (the printed
``check`` damping limit). A scene whose loop is between two ports or has more than one
port link is refused: the program reads the port's spring-damper to ground alone. The
delay is the scene's as written, a real number of periods (a split hold).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from provenance import REPO, command_line  # tools/, beside this file

sys.path.insert(0, str(REPO))

from hapsim.analysis.missing_replies import (MAX_RUN, MAX_SHARE, RULES,  # noqa: E402
                                            growth, patterns, tick_matrices)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(REPO / "configs" / "haply.yaml"),
                    help="a 1-D scene with one port link to ground (default "
                         "configs/haply.yaml)")
    ap.add_argument("--damping", type=float, nargs="+", default=None, metavar="B",
                    help="the virtual damping values to try [N s/m] (default: the scene's, "
                         "and 0.3, 0.5, 0.7 of the check's limit over its own)")
    ap.add_argument("--period-max", type=int, default=10, metavar="L",
                    help="longest pattern [ticks] (default 10)")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the results")
    a = ap.parse_args(argv)
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.stability import damping_limits
    from hapsim.analysis.missing_replies import wall_loop
    from hapsim.scene import load_scene
    from hapsim.errors import ConfigError
    try:
        sc = load_scene(a.scene)
    except ConfigError as exc:
        print(f"estimate_patterns: {exc}", file=sys.stderr)
        return 2
    loop = wall_loop(sc)
    if loop is None:
        print(f"{a.scene}: needs spring-dampers from the port to ground alone, a zero-order "
              f"hold and a delay > 0", file=sys.stderr)
        return 2
    # (the scene's delay as written: a run analyses it at its board's timing, the render
    # latency added)
    m, b0, T, d, K, B0 = loop
    lm = LoopModel(mass=m, friction=b0, rate_hz=sc.rate_hz, delay=d,
                   hold="zoh")
    lims = damping_limits(lm, K)
    bmax = max(hi for _, hi in lims) if lims else float("nan")
    Bs = a.damping or [B0] + [f * bmax for f in (0.3, 0.5, 0.7, 0.9)]
    from provenance import portable_path
    print(f"{portable_path(a.scene)}: m {m:g}, b0 {b0:g}, K {K:g}, d {d:g}, T {T:g} s; "
          f"check's damping limit {bmax:.4g} (every reading on time); patterns up to "
          f"{a.period_max} ticks, at most {MAX_RUN} missing in a row, "
          f"{MAX_SHARE:.0%} missing")
    on_time = growth(tick_matrices(m, b0, T, d, K, bmax * 0.999), ["F"])
    print(f"model check: every reading on time at 0.999 of the limit, growth {on_time:.6f} "
          f"per tick (< 1)")
    rows = []
    for B in Bs:
        mats = tick_matrices(m, b0, T, d, K, B)
        row = {"B": B}
        for name, rule in RULES.items():
            g, p = max((growth(mats, p), p) for p in patterns(rule, a.period_max))
            row[name] = {"growth": g, "pattern": "".join(k[0] for k in p)}
        rows.append(row)
        print(f"B {B:8.4g}: " + " | ".join(
            f"{n} {row[n]['growth']:.4f} ({row[n]['pattern']})" for n in RULES))
    # the damping where the worst pattern first grows, per rule: on a grid of the range
    # check calls stable, the last point of the first stable stretch, then bisection to
    # the next grid point
    limits = {}
    lo0 = max(max(lo for lo, _ in lims) if lims else 0.0, 0.0)
    grid = np.linspace(lo0, bmax, 41)[1:-1]
    for name, rule in RULES.items():
        ps = patterns(rule, a.period_max)

        def worst(B):
            mats = tick_matrices(m, b0, T, d, K, B)
            return max(growth(mats, p) for p in ps)
        ok = [worst(B) <= 1.0 for B in grid]
        if not any(ok):
            limits[name] = None
            continue
        i = ok.index(True)
        while i + 1 < grid.size and ok[i + 1]:
            i += 1
        lo, hi = grid[i], (grid[i + 1] if i + 1 < grid.size else bmax)
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if worst(mid) <= 1.0 else (lo, mid)
        limits[name] = float(lo)
    print("the damping limit with those patterns: " + ", ".join(
        f"{n} {v:.4g} ({v / bmax:.0%} of check's)" if v is not None else f"{n} none"
        for n, v in limits.items()))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"command": command_line(__file__, argv), "scene": portable_path(a.scene), "K": K,
                       "d": d, "check_damping_limit": bmax, "limits": limits,
                       "max_run": MAX_RUN,
                       "max_share": MAX_SHARE, "period_max": a.period_max, "rows": rows},
                      f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

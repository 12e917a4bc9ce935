"""The n-D braking's figures (docs/reliability.md, "In two and three dimensions"): the
travel of random 2-D/3-D devices thrown at speed and braked, against their friction alone
(tests/test_brake_nd.py's loop), the braked loops' largest spectral radius with random
friction and a hand's inertia, and each route's push out of its envelope, braked and not
(tests/test_brake_routes.py's runs: the emulated 2DIY and Falcon on their own clocks in
simulated time). Every figure is deterministic (seeded, simulated time).

Usage::

    python tools/brake_nd.py                 # 200 devices, both routes
    python tools/brake_nd.py --devices 500 --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


class _Patch:
    """``monkeypatch.setattr`` for the tests' helpers outside pytest (left patched: the
    process ends after)."""

    @staticmethod
    def setattr(mod, name, value):
        setattr(mod, name, value)


def devices(count: int) -> dict:
    """Random devices of tests/test_brake_nd.py (seeds 11 and 7), ``count`` of each."""
    import test_brake_nd as t
    from hapsim.analysis.stability import brake_loop_matrix
    from hapsim.braking import BRAKE_GAIN, brake_damping, brake_rest
    ratios, rests, by_delay = [], 0, {}
    for n, M, Bf, hand, d, rng in t._devices(count, 11):
        direction = rng.standard_normal(n)
        v0 = direction / np.linalg.norm(direction) * rng.uniform(1.0, 30.0)
        B = brake_damping(M, t.RATE)
        limit = (math.inf if rng.uniform() < 0.5
                 else 0.5 * float(np.max(np.abs(B @ v0))))
        rest = brake_rest(0.5, M, Bf)
        travel, rep = t._throw(M, Bf, d, v0, limit, rest)
        free, _ = t._throw(M, Bf, d, v0, limit, rest, braking=False)
        ratios.append(travel / free)
        rests += rep["ended"] == "rest"
        by_delay[d] = max(by_delay.get(d, 0.0), travel / free)
    rho = [float(np.max(np.abs(np.linalg.eigvals(
        brake_loop_matrix(M + hand, Bf, brake_damping(M, t.RATE), t.T, d)))))
        for n, M, Bf, hand, d, _ in t._devices(count, 7)]
    return {"devices": count, "gain": BRAKE_GAIN, "travel_over_free_max": max(ratios),
            "travel_over_free_by_delay": {str(k): v for k, v in sorted(by_delay.items())},
            "ended_at_rest": rests, "spectral_radius_max": max(rho)}


def routes() -> list:
    """Each route's pushes of tests/test_brake_routes.py, braked and not."""
    import test_brake_routes as t
    out = []
    for push in ((0.1, -0.06), (-0.04, -0.08)):
        _, rec, _, _, far, v_end = t._haply2(_Patch, None, push)
        _, rec0, _, _, far0, _ = t._haply2(_Patch, False, push)
        out.append({"route": "2DIY", "push_nm": push, "left_at": rec["left"],
                    "brake": rec["brake"], "travel_rad": far, "free_travel_rad": far0,
                    "v_end": v_end})
    for push in ((0.1, -0.05, 0.02), (-0.03, 0.06, 0.08)):
        _, res, _, far, v_end = t._falcon(_Patch, None, push)
        _, res0, _, far0, _ = t._falcon(_Patch, False, push)
        out.append({"route": "Falcon", "push_nm": push, "left_at": res["stopped"][0],
                    "brake": res["brake"], "travel_rad": far, "free_travel_rad": far0,
                    "v_end": v_end})
    return out


def main(argv=None) -> int:
    """Print (and with ``--json`` write) the figures; exit 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=200)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    dv = devices(a.devices)
    print(f"{dv['devices']} random 2-D/3-D devices, delays 0-5, g = {dv['gain']:g}: braked "
          f"travel at most {dv['travel_over_free_max']:.3g} of friction's "
          f"(by delay: " + ", ".join(f"d={k} {v:.3g}" for k, v in
                                     dv["travel_over_free_by_delay"].items())
          + f"); at rest {dv['ended_at_rest']}, the rest out of time; largest spectral "
          f"radius with friction and a hand {dv['spectral_radius_max']:.4f}")
    rt = routes()
    for r in rt:
        bk = r["brake"]
        print(f"{r['route']:6s} push {r['push_nm']} N m: out at tick {r['left_at']}, "
              f"{max(abs(v) for v in bk['v_start']):.2f} rad/s, braked in {bk['periods']} "
              f"periods ({bk['ended']}): travel {r['travel_rad']:.3f} rad against "
              f"{r['free_travel_rad']:.3f} rad on friction alone "
              f"({r['travel_rad'] / r['free_travel_rad']:.3f})")
    if a.json:
        Path(a.json).write_text(json.dumps({"devices": dv, "routes": rt}, indent=1,
                                           default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())

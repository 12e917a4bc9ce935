"""Sub-sample delays through ``hapsim identify``: how often the stated intervals hold the
truth (issue 29 item 3; docs/identify.md, 'Sub-sample delay').

Seeded random devices (m 0.05-1 kg, b0 0-3 N s/m, Coulomb 0-0.2 N, noise 0-3 um) with a
delay drawn uniform in [0, DMAX) periods, identified over the framed mock in process
(lockstep: the fit, not the timing, is measured here), default excitation. Prints one row
per device and the coverage of the delay, mass and friction intervals.

    python tools/identify_subsample.py --n 30
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hapsim.commands.identify import identify  # noqa: E402
from hapsim.scene import Device  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30, help="devices (default 30)")
    ap.add_argument("--dmax", type=float, default=4.0, help="largest delay [periods]")
    ap.add_argument("--seed", type=int, default=2911)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    hit = {"d": 0, "m": 0, "b0": 0}
    widths = []
    t0 = time.monotonic()
    print(f"{'d true':>7} {'d stated':>9} {'interval':>19} {'m in':>5} {'b0 in':>6}")
    for i in range(a.n):
        d = float(rng.uniform(0.0, a.dmax))
        dev = Device(mass=float(np.exp(rng.uniform(np.log(0.05), np.log(1.0)))),
                     friction=float(rng.uniform(0.0, 3.0)),
                     coulomb=float(rng.uniform(0.0, 0.2)), delay=d, hold="zoh",
                     noise=float(rng.uniform(0.0, 3e-6)), force_limit=10.0)
        fit, _ = identify(device=dev, transport="inprocess", duration=2.0, force_limit=4.0,
                          max_delay=int(a.dmax) + 1, seed=i, progress=False,
                          handle_signals=False)
        e = fit.delay_estimate
        ok = {"d": e.contains(d), "m": fit.mass.contains(dev.mass),
              "b0": fit.friction.contains(dev.friction)}
        for k, v in ok.items():
            hit[k] += v
        widths.append(e.hi - e.lo)
        print(f"{d:7.3f} {e.value:9.3f} [{e.lo:7.3f}, {e.hi:7.3f}] {ok['m']!s:>5} "
              f"{ok['b0']!s:>6}", flush=True)
    print(f"coverage of {a.n}: delay {hit['d']}, mass {hit['m']}, friction {hit['b0']}; "
          f"delay interval width median {np.median(widths):.3f} periods; "
          f"{time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

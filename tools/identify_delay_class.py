"""The delay ``hapsim identify`` chooses on coarse encoders, over seeded random devices.

Usage::

    python tools/identify_delay_class.py [--n 40] [--seed 7000] [--samples 1500]
                                         [--white] [--json FILE]

Each device (m 0.02-2 kg log-uniform, b0 0-5 N s/m, Coulomb 0-0.3 N, d 0-20, encoder
quantum 0-400 um, noise 0-5 um) is simulated independently of the product (the simulator
of ``tests/test_identify_gaps.py``: exact zero-order hold from the matrix exponential, a
binary force of 0.1 x the force limit, 4 N or 40 m N/kg) and fitted by
:func:`hapsim.analysis.device_fit.fit_device` with the delays 0-20 tried (a protocol that
names no applied force). Counted: the delay returned as certain and exact, or wrong; said
ambiguous (``delay_certain`` False; ``truth_in_range``: the true delay inside
``delay_range``); refused (the reason). ``--white`` counts the likelihood ratio on every
sample as if independent and judges by the delay returned, as before issue 19 (when no
delay was said undetermined; its range then held the same hold's delays only). A measurement program, not a
test.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--seed", type=int, default=7000)
    ap.add_argument("--samples", type=int, default=1500)
    ap.add_argument("--white", action="store_true")
    ap.add_argument("--json", metavar="FILE")
    a = ap.parse_args(argv)
    from test_identify_gaps import T, _coarse_device, simulate

    from hapsim.analysis import device_fit
    from hapsim.errors import IdentificationError
    if a.white:
        device_fit.effective_samples = lambda r, offs, lag: float(np.size(r))
    rows, count = [], {"exact": 0, "wrong": 0, "ambiguous": 0, "refused": 0}
    for i in range(a.n):
        rng = np.random.default_rng(a.seed + i)
        m, b0, fc, d, q, s = _coarse_device(rng)
        n = a.samples
        _, x, f, _, _ = simulate(m, b0, fc, d, n, np.zeros(n, bool), rng, quantum=q, noise=s,
                                 force_limit=float(np.clip(40 * m, 4.0, 40.0)), prbs=True)
        row = {"m": m, "b0": b0, "fc": fc, "d": d, "quantum": q, "noise": s}
        try:
            fit = device_fit.fit_device(x, f, T, max_delay=20)
            row.update(delay=fit.delay, delay_range=list(fit.delay_range),
                       truth_in_range=bool(fit.delay_range[0] <= d <= fit.delay_range[1]))
            if fit.delay_certain or a.white:
                row["said"] = "exact" if fit.delay == d else "wrong"
            else:
                row["said"] = "ambiguous"
        except (IdentificationError, ArithmeticError) as exc:
            row.update(said="refused", reason=str(exc))
        count[row["said"]] += 1
        rows.append(row)
        print(f"{i:3d} m {m:.3g} b0 {b0:.2f} fc {fc:.2f} d {d:2d} q {q * 1e6:5.1f} um: "
              f"{row['said']}" + (f" d = {row['delay']} {row['delay_range']}" if "delay" in row
                                  else f" ({row['reason'][:70]})"), flush=True)
    print(json.dumps(count))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"count": count, "rows": rows, "args": vars(a)}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

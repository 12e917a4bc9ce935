"""Identification across lost STATEs: every stretch fitted against the longest one alone.

Usage::

    python tools/identify_gap_coverage.py [--n 24] [--seed 1000] [--loss 0.3]
                                          [--quantum 20e-6] [--samples 2500]

Each seeded random device (m 0.02-2 kg log-uniform, b0 0-5 N s/m, Coulomb 0-0.3 N, d 1-20,
encoder quantum 0-``--quantum`` m, noise 0.5-5 um) is simulated independently of the
product (the simulator of ``tests/test_identify_gaps.py``, excited as ``hapsim identify``
excites) behind a link that loses bursts of 1-6 STATEs (``--loss``: the chance of a burst
every 20-200 ticks), and fitted from its force_seq account twice: the whole record
(``fit_device(..., seq=)``, every stretch of consecutive ticks) and its longest stretch
alone (what ``identify`` fitted before issue 19). Prints per device which of m, b0, fc
(both directions) fall outside their 99.9 % intervals (``X``), and the totals with the
median mass interval ratio hi/lo. A measurement program, not a test.
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
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--loss", type=float, default=0.3)
    ap.add_argument("--quantum", type=float, default=20e-6)
    ap.add_argument("--samples", type=int, default=2500)
    a = ap.parse_args(argv)
    from test_identify_gaps import T, _lost, simulate

    from hapsim.analysis.device_fit import fit_device
    from hapsim.applied import account_from_force_seq
    from hapsim.errors import IdentificationError
    miss = {"all": [0, 0, 0, 0], "longest": [0, 0, 0, 0]}
    ratio = {"all": [], "longest": []}
    for i in range(a.n):
        rng = np.random.default_rng(a.seed + i)
        m = float(np.exp(rng.uniform(math.log(0.02), math.log(2.0))))
        b0, fc, d = float(rng.uniform(0, 5)), float(rng.uniform(0, 0.3)), int(rng.integers(1, 21))
        q, s = float(rng.uniform(0, a.quantum)), float(rng.uniform(0.5e-6, 5e-6))
        n = a.samples
        seq, x, f, fseq, status = simulate(m, b0, fc, d, n, _lost(rng, n, a.loss), rng,
                                           quantum=q, noise=s)
        acc = account_from_force_seq(seq, f, fseq, status)
        e = np.concatenate([[0], np.flatnonzero(np.diff(seq) != 1) + 1, [seq.size]])
        k = int(np.argmax(np.diff(e)))
        lo, hi = int(e[k]), int(e[k + 1])
        out = []
        for name, call in (("all", lambda: fit_device(x, f, T, applied=acc, seq=seq)),
                           ("longest", lambda: fit_device(x[lo:hi], f[lo:hi], T,
                                                          applied=acc.rows(lo, hi)))):
            try:
                fit = call()
            except IdentificationError:
                miss[name][3] += 1
                out.append(f"{name}: refused")
                continue
            ok = (fit.mass.contains(m), fit.friction.contains(b0),
                  fit.coulomb_pos.contains(fc) and fit.coulomb_neg.contains(fc))
            for j, v in enumerate(ok):
                miss[name][j] += not v
            ratio[name].append(fit.mass.hi / fit.mass.lo)
            out.append(f"{name}: {''.join('.' if v else 'X' for v in ok)} m {fit.mass.value:.4g}")
        print(f"{i:3d} m {m:.3g} b0 {b0:.2f} fc {fc:.2f} d {d:2d} q {q * 1e6:4.1f} um, "
              f"{seq.size} rows, longest {hi - lo}: " + " | ".join(out), flush=True)
    print(json.dumps({"misses (m, b0, fc, refused)": miss,
                      "median mass hi/lo": {k_: float(np.median(v)) if v else None
                                            for k_, v in ratio.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Benchmark of ``hapsim family``: batched eigenvalues against one member at a time.

Times :func:`hapsim.analysis.family.family` on ``configs/hand_wall.yaml`` with N seeded
members (stacked plants, one batched ``numpy.linalg.eigvals``), and, as the baseline
measured in the same run, the same members one by one (``closed_loop(scene, member=...)``
then ``numpy.linalg.eigvals``) on the first M of them, scaled to N. Prints both times and
the speed-up; each figure is the best of R runs (the machine may be shared).

Then the same with each correction of the virtual element (the family's matrices carry
the correction's state), against the per-member scalar analysis of the corrected loop
(``closed_loop_poles(LoopModel.from_device(device, rate, member), K, B)``: the roots of
``P K + Q B + R``) as the baseline, and counts the members whose stable/unstable verdicts
differ between the two (expected 0).

Usage::

    python tools/bench_family.py [--n N] [--m M] [--repeat R]

Exit code 0, or 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from hapsim.analysis.corrections import Correction  # noqa: E402
from hapsim.analysis.family import family, family_members  # noqa: E402
from hapsim.analysis.loop import STABILITY_TOL, LoopModel  # noqa: E402
from hapsim.analysis.loop_poles import spectral_radius  # noqa: E402
from hapsim.analysis.network import closed_loop  # noqa: E402
from hapsim.scene import load_scene  # noqa: E402


#: The corrections timed (parameters for the 0.05 kg handle of hand_wall.yaml).
CORRECTIONS = [{"kind": "velocity_sensor"}, {"kind": "velocity_filter", "cutoff_hz": 100.0},
               {"kind": "prediction"}, {"kind": "inertia_compensation", "mass": 0.02},
               {"kind": "virtual_coupling", "stiffness": 3000.0, "damping": 1.0}]


def main(argv=None) -> int:
    """Run the benchmark; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10000, help="members of the batched family")
    ap.add_argument("--m", type=int, default=500, help="members timed one by one")
    ap.add_argument("--repeat", type=int, default=3, help="best of R runs")
    a = ap.parse_args(argv)
    if a.n < 1 or a.m < 1 or a.repeat < 1:
        print("--n, --m and --repeat must be >= 1", file=sys.stderr)
        return 2
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sc = load_scene(os.path.join(here, "configs", "hand_wall.yaml"))
    mem = family_members(sc, a.n)
    family(sc, mem=mem[:10])                      # warm-up (imports, caches)
    batched, single = [], []
    for _ in range(a.repeat):
        t = time.perf_counter()
        family(sc, mem=mem)
        batched.append(time.perf_counter() - t)
        t = time.perf_counter()
        for row in mem[:a.m]:
            A, _ = closed_loop(sc, member=row)
            np.linalg.eigvals(A)
        single.append((time.perf_counter() - t) * mem.shape[0] / a.m)
    b, s = min(batched), min(single)
    print(f"family of {mem.shape[0]} members (configs/hand_wall.yaml): batched {b:.3f} s, "
          f"one by one {s:.3f} s (from {a.m}, scaled), speed-up x{s / b:.1f}")
    for spec in CORRECTIONS:
        csc = dataclasses.replace(sc, device=dataclasses.replace(sc.device, correction=spec))
        family(csc, mem=mem[:10])
        lk = csc.links[0]
        batched, single = [], []
        for _ in range(a.repeat):
            t = time.perf_counter()
            res = family(csc, mem=mem)
            batched.append(time.perf_counter() - t)
            t = time.perf_counter()
            rho = [spectral_radius(LoopModel.from_device(csc.device, csc.rate_hz, row),
                                   lk.stiffness, lk.damping) for row in mem[:a.m]]
            single.append((time.perf_counter() - t) * mem.shape[0] / a.m)
        differ = int(np.sum(res.stable[:a.m] != (np.array(rho) <= 1.0 + STABILITY_TOL)))
        b, s = min(batched), min(single)
        label = Correction.from_dict(spec).label()
        print(f"  {label:<36} batched {b:.3f} s, scalar one by one {s:.3f} s (from {a.m}, "
              f"scaled), speed-up x{s / b:.1f}; {int(np.sum(~res.stable))} unstable, verdicts "
              f"differing on the first {a.m}: {differ}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

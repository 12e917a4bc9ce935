"""Identification on a noisy sensor when the host stalls: the coverage of the intervals.

Usage::

    python tools/identify_noisy_stalls.py [--n 30] [--noise 50e-6] [--no-stalls]
                                          [--oracle] [--json FILE]

Each seeded random device of ``tests/test_identify_stall.py`` (m 0.02-2 kg log-uniform, b0
0-5 N s/m, d 0-10, no Coulomb friction; seeds 0 .. n-1) is excited by ``hapsim
identify``'s engine (its default 2 N, 10 mm, 1 kHz, 4 s) through that file's simulated
host, which stalls once for 0-100 ms while the device rests and then for up to the
longest stall seen, at random moments (``--no-stalls``: never), the device on its own
clock holding the last force meanwhile (the exact zero-order-hold step). White sensor
noise of ``--noise`` m (standard deviation) is added to the positions, and the record is
fitted by :func:`hapsim.analysis.device_fit.fit_device` with the applied force known (the
device's own account, delay 0: no delay search). ``--oracle`` chooses the fit's moving
stretches on the noise-free positions, at the threshold the noisy record sets (a sensor
reach ``1.5 q`` with ``q = 4 sigma / 1.5``): what the fit gives when the selection of
its samples owes nothing to their noise.

Prints one row per device (truth, estimates with their 99.9 % intervals, ``MISS`` where
the truth is outside, or the refusal), and the totals: refused, misses of the mass and
the friction, the median and spread of the mass's relative error. A measurement program,
not a test (docs/identify.md, "A noisy sensor under host stalls").
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import types

import numpy as np

from provenance import command_line  # tools/, beside this file

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=30, help="devices: seeds 0 .. n-1")
    ap.add_argument("--noise", type=float, default=50e-6, help="sensor noise [m], sd")
    ap.add_argument("--no-stalls", action="store_true", help="a host that never stalls")
    ap.add_argument("--oracle", action="store_true",
                    help="stretches chosen on the noise-free positions")
    ap.add_argument("--json", help="write the rows and totals here")
    a = ap.parse_args(argv)
    import hapsim.analysis.device_fit as dfm
    from hapsim.analysis.device_fit_stretches import moving_stretches
    from hapsim.errors import IdentificationError
    from test_identify_stall import N, T, _case, run_stalled

    rows = []
    for seed in range(a.n):
        m, b0, d, stalls = _case(seed)
        if a.no_stalls:
            stalls = {}
        u = np.zeros(N)
        x = run_stalled(m, b0, d, stalls, seed, applied=u)
        xm = x + a.noise * np.random.default_rng(seed).standard_normal(x.size)
        select = moving_stretches
        if a.oracle:
            q = 4.0 * a.noise / 1.5

            def select(_x, _q, pieces=None, _clean=x, **kw):
                return moving_stretches(_clean, q, pieces=pieces, **kw)
        row = {"seed": seed, "m": m, "b0": b0, "d": d,
               "longest_stall_ms": max(stalls.values(), default=0) * T * 1e3,
               "excursion_mm": float(np.max(np.abs(x))) * 1e3}
        dfm.moving_stretches, saved = select, dfm.moving_stretches
        try:
            fit = dfm.fit_device(xm, u, T,
                                 applied=types.SimpleNamespace(applied=u, delay=0, known=None))
            for k, truth in (("mass", m), ("friction", b0)):
                e = getattr(fit, k)
                row[k] = [e.value, e.lo, e.hi]
                row[k + "_inside"] = bool(e.lo <= truth <= e.hi)
        except IdentificationError as exc:
            row["refused"] = str(exc)
        finally:
            dfm.moving_stretches = saved
        rows.append(row)
        if "refused" in row:
            said = "refused: " + row["refused"][:60]
        else:
            said = " | ".join(
                f"{k[:2]} {row[k][0]:.4g} [{row[k][1]:.4g}, {row[k][2]:.4g}]"
                f"{'' if row[k + '_inside'] else ' MISS'}" for k in ("mass", "friction"))
        print(f"{seed:3d} m {m:.3f} b0 {b0:.2f} d {d:2d} stall {row['longest_stall_ms']:5.1f} "
              f"ms excursion {row['excursion_mm']:.2f} mm | {said}", flush=True)
    fitted = [r for r in rows if "refused" not in r]
    rel = [r["mass"][0] / r["m"] - 1.0 for r in fitted]
    totals = {"devices": len(rows), "fitted": len(fitted), "refused": len(rows) - len(fitted),
              "mass_misses": sum(not r["mass_inside"] for r in fitted),
              "friction_misses": sum(not r["friction_inside"] for r in fitted),
              "mass_rel_error_median": statistics.median(rel) if rel else None,
              "mass_rel_error_sd": statistics.stdev(rel) if len(rel) > 1 else None}
    print(f"fitted {len(fitted)} of {len(rows)}; misses: mass {totals['mass_misses']}, "
          f"friction {totals['friction_misses']}; mass relative error median "
          f"{totals['mass_rel_error_median']:+.4f}, sd {totals['mass_rel_error_sd']:.4f}"
          if len(rel) > 1 else f"fitted {len(fitted)} of {len(rows)}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"command": command_line("tools/identify_noisy_stalls.py", argv),
                       "noise": a.noise, "stalls": not a.no_stalls,
                       "oracle": a.oracle, "rows": rows, "totals": totals}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

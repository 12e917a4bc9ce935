"""A driver's closed loop on its byte-exact mock with seeded byte loss: what is measured.

Usage::

    python tools/driver_loss.py [--drivers haply firefader] [--seeds 1 2 3 4]
                                [--drop-tx 0.005] [--drop-rx 0] [--corrupt-tx 0]

For each driver and seed, runs ``configs/<driver>.yaml`` through its mock
(:func:`hapsim.daemon.runner.run_scene` with ``driver_faults``) and prints the bytes the
link lost, the missing samples (estimated ones), re-synchronisations, the stop reason and
the relative errors of the measured k and b against the prediction with their stated
half-widths and, of those, the worst case of the estimated samples and of the forces a
missing answer leaves open (``k_bound_rows``), and the late ticks the account took out (the
FireFader's enable ramp after a host silence). A measurement program (issue 20), not a
test: real time, on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="driver_loss")
    p.add_argument("--drivers", nargs="+", default=["haply", "firefader"])
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4])
    p.add_argument("--drop-tx", type=float, default=1 / 200)
    p.add_argument("--drop-rx", type=float, default=0.0)
    p.add_argument("--corrupt-tx", type=float, default=0.0)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    from hapsim.daemon.runner import run_scene
    from hapsim.scene import load_scene
    rows = []
    for drv in a.drivers:
        for seed in a.seeds:
            faults = {"drop_tx": a.drop_tx, "drop_rx": a.drop_rx, "corrupt_tx": a.corrupt_tx,
                      "seed": seed}
            rep = run_scene(load_scene(f"configs/{drv}.yaml"), driver=drv,
                            handle_signals=False, rt_priority=0, driver_faults=faults)
            m, pr, lp = rep["measured"], rep["predicted"], rep["loop"]
            rel = m.get("rel_err") or {}
            row = {"driver": drv, "seed": seed, "lost_bytes": lp["mock"]["faults"],
                   "ticks": lp["ticks"], "missing": lp["driver"]["missing"],
                   "estimated": lp["estimated"], "resyncs": lp["driver"]["resyncs"],
                   "stop": lp["stop_reason"], "k_rel": rel.get("k"), "b_rel": rel.get("b"),
                   "k_half_rel": (m["k_unc"] / pr["k"]) if "k_unc" in m else None,
                   "b_half_rel": (m["b_unc"] / pr["b"]) if "b_unc" in m else None,
                   # the share of the estimated samples' (and open forces') worst case
                   "k_bound_rel": m.get("k_bound_rows", 0.0) / pr["k"],
                   "b_bound_rel": m.get("b_bound_rows", 0.0) / pr["b"],
                   "late_accounted": m.get("late_accounted"),
                   "samples_used": m.get("samples_used"),
                   "within": m.get("within"), "error": m.get("error")}
            rows.append(row)
            if not a.json:
                def pct(v):
                    return "   -   " if v is None else f"{v * 100:+.3f}%"
                print(f"{drv:10s} seed {seed}: missing {row['missing']:4d} (estimated "
                      f"{row['estimated']:4d}), resyncs {row['resyncs']:3d}, stop "
                      f"{row['stop']}; k {pct(row['k_rel'])} (+-{pct(row['k_half_rel'])}, "
                      f"worst case of the estimates {pct(row['k_bound_rel'])}), "
                      f"b {pct(row['b_rel'])} (+-{pct(row['b_half_rel'])}, "
                      f"{pct(row['b_bound_rel'])}), fitted {row['samples_used']} samples, "
                      f"late accounted {row['late_accounted'] or 0}, within "
                      f"{row['within']}{'; ' + row['error'] if row['error'] else ''}",
                      flush=True)
    if a.json:
        json.dump(rows, sys.stdout, indent=1)
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())

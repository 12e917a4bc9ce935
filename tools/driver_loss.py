"""A driver's closed loop on its byte-exact mock with seeded byte loss: what is measured.

Usage::

    python tools/driver_loss.py [--drivers haply firefader] [--seeds 1 2 3 4]
                                [--drop-tx 0.005] [--drop-rx 0.005] [--corrupt-tx 0]
                                [--json [PATH]]

``--json`` alone writes the JSON to stdout (and nothing else there); ``--json PATH`` writes
it to a file (``docs/driver_loss.json``, quoted by ``docs/drivers.md``) and prints the
human-readable lines as well. The file holds the run conditions (command, faults, seeds,
load average, CPU count), one row per run and a summary per driver (runs within, ranges).

For each driver and seed, runs ``configs/<driver>.yaml`` through its mock
(:func:`hapsim.pipeline.runner.run_scene` with ``driver_faults``: seeded byte loss in both
directions by default, host -> device and device -> host) and prints the bytes the
link lost, the host ticks the mock's clock counted against the firmware passes it ran, the missing samples (estimated ones), re-synchronisations, the stop reason and
the relative errors of the measured k and b against the prediction with their stated
half-widths and, of those, the worst case of the estimated samples and of the forces a
missing answer leaves open (``k_bound_rows``), and the late ticks the account took out (the
FireFader's enable ramp after a host silence). A measurement program (issue 20), not a
test: real time, on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from provenance import command_line  # tools/, beside this file


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="driver_loss")
    p.add_argument("--drivers", nargs="+", default=["haply", "firefader"])
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4])
    p.add_argument("--drop-tx", type=float, default=1 / 200)
    p.add_argument("--drop-rx", type=float, default=1 / 200)
    p.add_argument("--corrupt-tx", type=float, default=0.0)
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="PATH",
                   help="JSON to stdout (bare) or to PATH")
    a = p.parse_args(argv)
    load_before = _load()
    from hapsim.pipeline.runner import run_scene
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
                   "host_ticks": lp["mock"].get("host_ticks"),
                   "passes": lp["mock"].get("passes"),
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
            if a.json != "-":
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
    if a.json is None:
        return 0
    out = {"command": command_line("tools/driver_loss.py", argv),
           "faults": {"drop_tx": a.drop_tx, "drop_rx": a.drop_rx,
                      "corrupt_tx": a.corrupt_tx},
           "seeds": a.seeds, "load_before": load_before, "load_after": _load(),
           "cpus": os.cpu_count(), "runs": rows, "summary": summarize(rows)}
    if a.json == "-":
        json.dump(out, sys.stdout, indent=1)
        print()
    else:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
            f.write("\n")
    return 0


def _load():
    """The 1-minute load average, or None where the platform has none."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _span(vals):
    vals = [v for v in vals if v is not None]
    return {"min": min(vals), "max": max(vals)} if vals else None


def summarize(rows):
    """Per driver: the runs, how many measured within the stated uncertainty, and the
    ranges of |k|, |b| relative errors, their stated half-widths, the estimated samples'
    worst-case share and the estimated samples per run.

    Parameters
    ----------
    rows : list of dict
        The rows :func:`main` measures (one per driver and seed).

    Returns
    -------
    dict
        ``{driver: {"runs", "within", "measured", "abs_k_rel", "abs_b_rel", "k_half_rel",
        "b_half_rel", "k_bound_rel", "b_bound_rel", "k_bound_share", "b_bound_share",
        "estimated"}}`` (``*_bound_share``: the worst case's share of the half-width), each range a
        ``{"min", "max"}`` (None where no run measured it); relative values are fractions.
    """
    out = {}
    for drv in dict.fromkeys(r["driver"] for r in rows):
        rs = [r for r in rows if r["driver"] == drv]
        out[drv] = {
            "runs": len(rs), "within": sum(1 for r in rs if r["within"] is True),
            "measured": sum(1 for r in rs if r["k_rel"] is not None),
            "abs_k_rel": _span([abs(r["k_rel"]) for r in rs if r["k_rel"] is not None]),
            "abs_b_rel": _span([abs(r["b_rel"]) for r in rs if r["b_rel"] is not None]),
            "k_half_rel": _span([r["k_half_rel"] for r in rs]),
            "b_half_rel": _span([r["b_half_rel"] for r in rs]),
            "k_bound_rel": _span([r["k_bound_rel"] for r in rs]),
            "b_bound_rel": _span([r["b_bound_rel"] for r in rs]),
            "k_bound_share": _span([r["k_bound_rel"] / r["k_half_rel"] for r in rs
                                    if r["k_half_rel"]]),
            "b_bound_share": _span([r["b_bound_rel"] / r["b_half_rel"] for r in rs
                                    if r["b_half_rel"]]),
            "estimated": _span([r["estimated"] for r in rs]),
        }
    return out


if __name__ == "__main__":
    sys.exit(main())

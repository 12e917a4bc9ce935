"""A host silence on the FireFader: what the .ino's enable gate does to a measurement, and
what the host's replay of it (``FireFader.account``) gives back. Offline, deterministic.

Usage::

    python tools/firefader_silence.py [--silences 0.05 0.09 0.12 0.2]
                                      [--rows 100 500 40] [--json [PATH]]

``--json`` alone writes the JSON to stdout (and nothing else there); ``--json PATH`` writes
it to a file (``docs/firefader_silence.json``, quoted by ``docs/drivers.md``) and prints
the human-readable lines as well.

For each silence length and each row it is placed after, ``configs/firefader.yaml`` is
closed offline through hapsim's engine and the firmware's own loop
(:func:`hapsim.emulated.driver_mock.firefader_offline_loop`: no pty, no real time), the host silent
that long once. A silence above 0.1 s makes the firmware zero its enable (the mock's
sharp threshold; the host's account takes 0.08-0.14 s as either), and the force is off
for the 5 passes the enable needs to pass its gate of 20. Each record is measured twice
(:func:`hapsim.pipeline.runner.identify_run`): with the driver's account (the gate replayed
from the host's clock) and blind (the forces sent taken as applied). The rows: whether
the account holds the mock's applied force on every row (within its half-width), the
rows it took out, and (k, b) against the prediction with the stated half-widths.
"""

from __future__ import annotations

import argparse
import json
import sys
import types

from provenance import command_line  # tools/, beside this file


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="firefader_silence")
    p.add_argument("--silences", nargs="+", type=float, default=[0.05, 0.09, 0.12, 0.2])
    p.add_argument("--rows", nargs=3, type=int, default=[100, 500, 40],
                   metavar=("FIRST", "LAST", "STEP"))
    p.add_argument("--n", type=int, default=600, help="rows per record")
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="PATH",
                   help="JSON to stdout (bare) or to PATH")
    a = p.parse_args(argv)
    import numpy as np

    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import identify_run, prepare_run
    from hapsim.emulated.driver_mock import firefader_offline_loop
    from hapsim.scene import load_scene
    prep = prepare_run(load_scene("configs/firefader.yaml"),
                       RunOptions(driver="firefader", rt_priority=0, handle_signals=False))
    pk, pb = prep.pred["k"], prep.pred["b"]

    def measure(cols, drv):
        tel = types.SimpleNamespace(wrapped=False, n=cols["seq"].size, head=cols["seq"].size,
                                    columns=lambda *x: cols)
        return identify_run(prep, tel, None, driver=drv)

    rows = []
    first, last, step = a.rows
    for s in a.silences:
        for at in range(first, last + 1, step):
            cols, drv, applied = firefader_offline_loop(prep.scene, a.n, silence_at=at,
                                                        silence=s)
            acc = drv.account(cols, cols["force"])
            if acc is None:
                exact, n_late = True, 0
                dev_max = float(np.max(np.abs(cols["force"][:-1] - applied[1:])))
            else:
                # (row 1: the device's own clamp at its force limit, not the firmware's)
                err = np.abs(acc.applied - applied)[2:] - acc.half_width[2:]
                exact, n_late = bool(np.all(err <= 1e-9)), int(acc.n_late)
                dev_max = float(err.max())
            m = measure(cols, drv)
            bl = measure(cols, None)
            row = {"silence": s, "at": at, "late_accounted": n_late,
                   "account_holds_applied": exact, "account_excess_max": dev_max,
                   "k_rel": m["k"] / pk - 1, "b_rel": m["b"] / pb - 1,
                   "k_half_rel": m["k_unc"] / pk, "b_half_rel": m["b_unc"] / pb,
                   "k_in_half_widths": (m["k"] - pk) / m["k_unc"],
                   "within": bool(m["within"]),
                   "blind_k_rel": bl["k"] / pk - 1, "blind_b_rel": bl["b"] / pb - 1,
                   "blind_within": bool(bl["within"])}
            rows.append(row)
            if a.json != "-":
                print(f"silence {s:.3f} s after row {at:3d}: {n_late} rows taken out, "
                      f"account holds the applied force {exact}; k {row['k_rel']:+.3%} "
                      f"(+-{row['k_half_rel']:.3%}), b {row['b_rel']:+.2%} "
                      f"(+-{row['b_half_rel']:.2%}), within {row['within']}; blind k "
                      f"{row['blind_k_rel']:+.3%}, b {row['blind_b_rel']:+.2%}, within "
                      f"{row['blind_within']}", flush=True)
    if a.json is None:
        return 0
    out = {"command": command_line("tools/firefader_silence.py", argv),
           "scene": "configs/firefader.yaml", "n": a.n, "runs": rows,
           "summary": summarize(rows)}
    if a.json == "-":
        json.dump(out, sys.stdout, indent=1)
        print()
    else:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
            f.write("\n")
    return 0


def _span(vals):
    vals = [v for v in vals if v is not None]
    return {"min": min(vals), "max": max(vals)} if vals else None


def summarize(rows):
    """Per silence length, and over all: runs, how many the account held exactly, how
    many measured within with the account and blind, and the ranges of the rows taken out
    and of the k error in stated half-widths.

    Parameters
    ----------
    rows : list of dict
        The rows :func:`main` measures.

    Returns
    -------
    dict
        ``{"all": {...}, "s<silence in ms>": {...}}``, each ``{"runs", "account_exact",
        "within", "blind_within", "late_accounted", "k_in_half_widths", "abs_b_rel",
        "blind_abs_b_rel"}`` (ranges as ``{"min", "max"}``; relative values fractions).
    """
    def one(rs):
        return {"runs": len(rs),
                "account_exact": sum(r["account_holds_applied"] for r in rs),
                "within": sum(r["within"] for r in rs),
                "blind_within": sum(r["blind_within"] for r in rs),
                "late_accounted": _span([r["late_accounted"] for r in rs]),
                "k_in_half_widths": _span([r["k_in_half_widths"] for r in rs]),
                "abs_b_rel": _span([abs(r["b_rel"]) for r in rs]),
                "blind_abs_b_rel": _span([abs(r["blind_b_rel"]) for r in rs])}
    out = {"all": one(rows)}
    for s in dict.fromkeys(r["silence"] for r in rows):
        out[f"s{round(s * 1000)}"] = one([r for r in rows if r["silence"] == s])
    return out


if __name__ == "__main__":
    sys.exit(main())

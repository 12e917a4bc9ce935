"""``hapsim run`` in real time beside CPU-bound processes: is the verdict still right?

Usage::

    python tools/run_loaded.py [--runs 5] [--busy 2] [--scene configs/wall.yaml]
                               [--json docs/run_loaded.json] [-- extra run options]

Starts ``--busy`` CPU-bound processes (busy loops, stopped at the end), then runs
``hapsim run SCENE --json`` (the embedded mock on a real pty, real time) ``--runs`` times
and prints, per run: late ticks (accounted as known inputs of the loop), missed STATEs, the
samples measured, the relative errors of k and b, the stated half-widths and the verdict.
Also writes them as JSON. A measurement program, not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--scene", default="configs/wall.yaml")
    ap.add_argument("--json", metavar="FILE")
    a = ap.parse_args(argv)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(a.busy)]
    rows = []
    try:
        time.sleep(0.5)
        for i in range(a.runs):
            load = os.getloadavg()[0]
            r = subprocess.run([sys.executable, "-m", "hapsim", "run", a.scene, "--json",
                                *extra], capture_output=True, text=True, timeout=600)
            try:
                rep = json.loads(r.stdout)
            except ValueError:
                rep = {}
            m = rep.get("measured", {})
            lp = rep.get("loop", {})
            pred = rep.get("predicted", {})
            row = {"run": i, "exit": r.returncode, "load1": load,
                   "late": lp.get("late"), "missed": lp.get("missed"),
                   "skipped": lp.get("skipped"), "late_accounted": m.get("late_accounted"),
                   "device_delay": m.get("device_delay"),
                   "samples_used": m.get("samples_used"),
                   "k_err": (m["k"] - pred["k"]) if "k" in m else None,
                   "b_err": (m["b"] - pred["b"]) if "b" in m else None,
                   "k_interval": m.get("k_interval"), "b_interval": m.get("b_interval"),
                   "rel_err": m.get("rel_err"), "within": m.get("within"),
                   "verdict": m.get("verdict") or m.get("error"),
                   "traceback": "Traceback" in r.stderr}
            rows.append(row)
            re_ = row["rel_err"] or {}
            print(f"run {i}: exit {row['exit']} load {load:.1f} late {row['late']} "
                  f"(accounted {row['late_accounted']}) missed {row['missed']} "
                  f"skipped {row['skipped']} samples {row['samples_used']} "
                  f"rel.err k {re_.get('k', float('nan')):+.2e} "
                  f"b {re_.get('b', float('nan')):+.2e} "
                  f"| +- k {row['k_interval'] or float('nan'):.3g} "
                  f"b {row['b_interval'] or float('nan'):.3g} | {row['verdict']}", flush=True)
    finally:
        for p in busy:
            p.terminate()
            p.wait()
    within = sum(bool(r["within"]) for r in rows)
    print(f"within the stated uncertainty: {within}/{len(rows)} (beside {a.busy} CPU-bound "
          f"processes)")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"command": "python tools/run_loaded.py " + " ".join(
                sys.argv[1:] if argv is None else sys.argv[1:]), "busy": a.busy,
                "scene": a.scene, "runs": rows, "within": within}, fh, indent=1)
    return 0 if within == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())

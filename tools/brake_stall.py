"""Stop the host of ``hapsim run`` (SIGSTOP) for a while mid-run and print how the braking
after the safety stop ends it (docs/reliability.md, "Braking before the zero force").

A board without a watchdog (the Hapkit sketch behind the embedded pty mock of
``configs/hapkit_serial.yaml``) holds its last force while the host does not run; the
host wakes late, stops, brakes the handle to rest, then sends zero force. For each run
this prints the stop, the speed the host found, how long the braking took, and the
coast that friction alone would have given from that speed, ``|v| m / b`` (closed form),
beside the handle's true largest excursion (the mock's own record); in metres, or in
radians for a rotary axis (``configs/haply.yaml``: the M3's joint, its inertia as mass).

Usage::

    python tools/brake_stall.py                      # 5 runs, 500 ms stalls
    python tools/brake_stall.py --stall-ms 600 --runs 3 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def one(scene: str, stall_s: float, at_s: float) -> dict:
    """One ``hapsim run SCENE --json`` whose process is stopped ``stall_s`` at ``at_s``."""
    p = subprocess.Popen([sys.executable, "-m", "hapsim", "run", scene, "--json",
                          "--duration", "2"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    time.sleep(at_s)
    os.kill(p.pid, signal.SIGSTOP)
    time.sleep(stall_s)
    os.kill(p.pid, signal.SIGCONT)
    out, err = p.communicate()
    try:
        rep = json.loads(out)
    except json.JSONDecodeError:
        raise SystemExit(f"hapsim run gave no report (exit {p.returncode}):\n{err[-2000:]}")
    return rep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="configs/hapkit_serial.yaml",
                    help="scene run (default: %(default)s)")
    ap.add_argument("--stall-ms", type=float, default=500.0, help="host stop [ms]")
    ap.add_argument("--at", type=float, default=1.5,
                    help="when the stop begins, after the command starts [s]")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", metavar="FILE", help="write the runs as JSON")
    args = ap.parse_args(argv)
    from hapsim.scene import load_scene
    sc = load_scene(str(ROOT / args.scene))
    dev = sc.device
    # a rotary axis (the Haply M3's joint: device.mass an inertia) is in radians
    u = "rad" if "haply" in str(getattr(dev, "protocol", "") or "") else "m"
    rows = []
    for i in range(args.runs):
        print(f"run {i + 1}/{args.runs} ...", file=sys.stderr, flush=True)
        rep = one(args.scene, args.stall_ms / 1e3, args.at)
        lp = rep["loop"]
        bk = lp.get("brake") or {}
        v0 = bk.get("v_start")
        row = {"stop": lp["stop_reason"], "true_excursion_m": lp["mock"].get("true_excursion"),
               "workspace_m": lp["safety"]["position_limit"],
               "brake_periods": bk.get("periods"), "brake_s": bk.get("seconds"),
               "brake_ended": bk.get("ended"), "v_start": v0,
               "friction_coast_m": None if v0 is None or dev.friction <= 0
               else abs(v0) * dev.mass / dev.friction,
               "verdict": (rep.get("measured") or {}).get("verdict")}
        rows.append(row)
        print(f"{row['stop'][:70]:70s} v {v0 if v0 is None else round(v0, 3)} {u}/s, braked "
              f"{row['brake_periods']} periods ({row['brake_s'] or 0:.3f} s, "
              f"{row['brake_ended']}); friction alone: "
              f"{row['friction_coast_m'] if row['friction_coast_m'] is None else round(row['friction_coast_m'], 3)} {u}"
              f" further; true excursion {row['true_excursion_m']:.3f} {u} "
              f"(workspace {row['workspace_m']:g} {u})")
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": args.scene, "stall_ms": args.stall_ms,
                                               "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

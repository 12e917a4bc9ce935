"""``hapsim run`` in real time, as users run it: is measured = predicted every time?

Usage::

    python tools/run_loaded.py [--mock-runs 5] [--busy 2] [--firmware-runs 3]
                               [--scene configs/wall.yaml] [--firmware-scene configs/hapkit.yaml]
                               [--telemetry DIR] [--json docs/run_loaded.json]
                               [-- extra run options]

Two parts, one table:

- ``mock``: starts ``--busy`` CPU-bound processes (busy loops, stopped after this part),
  then runs ``hapsim run SCENE --json`` (the embedded mock on a real pty, real time)
  ``--mock-runs`` times.
- ``firmware``: ``--firmware-runs`` times, starts ``hapsim mock --firmware --scene
  FIRMWARE_SCENE`` (the Hapkit firmware on the emulated ATmega328P, on the wall clock, its
  own process and pty) and runs ``hapsim run FIRMWARE_SCENE --port PORT --json`` against
  it, as docs/mock.md shows.

Per run it prints the machine's load, late ticks (accounted as known inputs of the loop),
missed and skipped STATEs, the samples and stretches measured, the errors of k and b
against the prediction, the stated half-widths (the fit's, the sensor's and the wire's /
actuator's, derived in hapsim.analysis.identify.measure_felt, not tuned here) and the
verdict; then how many runs are within the stated uncertainty. Writes the same as JSON.
A measurement program, not a test: on a shared machine its figures are loaded ones (the
load is in every row). Exit 0 when every run is within.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from provenance import command_line  # tools/, beside this file


def _row(kind: str, i: int, load: float, r: subprocess.CompletedProcess) -> dict:
    """One run's row from ``hapsim run --json``'s report."""
    try:
        rep = json.loads(r.stdout)
    except ValueError:
        rep = {}
    m = rep.get("measured", {})
    lp = rep.get("loop", {})
    pred = rep.get("predicted", {})
    return {"part": kind, "run": i, "exit": r.returncode, "load1": load,
            "late": lp.get("late"), "missed": lp.get("missed"),
            "skipped": lp.get("skipped"), "late_accounted": m.get("late_accounted"),
            "device_delay": m.get("device_delay"),
            "samples_used": m.get("samples_used"), "stretches_used": m.get("stretches_used"),
            "k": m.get("k"), "b": m.get("b"), "k_pred": pred.get("k"),
            "b_pred": pred.get("b"),
            "k_err": (m["k"] - pred["k"]) if "k" in m else None,
            "b_err": (m["b"] - pred["b"]) if "b" in m else None,
            "k_interval": m.get("k_interval"), "b_interval": m.get("b_interval"),
            "interval_note": m.get("interval_note"),
            "within": m.get("within"), "verdict": m.get("verdict") or m.get("error"),
            "stdout_json": bool(rep), "traceback": "Traceback" in r.stderr,
            "stderr_tail": r.stderr[-400:] if r.returncode else ""}


def _print(row: dict) -> None:
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "-"
    print(f"{row['part']:8s} {row['run']:2d} exit {row['exit']} load {row['load1']:4.1f} "
          f"late {row['late']} (acc. {row['late_accounted']}) missed {row['missed']} "
          f"skipped {row['skipped']} | samples {row['samples_used']} in "
          f"{row['stretches_used']} | k {f(row['k_err'], '+.3g')} +- "
          f"{f(row['k_interval'], '.3g')} N/m, b {f(row['b_err'], '+.3g')} +- "
          f"{f(row['b_interval'], '.3g')} N s/m | {row['verdict']}", flush=True)


def run_mock(a, extra, tel_dir) -> list:
    """The ``mock`` part (module notes)."""
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(a.busy)]
    rows = []
    try:
        time.sleep(0.5)
        for i in range(a.mock_runs):
            load = os.getloadavg()[0]
            tel = ["--telemetry", os.path.join(tel_dir, f"mock{i}.npz")] if tel_dir else []
            r = subprocess.run([sys.executable, "-m", "hapsim", "run", a.scene, "--json",
                                *tel, *extra], capture_output=True, text=True, timeout=600)
            rows.append(_row("mock", i, load, r))
            _print(rows[-1])
    finally:
        for p in busy:
            p.terminate()
            p.wait()
    return rows


def run_firmware(a, extra, tel_dir) -> list:
    """The ``firmware`` part (module notes)."""
    rows = []
    for i in range(a.firmware_runs):
        board = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--firmware",
                                  "--scene", a.firmware_scene], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            line = board.stdout.readline()
            load = os.getloadavg()[0]
            if not line.startswith("PORT"):
                board.kill()
                err = board.stderr.read()
                rows.append({"part": "firmware", "run": i, "exit": -1, "load1": load,
                             "verdict": "the board did not start: " + line + err[-300:],
                             "within": False, "traceback": "Traceback" in err})
                print(rows[-1]["verdict"], flush=True)
                continue
            port = line.split()[1]
            tel = ["--telemetry", os.path.join(tel_dir, f"fw{i}.npz")] if tel_dir else []
            r = subprocess.run([sys.executable, "-m", "hapsim", "run", a.firmware_scene,
                                "--port", port, "--json", *tel, *extra],
                               capture_output=True, text=True, timeout=600)
            rows.append(_row("firmware", i, load, r))
            _print(rows[-1])
        finally:
            board.terminate()
            try:
                board.wait(20)
            except subprocess.TimeoutExpired:
                board.kill()
                board.wait()
    return rows


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cmd = command_line("tools/run_loaded.py", argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mock-runs", type=int, default=5)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--firmware-runs", type=int, default=3)
    ap.add_argument("--scene", default="configs/wall.yaml")
    ap.add_argument("--firmware-scene", default="configs/hapkit.yaml")
    ap.add_argument("--telemetry", metavar="DIR", help="keep each run's telemetry there")
    ap.add_argument("--json", metavar="FILE")
    a = ap.parse_args(argv)
    if a.telemetry:
        os.makedirs(a.telemetry, exist_ok=True)
    t0 = time.time()
    rows = run_mock(a, extra, a.telemetry) + run_firmware(a, extra, a.telemetry)
    within = sum(bool(r.get("within")) for r in rows)
    for part in ("mock", "firmware"):
        pr = [r for r in rows if r["part"] == part]
        if pr:
            print(f"{part}: within the stated uncertainty {sum(bool(r.get('within')) for r in pr)}"
                  f"/{len(pr)}" + (f" (beside {a.busy} CPU-bound processes)"
                                   if part == "mock" else " (real time, wall clock)"))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"command": cmd, "busy": a.busy, "scene": a.scene,
                       "firmware_scene": a.firmware_scene, "runs": rows, "within": within,
                       "of": len(rows), "wall_s": time.time() - t0,
                       "load1_end": os.getloadavg()[0]}, fh, indent=1)
    return 0 if within == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())

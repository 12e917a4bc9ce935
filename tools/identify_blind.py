"""Blind identification: hidden random devices, coverage of the reported intervals.

Usage::

    python tools/identify_blind.py [--n 30] [--seed 19] [--busy 2] [--fractional]
                                   [--noise-free] [--mode port|inprocess]
                                   [--json docs/identify_blind.json]

``--mode port`` (default): each hidden device is a scene file given to a standalone
``hapsim mock --scene DEV.yaml`` (real time, its own process, a real pty), identified by
``hapsim identify --port PORT --json`` with its default options (no --force-limit, no
--duration, no --envelope: the excitation designs itself), as a user would; every device
runs beside ``--busy`` CPU-bound processes (busy loops this program starts and stops).
``--mode inprocess``: the lockstep in-process mock (no real time), as the test suite's.

The devices (issue 29): m 0.02-2 kg (log-uniform), b0 0-5 N s/m, Coulomb friction 0-0.5 N,
d 1-20 samples (d = 0 exists in lockstep only; ``inprocess`` draws 0-20; ``--fractional``:
a real number of periods, 1-20), sensor noise 0-50 um and encoder quantum 0-20 um (each
zero for a quarter of the devices), force limit 10 N. ``--noise-free``: no noise, no
quantum and Coulomb friction 0.05-0.5 N (the same draws otherwise): the records where
nothing hides a model error, so a stop the model cannot follow shows as "not explained".

A row counts as identified when ``identify`` printed a device; a safety stop is the loop's
``safety_stop``; the coverage of a quantity is the share of identified devices whose truth
lies inside the reported interval (d: the reported delay interval, ``delay_range`` or the
real-valued ``delay_estimate``, holds the truth).

Prints one row per device (truth, estimate, interval, misses), the coverage per quantity
(the share of devices whose truth lies in the reported interval; d: exact), the exit codes
and whether any traceback was seen; writes the same as JSON. A benchmark-style program,
not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from provenance import command_line  # tools/, beside this file

QUANTITIES = ("m", "b0", "fc+", "fc-", "d", "q", "noise")


def draw(rng, realtime: bool, fractional: bool = False, noise_free: bool = False) -> dict:
    """One hidden device (module notes)."""
    dev = {"mass": float(np.exp(rng.uniform(math.log(0.02), math.log(2.0)))),
           "friction": float(rng.uniform(0.0, 5.0)),
           "coulomb": float(rng.uniform(0.0, 0.5)),
           "delay": (round(float(rng.uniform(1.0, 20.0)), 3) if fractional else
                     int(rng.integers(1 if realtime else 0, 21))),
           "position_resolution": float(rng.uniform(0, 20e-6)) if rng.random() < 0.75
           else 0.0,
           "noise": float(rng.uniform(0, 50e-6)) if rng.random() < 0.75 else 0.0,
           "hold": "zoh", "force_limit": 10.0}
    if noise_free:
        dev.update(position_resolution=0.0, noise=0.0,
                   coulomb=0.05 + 0.45 * dev["coulomb"] / 0.5)
    return dev


def busy_loop() -> subprocess.Popen:
    """A CPU-bound process (one core), stopped by the caller."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def identify_port(dev: dict, seed: int, tmp: str) -> tuple[dict, int, str]:
    """``hapsim identify --port`` against ``hapsim mock --scene``; (JSON, exit, stderr)."""
    path = os.path.join(tmp, f"dev{seed}.yaml")
    with open(path, "w") as fh:
        fh.write("rate_hz: 1000\nmasses:\n  - {name: hand, kind: port}\nlinks: []\n"
                 f"device: {json.dumps(dev)}\n")
    mock = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--scene", path,
                             "--seed", str(seed)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = mock.stdout.readline()
        if not line.startswith("PORT"):
            return {}, -1, "mock did not start: " + line + mock.stderr.read()
        port = line.split()[1]
        r = subprocess.run([sys.executable, "-m", "hapsim", "identify", "--port", port,
                            "--json", "--seed", str(seed)], capture_output=True, text=True,
                           timeout=600)
    finally:
        mock.terminate()
        try:
            mock.wait(10)
        except subprocess.TimeoutExpired:
            mock.kill()
    try:
        out = json.loads(r.stdout)
    except ValueError:
        out = {"stdout_not_json": r.stdout[:400]}
    return out, r.returncode, r.stderr


def identify_inprocess(dev: dict, seed: int) -> tuple[dict, int, str]:
    """The lockstep in-process mock; (the JSON ``hapsim identify`` would print, exit, '')."""
    from hapsim.commands.identify import identify
    from hapsim.errors import HapsimError
    from hapsim.scene import Device
    try:
        fit, rec = identify(device=Device(**dev), transport="inprocess", seed=seed,
                            progress=False,
                            handle_signals=False)
    except HapsimError as exc:
        return {"error": {"type": type(exc).__name__, "message": str(exc)}}, 1, ""
    return ({"device": fit.to_dict(), "loop": rec["loop"]},
            0 if fit.explained and not rec["loop"]["safety_stop"] else 1, "")


def check(dev: dict, out: dict) -> dict:
    """Whether each truth lies in its reported interval (d: exact)."""
    fit = out.get("device")
    if not fit:
        return {q: False for q in QUANTITIES}

    def inside(key, truth):
        e = fit[key]
        lo = -math.inf if e["lo"] is None else e["lo"]
        hi = math.inf if e["hi"] is None else e["hi"]
        return bool(lo <= truth <= hi)
    return {"m": inside("mass", dev["mass"]), "b0": inside("friction", dev["friction"]),
            "fc+": inside("coulomb_pos", dev["coulomb"]),
            "fc-": inside("coulomb_neg", dev["coulomb"]),
            "d": _delay_inside(fit, dev["delay"]) and fit["hold"] == "zoh",
            "q": inside("position_resolution", dev["position_resolution"]),
            "noise": inside("noise", dev["noise"])}


def _delay_inside(fit: dict, truth: float) -> bool:
    """The reported delay interval holds the truth (a real-valued one when reported)."""
    iv = fit.get("delay_estimate")
    if iv:
        return bool(iv["lo"] <= truth <= iv["hi"])
    lo, hi = fit.get("delay_range") or (fit["delay"], fit["delay"])
    return bool(lo <= truth <= hi)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--busy", type=int, default=2,
                    help="CPU-bound processes running beside every identification")
    ap.add_argument("--fractional", action="store_true",
                    help="hidden delays a real number of periods (1-20)")
    ap.add_argument("--noise-free", action="store_true",
                    help="no sensor noise, no quantum, Coulomb friction 0.05-0.5 N")
    ap.add_argument("--mode", choices=("port", "inprocess"), default="port")
    ap.add_argument("--json", metavar="FILE", help="write the results there")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    rows = []
    t0 = time.time()
    n_busy = a.busy if a.mode == "port" else 0
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.n):
            dev = draw(rng, a.mode == "port", a.fractional, a.noise_free)
            busy = [busy_loop() for _ in range(n_busy)]
            t1 = time.time()
            try:
                if a.mode == "port":
                    out, code, err = identify_port(dev, a.seed * 1000 + i, tmp)
                else:
                    out, code, err = identify_inprocess(dev, i)
            finally:
                for b in busy:
                    b.terminate()
                    b.wait()
            ok = check(dev, out)
            fit = out.get("device") or {}
            lp = out.get("loop") or {}
            row = {"i": i, "busy": len(busy), "truth": dev, "exit": code,
                   "identified": bool(out.get("device")),
                   # (a record refused after a safety stop says so in its message)
                   "safety_stop": bool(lp.get("safety_stop")) or "ended on a safety stop"
                   in ((out.get("error") or {}).get("message") or ""),
                   "traceback": "Traceback" in err, "ok": ok, "seconds": time.time() - t1,
                   "error": (out.get("error") or {}).get("message"),
                   "estimate": {k: fit.get(k) for k in ("mass", "friction", "coulomb_pos",
                                                        "coulomb_neg", "delay", "hold",
                                                        "delay_estimate", "delay_range",
                                                        "position_resolution", "noise",
                                                        "explained")},
                   "loop": {k: (out.get("loop") or {}).get(k)
                            for k in ("samples", "late", "stop_reason", "account",
                                      "fitted_rows")}}
            rows.append(row)
            bad = [q for q, v in ok.items() if not v]
            e = row["estimate"]
            est = (f"m^ {e['mass']['value']:.4g} b^ {e['friction']['value']:.3g} "
                   f"fc^ {e['coulomb_pos']['value']:.3g}/{e['coulomb_neg']['value']:.3g} "
                   f"d^ {e['delay']}" if e.get("mass") else f"no fit: {row['error']}")
            late = (row["loop"].get("account") or {}).get("late")
            print(f"{i:3d} busy {row['busy']} m {dev['mass']:.4g} "
                  f"b0 {dev['friction']:.3g} fc {dev['coulomb']:.3g} d {dev['delay']} "
                  f"q {dev['position_resolution'] * 1e6:.3g}um nz {dev['noise'] * 1e6:.3g}um"
                  f" | {est} | exit {code}{' SAFETY' if row['safety_stop'] else ''} late "
                  f"{late} {row['seconds']:.1f}s"
                  f"{' MISS ' + ','.join(bad) if bad else ''}"
                  f"{' TRACEBACK' if row['traceback'] else ''}", flush=True)
    ident = [r for r in rows if r["identified"]]
    cover = {q: sum(r["ok"][q] for r in ident) / max(len(ident), 1) for q in QUANTITIES}
    inside = sum(sum(r["ok"].values()) for r in ident)
    total = sum(len(r["ok"]) for r in ident)
    summary = {"n": len(rows), "busy": n_busy, "mode": a.mode, "seed": a.seed,
               "fractional": a.fractional, "noise_free": a.noise_free,
               "identified": len(ident),
               "safety_stops": sum(r["safety_stop"] for r in rows),
               "coverage_all": inside / max(total, 1), "coverage": cover,
               "load_before": os.getloadavg()[0],
               "exit_codes": {str(c): sum(r["exit"] == c for r in rows)
                              for c in sorted({r["exit"] for r in rows})},
               "tracebacks": sum(r["traceback"] for r in rows),
               "late_ticks": sum(((r["loop"].get("account") or {}).get("late") or 0)
                                 for r in rows),
               "wall_s": time.time() - t0,
               "command": command_line("tools/identify_blind.py", argv)}
    print(f"identified {len(ident)} of {len(rows)}, safety stops {summary['safety_stops']}, "
          f"truths inside their intervals {inside} of {total} "
          f"({100 * summary['coverage_all']:.1f} %)")
    print("coverage: " + ", ".join(f"{q} {v * 100:.0f} %" for q, v in cover.items()))
    print(f"exit codes {summary['exit_codes']}, tracebacks {summary['tracebacks']}, "
          f"late ticks accounted {summary['late_ticks']}, {summary['wall_s']:.0f} s")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"summary": summary, "devices": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

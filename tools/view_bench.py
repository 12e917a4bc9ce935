"""Does the live view disturb the loop? The same ``hapsim run`` with and without ``--view``
(the page open and drawing in headless chromium), side by side, same run length.

Both runs use the Python host loop (``--loop python``: a run with ``--view`` takes live
changes, which keep the Python loop, as ``--osc`` does); the pairs alternate so a change in
the machine's load falls on both. With ``--beside``, a third side: the run without
``--view`` while the same browser draws the live view of another process (a lockstep run
paced by its host, normal scheduling): the browser's drawing without the view in the
loop's process. Printed: per run the turnaround p50 / p99 [us], the late ticks, the
longest silence (the largest step of the device's sample counter between two samples the
host answered, from the run's telemetry) and how the run ended; then the medians of each
side and their ratio (view / without), with the load.

Usage::

    python tools/view_bench.py [--scene configs/wall.yaml] [--duration 5] [--pairs 3] [--beside]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import view_browser as vb  # noqa: E402


def one(scene: str, duration: float, side: str, driver, tmp: str, decoy=None) -> dict:
    """One run (``side``: ``without``, ``--view`` or ``beside``); its turnaround p50 / p99
    [us], late ticks, ticks, longest silence [samples] and stop reason."""
    import numpy as np
    tel = os.path.join(tmp, f"run{time.monotonic_ns()}.npz")
    argv = ["run", scene, "--duration", str(duration), "--loop", "python", "--json",
            "--telemetry", tel]
    frames = None
    if side == "--view":
        r = vb.ViewRun(argv)
        try:
            driver.get(r.url)
            vb.wait_for(driver, "window.hapsimView && window.hapsimView.frames > 0", 120)
            code, out, err = r.finish(duration + 120)
            frames = driver.execute_script("return window.hapsimView.frames")
        finally:
            r.kill()
    else:
        driver.get(decoy.url if side == "beside" else "about:blank")
        if side == "beside":
            vb.wait_for(driver, "window.hapsimView && window.hapsimView.frames > 0", 120)
        p = subprocess.run([sys.executable, "-m", "hapsim", *argv], capture_output=True,
                           text=True, cwd=vb.ROOT, timeout=duration + 300)
        code, out, err = p.returncode, p.stdout, p.stderr
        if side == "beside":
            frames = driver.execute_script("return window.hapsimView.frames")
    if code not in (0, 1) or not out.strip():     # 1: a safety stop, still reported
        raise RuntimeError(f"hapsim run exited {code}: {err[-1500:]}")
    loop = json.loads(out)["loop"]
    ta = loop["turnaround_us"]
    seq = np.load(tel)["seq"]
    silence = int(np.max(np.diff(seq))) if seq.size > 1 else 0
    return {"side": side, "p50_us": ta["p50"], "p99_us": ta["p99"], "late": loop["late"],
            "ticks": loop["ticks"], "silence": silence, "frames_drawn": frames,
            "stop": loop["stop_reason"]}


def main(argv=None) -> int:
    """Run the pairs and print the table (markdown) on stdout."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="configs/wall.yaml")
    p.add_argument("--duration", type=float, default=5.0, help="run length [s]")
    p.add_argument("--pairs", type=int, default=3, help="runs of each side")
    p.add_argument("--beside", action="store_true",
                   help="also the run without --view while the browser draws another "
                        "process's live view")
    a = p.parse_args(argv)
    why = vb.browser_missing()
    if why:
        print(f"view_bench: {why}", file=sys.stderr)
        return 2
    sides = ("without", "--view", "beside") if a.beside else ("without", "--view")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        drv = vb.open_browser(os.path.join(tmp, "profile"))
        decoy = (vb.ViewRun(["run", a.scene, "--duration", "0", "--lockstep", "--host-clocked",
                             "--rt-priority", "0"]) if a.beside else None)
        try:
            for i in range(a.pairs):
                for side in (sides if i % 2 == 0 else sides[::-1]):
                    r = one(a.scene, a.duration, side, drv, tmp, decoy)
                    r["load"] = os.getloadavg()[0]
                    rows.append(r)
                    print(f"view_bench: {r}", file=sys.stderr, flush=True)
        finally:
            if decoy is not None:
                decoy.kill()
            drv.quit()
    print(f"`python tools/view_bench.py --scene {a.scene} --duration {a.duration:g} "
          f"--pairs {a.pairs}{' --beside' if a.beside else ''}` ({time.strftime('%Y-%m-%d')}, "
          f"load average {min(r['load'] for r in rows):.1f} to "
          f"{max(r['load'] for r in rows):.1f} on {os.cpu_count()} cores)\n")
    print("| run | turnaround p50 [us] | p99 [us] | late ticks | ticks | longest silence "
          "[samples] | page frames | stop |")
    print("|---|---|---|---|---|---|---|---|")
    names = {"without": "without", "--view": "--view", "beside": "without, page beside"}
    for r in rows:
        print(f"| {names[r['side']]} | {r['p50_us']:.1f} | {r['p99_us']:.1f} | {r['late']} | "
              f"{r['ticks']} | {r['silence']} | "
              f"{r['frames_drawn'] if r['frames_drawn'] is not None else '-'} | {r['stop']} |")
    med = {}
    for side in sides:
        s = [r for r in rows if r["side"] == side]
        med[side] = {q: statistics.median(r[q] for r in s)
                     for q in ("p50_us", "p99_us", "late", "silence")}
        stops = sum(1 for r in s if r["stop"] != "duration")
        print(f"\nmedians {names[side]}: p50 {med[side]['p50_us']:.1f} us, p99 "
              f"{med[side]['p99_us']:.1f} us, late {med[side]['late']:g}, longest silence "
              f"{med[side]['silence']:g}; {stops} of {len(s)} runs stopped early")
    w, v = med["without"], med["--view"]
    ratio = {q: (v[q] / w[q] if w[q] else float("nan")) for q in v}
    print(f"\nratio view/without: p50 {ratio['p50_us']:.2f}, p99 {ratio['p99_us']:.2f}, "
          f"late {ratio['late']:.2f}, longest silence {ratio['silence']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Does the live view disturb the loop? The same ``hapsim run`` with and without ``--view``
(the page open and drawing in headless chromium), side by side, same run length.

Both runs use the Python host loop (``--loop python``: a run with ``--view`` takes live
changes, which keep the Python loop, as ``--osc`` does); the pairs alternate so a change in
the machine's load falls on both. Printed: per run the turnaround p50 / p99 [us] and the
late ticks; then the medians of each side and their ratio (view / without), with the load.

Usage::

    python tools/view_bench.py [--scene configs/wall.yaml] [--duration 5] [--pairs 3]
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


def one(scene: str, duration: float, view: bool, driver) -> dict:
    """One run; its turnaround p50 / p99 [us], late ticks and ticks."""
    argv = ["run", scene, "--duration", str(duration), "--loop", "python", "--json"]
    if view:
        r = vb.ViewRun(argv)
        try:
            driver.get(r.url)
            vb.wait_for(driver, "window.hapsimView && window.hapsimView.frames > 0", 120)
            code, out, err = r.finish(duration + 120)
            frames = driver.execute_script("return window.hapsimView.frames")
        finally:
            r.kill()
    else:
        p = subprocess.run([sys.executable, "-m", "hapsim", *argv], capture_output=True,
                           text=True, cwd=vb.ROOT, timeout=duration + 300)
        code, out, err, frames = p.returncode, p.stdout, p.stderr, None
    if code not in (0, 1) or not out.strip():     # 1: a safety stop, still reported
        raise RuntimeError(f"hapsim run exited {code}: {err[-1500:]}")
    loop = json.loads(out)["loop"]
    ta = loop["turnaround_us"]
    return {"view": view, "p50_us": ta["p50"], "p99_us": ta["p99"], "late": loop["late"],
            "ticks": loop["ticks"], "frames_drawn": frames, "stop": loop["stop_reason"]}


def main(argv=None) -> int:
    """Run the pairs and print the table (markdown) on stdout."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="configs/wall.yaml")
    p.add_argument("--duration", type=float, default=5.0, help="run length [s]")
    p.add_argument("--pairs", type=int, default=3, help="runs of each side")
    a = p.parse_args(argv)
    why = vb.browser_missing()
    if why:
        print(f"view_bench: {why}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        drv = vb.open_browser(os.path.join(tmp, "profile"))
        try:
            for i in range(a.pairs):
                for view in ((False, True) if i % 2 == 0 else (True, False)):
                    r = one(a.scene, a.duration, view, drv)
                    r["load"] = os.getloadavg()[0]
                    rows.append(r)
                    print(f"view_bench: {r}", file=sys.stderr, flush=True)
        finally:
            drv.quit()
    print(f"`python tools/view_bench.py --scene {a.scene} --duration {a.duration:g} "
          f"--pairs {a.pairs}` ({time.strftime('%Y-%m-%d')}, load average "
          f"{min(r['load'] for r in rows):.1f} to {max(r['load'] for r in rows):.1f} on "
          f"{os.cpu_count()} cores)\n")
    print("| run | turnaround p50 [us] | p99 [us] | late ticks | ticks | page frames | stop |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {'--view' if r['view'] else 'without'} | {r['p50_us']:.1f} | "
              f"{r['p99_us']:.1f} | {r['late']} | {r['ticks']} | "
              f"{r['frames_drawn'] if r['frames_drawn'] is not None else '-'} | "
              f"{r['stop']} |")
    med = {}
    for side in (False, True):
        s = [r for r in rows if r["view"] is side]
        med[side] = {q: statistics.median(r[q] for r in s) for q in ("p50_us", "p99_us", "late")}
    ratio = {q: (med[True][q] / med[False][q] if med[False][q] else float("nan"))
             for q in med[True]}
    print(f"\nmedians without: p50 {med[False]['p50_us']:.1f} us, p99 "
          f"{med[False]['p99_us']:.1f} us, late {med[False]['late']:g}; with --view: p50 "
          f"{med[True]['p50_us']:.1f} us, p99 {med[True]['p99_us']:.1f} us, late "
          f"{med[True]['late']:g}; ratio view/without p50 {ratio['p50_us']:.2f}, p99 "
          f"{ratio['p99_us']:.2f}, late {ratio['late']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

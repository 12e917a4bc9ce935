#!/usr/bin/env python3
"""Benchmark of ``hapsim run``'s start-up to its first sample, warm and cold (a program,
not a test).

Runs ``python -m hapsim run configs/wall.yaml --duration 0.2 --json`` as a new process, R
times, cold (numba's cache in a new empty directory: everything compiles) and warm (the
same cache again), and reads the moment the device was armed (the report's
``loop.armed_monotonic_s``, CONFIG sent; the first STATE follows within a period) against
the moment the process was started here. With ``--baseline REV`` the same is measured, in
the same run and interleaved with it, on the tree of a git revision (``git archive``), and
the ratios printed. The machine's load is printed with the figures: on a shared machine
say "loaded machine" beside them.

:func:`startup_seconds` is what ``tools/bench_loop.py`` can call for its start-up line.

Usage::

    PYTHONPATH=$PWD python tools/bench_startup.py [--repeats 5] [--baseline main]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def startup_seconds(repo: Path, cache: Path, cold: bool) -> dict:
    """One ``hapsim run configs/wall.yaml`` of the tree ``repo`` with numba's cache in
    ``cache`` (emptied first when ``cold``).

    Returns
    -------
    dict
        ``armed_s``: seconds from starting the process to CONFIG sent (the first
        sample); ``first_sample_s``: the report's own figure (first STATE after the
        process started; None on trees without it); ``wall_s``: the whole run.
    """
    if cold:
        shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(repo), NUMBA_CACHE_DIR=str(cache))
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "hapsim", "run", "configs/wall.yaml",
                        "--duration", "0.2", "--json"], env=env, capture_output=True,
                       text=True, cwd=str(repo))
    wall = time.monotonic() - t0
    if p.returncode != 0:
        raise SystemExit(f"hapsim run failed in {repo}: {p.stderr[-800:]}")
    loop = json.loads(p.stdout)["loop"]
    return {"armed_s": loop["armed_monotonic_s"] - t0,
            "first_sample_s": loop.get("first_sample_s"), "wall_s": wall}


def _tree(rev: str, tmp: Path) -> Path:
    """The files of git revision ``rev`` of this repository, in ``tmp/rev``."""
    out = tmp / rev.replace("/", "_")
    out.mkdir(parents=True)
    arc = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True,
                         capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(out)], input=arc, check=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per case (default 5)")
    ap.add_argument("--baseline", metavar="REV", help="also measure this git revision")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench_startup_"))
    trees = {"this": REPO}
    if args.baseline:
        trees[args.baseline] = _tree(args.baseline, tmp)
    print("command: " + " ".join([sys.executable, *sys.argv]))
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    res = {name: {"cold": [], "warm": []} for name in trees}
    for i in range(args.repeats):
        for name, repo in trees.items():        # interleaved: the same load for both
            cache = tmp / f"cache_{name.replace('/', '_')}"
            res[name]["cold"].append(startup_seconds(repo, cache, True))
            startup_seconds(repo, cache, False)           # the cache complete
            res[name]["warm"].append(startup_seconds(repo, cache, False))
        print(f"  round {i + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    print(f"\nstart-up of 'hapsim run configs/wall.yaml' to its first sample (CONFIG sent) "
          f"[s], min / median of {args.repeats}")
    med = {}
    for name in trees:
        for kind in ("warm", "cold"):
            a = [r["armed_s"] for r in res[name][kind]]
            med[name, kind] = statistics.median(a)
            own = [r["first_sample_s"] for r in res[name][kind] if r["first_sample_s"]]
            extra = (f"   (report: first sample {statistics.median(own):.2f} s)" if own
                     else "")
            print(f"  {name:>12} {kind}: {min(a):5.2f} / {med[name, kind]:5.2f}{extra}")
    if args.baseline:
        for kind in ("warm", "cold"):
            print(f"  {kind}: this / {args.baseline} = "
                  f"{med['this', kind] / med[args.baseline, kind]:.2f} (medians)")
    print(f"load average now {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

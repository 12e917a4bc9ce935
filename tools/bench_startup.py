#!/usr/bin/env python3
"""Benchmark of ``hapsim run``'s start-up: its first line and its first sample, cold and
warm (a program, not a test).

Runs ``python -m hapsim run configs/wall.yaml --duration 0.2 --json`` as a new process, R
times, cold (numba's cache in a new empty directory: everything compiles) and warm (the
same cache again), and records, against the moment the process was started here:

- **first line**: the first line the run writes on stderr (cold: what it compiles, said
  before it compiles; warm: the loop starting);
- **first sample**: the report's own figure (``loop.first_sample_s``: the first STATE
  answered, from the process's start) and the moment the device was armed
  (``loop.armed_monotonic_s``, CONFIG sent).

With ``--baseline REV`` the same is measured, in the same run and interleaved with it, on
the tree of a git revision (``git archive``), and the ratios printed. The machine's load is
printed and stored with the figures: on a shared machine say "loaded machine" beside them.
``--json FILE`` writes them (``docs/bench_startup.json`` is what ``docs/startup.md`` shows).

:func:`startup_seconds` is what ``tools/bench_loop.py`` can call for its start-up line.

Usage::

    PYTHONPATH=$PWD python tools/bench_startup.py [--repeats 5] [--baseline main] \\
        [--json docs/bench_startup.json]
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

from provenance import command_line, scrub  # tools/, beside this file

REPO = Path(__file__).resolve().parents[1]


def startup_seconds(repo: Path, cache: Path, cold: bool) -> dict:
    """One ``hapsim run configs/wall.yaml`` of the tree ``repo`` with numba's cache in
    ``cache`` (emptied first when ``cold``).

    Returns
    -------
    dict
        ``first_line_s``: seconds from starting the process to its first stderr line
        (None when it wrote none), ``first_line``: that line; ``armed_s``: to CONFIG sent;
        ``first_sample_s``: the report's own figure (first STATE after the process
        started; None on trees without it); ``wall_s``: the whole run.
    """
    import threading
    if cold:
        shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(repo), NUMBA_CACHE_DIR=str(cache))
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "hapsim", "run", "configs/wall.yaml",
                          "--duration", "0.2", "--json"], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=str(repo))
    lines: list = []

    def read_err() -> None:
        for ln in p.stderr:
            lines.append((time.monotonic() - t0, ln.rstrip("\n")))
    reader = threading.Thread(target=read_err, daemon=True)
    reader.start()
    out = p.stdout.read()
    p.wait()
    reader.join()
    wall = time.monotonic() - t0
    try:    # exit 1 (a negative verdict, e.g. a safety stop under load) still has a report
        loop = json.loads(out)["loop"]
    except (ValueError, KeyError):
        raise SystemExit(f"hapsim run failed in {repo} (exit {p.returncode}): "
                         f"{chr(10).join(ln for _, ln in lines)[-800:]}") from None
    return {"exit": p.returncode, "stop": loop.get("stop_reason"),
            "first_line_s": lines[0][0] if lines else None,
            # the cache directory is this run's temporary one: named, not written out
            "first_line": scrub(lines[0][1], {str(cache): "$NUMBA_CACHE_DIR"}) if lines else None,
            "armed_s": loop["armed_monotonic_s"] - t0,
            "first_sample_s": loop.get("first_sample_s"), "wall_s": wall}


def _stats(runs: list, key: str) -> dict | None:
    vals = [r[key] for r in runs if r.get(key) is not None]
    if not vals:
        return None
    return {"min": min(vals), "median": statistics.median(vals), "max": max(vals)}


def _tree(rev: str, tmp: Path) -> Path:
    """The files of git revision ``rev`` of this repository, in ``tmp/rev``."""
    out = tmp / rev.replace("/", "_")
    out.mkdir(parents=True)
    arc = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True,
                         capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(out)], input=arc, check=True)
    return out


#: The targets (issue 21), on a quiet 2-core machine: first sample cold and warm [s].
TARGETS = {"cold": 5.0, "warm": 0.7}


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
    command = command_line("tools/bench_startup.py", argv)
    load_before = list(os.getloadavg())
    print("command: " + command)
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.2f}' for x in load_before)}")
    res = {name: {"cold": [], "warm": []} for name in trees}
    for i in range(args.repeats):
        for name, repo in trees.items():        # interleaved: the same load for both
            cache = tmp / f"cache_{name.replace('/', '_')}"
            res[name]["cold"].append(startup_seconds(repo, cache, True))
            startup_seconds(repo, cache, False)           # the cache complete
            res[name]["warm"].append(startup_seconds(repo, cache, False))
        print(f"  round {i + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    print(f"\nstart-up of 'hapsim run configs/wall.yaml' [s], min / median / max of "
          f"{args.repeats}")
    summary = {}
    for name in trees:
        summary[name] = {}
        for kind in ("warm", "cold"):
            runs = res[name][kind]
            st = {key: _stats(runs, key)
                  for key in ("first_line_s", "first_sample_s", "armed_s", "wall_s")}
            st["first_line"] = runs[-1]["first_line"]
            st["runs"] = runs
            summary[name][kind] = st
            for key, what in (("first_line_s", "first line"),
                              ("first_sample_s", "first sample (report)"),
                              ("armed_s", "armed (CONFIG sent)")):
                if st[key]:
                    print(f"  {name:>12} {kind} {what:>22}: {st[key]['min']:6.2f} / "
                          f"{st[key]['median']:6.2f} / {st[key]['max']:6.2f}")
            print(f"  {name:>12} {kind} first line: {st['first_line']!r}")
    this = summary["this"]
    for kind, target in TARGETS.items():
        fs = this[kind]["first_sample_s"] or this[kind]["armed_s"]
        print(f"  target: first sample {kind} <= {target} s on a quiet 2-core machine: "
              f"median {fs['median']:.2f} s here "
              f"({'met' if fs['median'] <= target else 'NOT MET'} at this load)")
    if args.baseline:
        for kind in ("warm", "cold"):
            a, b = summary["this"][kind]["armed_s"], summary[args.baseline][kind]["armed_s"]
            print(f"  {kind}: this / {args.baseline} = {a['median'] / b['median']:.2f} "
                  f"(medians, armed)")
    load_after = list(os.getloadavg())
    print(f"load average now {' '.join(f'{x:.2f}' for x in load_after)}")
    if args.json:
        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "-C", str(REPO), "status", "--porcelain",
                                     "--", "hapsim"], capture_output=True,
                                    text=True).stdout.strip())
        doc = {"command": command, "git_commit": commit, "git_dirty": dirty,
               "python": sys.version.split()[0], "cpus": os.cpu_count(),
               "load_before": load_before, "load_after": load_after,
               "repeats": args.repeats, "scene": "configs/wall.yaml", "targets_s": TARGETS,
               **summary}
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

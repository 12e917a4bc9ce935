"""The suite's time beside CPU-bound processes, and where it goes (issue 31 item 2).

Usage::

    python tools/suite_time.py [--busy 1] [--top 20] [--json docs/suite_time.json]
                               [-- extra pytest arguments]

Starts ``--busy`` CPU-bound processes (``python -c 'while 1: pass'``, stopped at the end),
runs the README's test command (``python -m pytest -q``, its pytest-xdist workers) with the
suite's ``--cpu-time`` option (tests/conftest.py: CPU seconds of the worker and of the
children it waited for, per test), and prints the wall seconds against the 6-minute budget
(the ratio), the load before and after, the CPU seconds in total, and the heaviest tests
and modules by CPU seconds. Writes the same as JSON with ``--json``. A measurement program,
not a test: the wall figure is only the budget's when the machine has nothing else
running than the ``--busy`` processes (the load is written beside it). Exit status:
pytest's.

Where the wall clock goes, from the tests' start and end times: the session's start-up
(starting the workers and collecting, up to the first test), each worker's time in tests
and its idle end (from its last test to the last test of the run), and each
``xdist_group``'s chain (its tests run in turn on one worker). ``--from CPU_JSON`` reads a
run's ``--cpu-time-json`` file instead of running the suite.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import subprocess
import sys
import tempfile
import time

from provenance import REPO, command_line  # tools/, beside this file

#: The project's budget for the README's test command, seconds (2 cores, one busy process).
BUDGET_S = 360.0


def _default_sigint() -> None:
    """In the pytest child, before it starts: SIGINT's default action."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def main(argv=None) -> int:
    """Run the suite as described in the module docstring.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        pytest's exit status.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--busy", type=int, default=1,
                    help="CPU-bound processes beside the suite (default 1, the budget's)")
    ap.add_argument("--top", type=int, default=20, help="heaviest tests and modules shown")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--from", dest="source", metavar="CPU_JSON",
                    help="read a run's --cpu-time-json file instead of running the suite")
    ap.add_argument("pytest_args", nargs="*", help="after --: more pytest arguments")
    a = ap.parse_args(argv)
    if a.source:
        with open(a.source) as f:
            run = json.load(f)
        res = {"command": command_line("tools/suite_time.py", argv), "source": a.source,
               "tests": len(run["tests"]), "session_wall_s": round(run["session_wall"], 1),
               "load_after": [round(x, 2) for x in run["load"]],
               "cpu_own_s": round(sum(r["cpu"] for r in run["tests"].values()), 1),
               "cpu_children_s": round(sum(r["children"] for r in run["tests"].values()), 1),
               "timeline": timeline(run)}
        _print_timeline(res)
        _write(a, res, run["tests"])
        return 0
    busy = [subprocess.Popen([sys.executable, "-c", "while 1: pass"])
            for _ in range(a.busy)]
    tmp = tempfile.mkdtemp(prefix="suite_time_")
    out = _asked_json(a.pytest_args)
    own = out is None                   # the figures in our temporary folder, else theirs
    if own:
        out = os.path.join(tmp, "cpu.json")
    run = {}
    try:
        time.sleep(2.0)                          # the busy processes are running
        load0 = os.getloadavg()[0]
        cmd = [sys.executable, "-m", "pytest", "-q", "--cpu-time=0",
               *([f"--cpu-time-json={out}"] if own else []), *a.pytest_args]
        print(f"suite_time: {' '.join(cmd[1:])} beside {a.busy} busy process(es), "
              f"load {load0:.2f}", file=sys.stderr)
        t0 = time.perf_counter()
        # progress on stderr; SIGINT as a shell's foreground command has it: started in
        # the background of a non-interactive shell (``cmd &``) this process inherits it
        # ignored, and the suite's Ctrl-C tests then fail (their SIGINT never arrives)
        rc = subprocess.call(cmd, cwd=str(REPO), stdout=sys.stderr,
                             preexec_fn=_default_sigint)
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()[0]
    finally:
        for p in busy:
            p.kill()
            p.wait()
    try:
        with open(out) as f:
            run = json.load(f)
        tests = run["tests"]
    except (OSError, ValueError, KeyError):
        tests = {}
    finally:
        for name in os.listdir(tmp):
            os.unlink(os.path.join(tmp, name))
        os.rmdir(tmp)
    cpu = lambda r: r["cpu"] + r["children"]                            # noqa: E731
    heavy = sorted(tests.items(), key=lambda kv: -cpu(kv[1]))[:a.top]
    mods = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for node, r in tests.items():
        m = mods[node.split("::")[0]]
        m[0] += cpu(r)
        m[1] += r["wall"]
        m[2] += 1
    res = {"command": command_line("tools/suite_time.py", argv),
           "pytest": "python -m pytest -q " + " ".join(a.pytest_args),
           "busy": a.busy, "cores": os.cpu_count(), "load_before": round(load0, 2),
           "load_after": round(load1, 2), "exit": rc, "tests": len(tests),
           "wall_s": round(wall, 1), "budget_s": BUDGET_S,
           "wall_over_budget": round(wall / BUDGET_S, 3),
           "cpu_own_s": round(sum(r["cpu"] for r in tests.values()), 1),
           "cpu_children_s": round(sum(r["children"] for r in tests.values()), 1),
           # Python's bytecode cache off: every pytest worker compiles and rewrites the
           # whole suite again (17.6 CPU-s to collect it, 6.3 with the cache) and every
           # hapsim child its modules (~0.3 s): a measurement with it set is not a
           # newcomer's (docs/testing.md, 'The time budget')
           "bytecode_cache": not os.environ.get("PYTHONDONTWRITEBYTECODE"),
           "heaviest_tests": [{"test": n, "cpu_s": round(cpu(r), 2),
                               "children_s": round(r["children"], 2),
                               "wall_s": round(r["wall"], 2)} for n, r in heavy],
           "heaviest_modules": [{"module": n, "cpu_s": round(v[0], 1), "wall_s": round(v[1], 1),
                                 "tests": v[2]}
                                for n, v in sorted(mods.items(), key=lambda kv: -kv[1][0])
                                [:a.top]],
           "timeline": timeline(run) if tests else None}
    print(f"suite: {res['wall_s']} s wall = {res['wall_over_budget']:.2f} x the "
          f"{BUDGET_S:.0f} s budget, beside {a.busy} busy process(es) on {res['cores']} "
          f"cores, load {res['load_before']} -> {res['load_after']}; CPU {res['cpu_own_s']} s "
          f"in the workers + {res['cpu_children_s']} s in their children; exit {rc}")
    if not res["bytecode_cache"]:
        print("suite: PYTHONDONTWRITEBYTECODE is set: no .pyc is written, every process "
              "compiles its modules from source (a fresh clone's first run at every run)")
    for t in res["heaviest_tests"]:
        print(f"  {t['cpu_s']:7.2f} s CPU ({t['children_s']:6.2f} children) "
              f"{t['wall_s']:7.2f} s wall  {t['test']}")
    _print_timeline(res)
    _write(a, res, tests)
    return rc


def _asked_json(pytest_args: list) -> str | None:
    """The ``--cpu-time-json`` path among the pytest arguments (the last one, as pytest
    takes it; relative to the repository, where pytest runs), None when none is given:
    the figures are then read from there (a second option of ours before it left the
    summary with no tests)."""
    path = None
    for i, arg in enumerate(pytest_args):
        if arg.startswith("--cpu-time-json="):
            path = arg.split("=", 1)[1]
        elif arg == "--cpu-time-json" and i + 1 < len(pytest_args):
            path = pytest_args[i + 1]
    return path and os.path.join(str(REPO), path)      # pytest runs in the repository


def _write(a, res: dict, tests: dict) -> None:
    """Write ``--json`` as asked."""
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
            f.write("\n")


def timeline(run: dict) -> dict | None:
    """Where a run's wall clock went, from its tests' end times and wall seconds.

    Parameters
    ----------
    run : dict
        A ``--cpu-time-json`` file's content (``tests``; ``session_start`` and
        ``session_end`` when the suite wrote them).

    Returns
    -------
    dict or None
        ``start_up_s`` (session start to the first test's start), ``tests_s`` (first
        test's start to the last one's end), ``after_s`` (last test's end to the
        session's end); per worker ``tests``, ``busy_s`` (sum of its tests' wall
        seconds), ``first_start_s`` and ``last_end_s`` (from the session's start) and
        ``idle_end_s`` (its last test's end to the run's last); per ``xdist_group`` its
        ``worker``, ``tests``, ``wall_s`` and ``start_s``/``end_s``. None when the tests
        carry no end time (a run before they did).
    """
    rows = run.get("tests", {})
    if not rows or any("end" not in r for r in rows.values()):
        return None
    t0 = run.get("session_start") or min(r["end"] - r["wall"] for r in rows.values())
    first = min(r["end"] - r["wall"] for r in rows.values())
    last = max(r["end"] for r in rows.values())
    workers: dict[str, dict] = {}
    groups: dict[str, dict] = {}
    for nodeid, r in rows.items():
        w = workers.setdefault(r["worker"], {"tests": 0, "busy_s": 0.0,
                                             "first_start_s": math.inf, "last_end_s": 0.0})
        w["tests"] += 1
        w["busy_s"] += r["wall"]
        w["first_start_s"] = min(w["first_start_s"], r["end"] - r["wall"] - t0)
        w["last_end_s"] = max(w["last_end_s"], r["end"] - t0)
        at = nodeid.rfind("@")
        if at > nodeid.rfind("]"):
            g = groups.setdefault(nodeid[at + 1:], {"worker": set(), "tests": 0,
                                                    "wall_s": 0.0, "start_s": math.inf,
                                                    "end_s": 0.0})
            g["worker"].add(r["worker"])
            g["tests"] += 1
            g["wall_s"] += r["wall"]
            g["start_s"] = min(g["start_s"], r["end"] - r["wall"] - t0)
            g["end_s"] = max(g["end_s"], r["end"] - t0)
    for w in workers.values():
        w["idle_end_s"] = last - t0 - w["last_end_s"]
        for k in w:
            w[k] = round(w[k], 1)
    for g in groups.values():
        g["worker"] = ",".join(sorted(g["worker"]))
        for k in ("wall_s", "start_s", "end_s"):
            g[k] = round(g[k], 1)
    return {"start_up_s": round(first - t0, 1), "tests_s": round(last - first, 1),
            "after_s": (round(run["session_end"] - last, 1) if "session_end" in run
                        else None),
            "workers": dict(sorted(workers.items())),
            "groups": dict(sorted(groups.items(), key=lambda kv: -kv[1]["wall_s"]))}


def _print_timeline(res: dict) -> None:
    """Print :func:`timeline`'s figures."""
    tl = res.get("timeline")
    if not tl:
        return
    print(f"timeline: start-up (workers, collection) {tl['start_up_s']} s, tests "
          f"{tl['tests_s']} s, after the last test {tl['after_s']} s")
    for name, w in tl["workers"].items():
        print(f"  {name}: {w['tests']} tests, {w['busy_s']} s in tests, from "
              f"{w['first_start_s']} to {w['last_end_s']} s, idle at the end "
              f"{w['idle_end_s']} s")
    for name, g in list(tl["groups"].items())[:8]:
        print(f"  group {name} on {g['worker']}: {g['tests']} tests, {g['wall_s']} s, "
              f"from {g['start_s']} to {g['end_s']} s")


if __name__ == "__main__":
    sys.exit(main())

"""What numba compiles during a command, in every Python process it starts (issue 31 item 2).

Usage::

    python tools/numba_compiles.py [--empty-cache] [--top 25] [--json FILE]
                                   [-- command ...]

Runs the command (default: the README's test command, ``python -m pytest -q``) with a
listener on numba's ``numba:compile`` event (``numba.core.event``, numba's own event API)
installed in every Python process it starts: the pytest workers and every ``python -m
hapsim`` child the tests start. The listener is a ``sitecustomize`` module in a temporary
folder put first on ``PYTHONPATH``; it installs itself once numba is imported and writes
one JSON line per top-level compilation (the kernel, its signature, the process's CPU and
wall seconds it took, the test running then). A compilation is what numba does on a miss
of its disk cache: a kernel loaded from the cache is not counted.

``--empty-cache`` points ``NUMBA_CACHE_DIR`` at an empty temporary folder, so that every
kernel the command needs is compiled, as on a fresh clone (numba's cache otherwise lives
in the ``__pycache__`` folders beside the sources); the folder is removed at the end.
Without it, only what the cache lacks is compiled.

Prints the compilations' CPU seconds in total, per kernel and signature (heaviest first),
and the kernels compiled more than once (in several processes: the same work twice).
A measurement program, not a test. Exit status: the command's.

Limits: a process that already has a ``sitecustomize`` of its own on its path loses it
while this runs (this project's environments have none); a process killed before it
flushes loses its last line.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile

from provenance import REPO, command_line  # tools/, beside this file

#: The listener each Python process of the command loads (as its ``sitecustomize``).
_SITECUSTOMIZE = r'''
import os as _os
if _os.environ.get("HAPSIM_COMPILE_LOG"):
    import builtins as _b, json as _json, sys as _sys, time as _time
    _orig, _depth, _done = _b.__import__, [0], [False]

    def _install():
        from numba.core import event
        out = open(_os.path.join(_os.environ["HAPSIM_COMPILE_LOG"],
                                 f"{_os.getpid()}.jsonl"), "a")
        argv = " ".join(_sys.argv)[:200]

        class _Listener(event.Listener):
            def __init__(self):
                self.stack = []

            def on_start(self, ev):
                self.stack.append((_time.process_time(), _time.perf_counter()))

            def on_end(self, ev):
                c0, w0 = self.stack.pop()
                if self.stack:           # nested: counted in the outermost compilation
                    return
                f = getattr(ev.data.get("dispatcher"), "py_func", None)
                name = f"{getattr(f, '__module__', '?')}.{getattr(f, '__qualname__', '?')}"
                out.write(_json.dumps({
                    "kernel": name, "signature": str(ev.data.get("args"))[:300],
                    "cpu_s": _time.process_time() - c0, "wall_s": _time.perf_counter() - w0,
                    "pid": _os.getpid(), "argv": argv,
                    "test": _os.environ.get("PYTEST_CURRENT_TEST")}) + "\n")
                out.flush()

        event.register("numba:compile", _Listener())

    def _import(name, *args, **kwargs):
        _depth[0] += 1
        try:
            module = _orig(name, *args, **kwargs)
        finally:
            _depth[0] -= 1
        # once numba's event module is whole (the outermost import has returned)
        if _depth[0] == 0 and not _done[0] and "numba.core.event" in _sys.modules:
            _done[0] = True
            _b.__import__ = _orig
            _install()
        return module

    _b.__import__ = _import
'''


def summarise(rows: list[dict], top: int) -> dict:
    """The compilations' totals, per kernel and signature, and those done more than once.

    Parameters
    ----------
    rows : list of dict
        One per compilation (keys ``kernel``, ``signature``, ``cpu_s``, ``pid``).
    top : int
        Kernels listed.

    Returns
    -------
    dict
        ``compilations``, ``cpu_s`` (total), ``processes``, ``kernels`` (the ``top``
        heaviest: kernel, signature, count, cpu_s), ``repeated`` (compiled in more than one
        process: kernel, signature, count, cpu_s beyond the first).
    """
    by = collections.defaultdict(list)
    for r in rows:
        by[(r["kernel"], r["signature"])].append(r)
    kernels = sorted(({"kernel": k, "signature": s, "count": len(v),
                       "cpu_s": round(sum(r["cpu_s"] for r in v), 2)}
                      for (k, s), v in by.items()), key=lambda e: -e["cpu_s"])
    repeated = [{"kernel": k, "signature": s, "count": len(v),
                 "cpu_s": round(sum(sorted(r["cpu_s"] for r in v)[:-1]), 2)}
                for (k, s), v in by.items() if len({r["pid"] for r in v}) > 1]
    return {"compilations": len(rows), "cpu_s": round(sum(r["cpu_s"] for r in rows), 2),
            "processes": len({r["pid"] for r in rows}), "kernels": kernels[:top],
            "repeated": repeated}


def main(argv=None) -> int:
    """Run the command as described in the module docstring.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        The command's exit status.
    """
    ap = argparse.ArgumentParser(prog="numba_compiles", description=__doc__.split("\n")[0])
    ap.add_argument("--empty-cache", action="store_true",
                    help="compile every kernel, as on a fresh clone (an empty NUMBA_CACHE_DIR)")
    ap.add_argument("--top", type=int, default=25, help="kernels listed (25)")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("command", nargs="*", help="after --: the command (default: the "
                    "README's test command, python -m pytest -q)")
    a = ap.parse_args(argv)
    cmd = a.command or [sys.executable, "-m", "pytest", "-q"]
    tmp = tempfile.mkdtemp(prefix="hapsim-compiles-")
    try:
        site, log = os.path.join(tmp, "site"), os.path.join(tmp, "log")
        os.makedirs(site)
        os.makedirs(log)
        with open(os.path.join(site, "sitecustomize.py"), "w") as f:
            f.write(_SITECUSTOMIZE)
        env = dict(os.environ, HAPSIM_COMPILE_LOG=log,
                   PYTHONPATH=os.pathsep.join(p for p in (site, os.environ.get("PYTHONPATH"))
                                              if p))
        if a.empty_cache:
            env["NUMBA_CACHE_DIR"] = os.path.join(tmp, "numba-cache")
        code = subprocess.call(cmd, cwd=REPO, env=env)
        rows = []
        for path in glob.glob(os.path.join(log, "*.jsonl")):
            with open(path) as f:
                rows += [json.loads(line) for line in f if line.strip()]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s = summarise(rows, a.top)
    print(f"numba compiled {s['compilations']} kernel signatures in {s['processes']} "
          f"processes: {s['cpu_s']:.1f} CPU-s")
    for e in s["kernels"]:
        print(f"{e['cpu_s']:7.2f} CPU-s  x{e['count']}  {e['kernel']}  {e['signature'][:70]}")
    extra = sum(e["cpu_s"] for e in s["repeated"])
    print(f"compiled in more than one process: {len(s['repeated'])} ({extra:.1f} CPU-s "
          "beyond the first of each)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(dict(s, command=command_line("tools/numba_compiles.py", argv), run=cmd,
                           empty_cache=a.empty_cache, exit=code), f, indent=1)
    return code


if __name__ == "__main__":
    sys.exit(main())

"""Thread pools that do not fight: ``hapsim check`` on a string of beads, alone and N at once.

numpy's OpenBLAS pool spins while it waits for work: two analyses at once on a 2-core
machine, each with a pool as large as the machine, take turns spinning on each other's
cores (issue 19: 44 s each against 1.4 s alone). This program runs the same command alone,
then ``--together`` copies at once, and prints each copy's wall time against the alone time
(target: within 1.5x), with the BLAS pools the command sized itself (the default) and,
for comparison, with ``OPENBLAS_NUM_THREADS`` forced (``--threads``), which the command
keeps when the user sets it. The load average and the cores are printed first: the
ratio is a statement about this machine at this time.

    python tools/bench_pools.py [--beads 500] [--together 2] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))


def _one(scene: str, env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "hapsim", "check", scene, "--json"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)


def _wait(procs: list, t0: float) -> list:
    out = []
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"hapsim check failed (exit {p.returncode}): {err.decode()[-500:]}")
        out.append(time.perf_counter() - t0)
    return out


def measure(scene: str, together: int, env: dict) -> tuple[float, list]:
    """Wall time [s] of one command alone, then of each of ``together`` started at once.

    Parameters
    ----------
    scene : str
        Scene file.
    together : int
        Copies run at once (>= 2).
    env : dict
        Environment of the commands.

    Returns
    -------
    tuple
        ``(alone [s], [each copy [s]])``; each copy's time runs from the common start to
        its own exit.
    """
    t0 = time.perf_counter()
    alone = _wait([_one(scene, env)], t0)[0]
    t0 = time.perf_counter()
    return alone, _wait([_one(scene, env) for _ in range(together)], t0)


def main(argv=None) -> int:
    """Print the alone and together times and their ratios; 0 when every ratio <= 1.5."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--beads", type=int, default=500, help="beads in the string (500)")
    ap.add_argument("--together", type=int, default=2, help="copies at once (2)")
    ap.add_argument("--threads", type=int, default=0,
                    help="also run with OPENBLAS_NUM_THREADS=N forced (0: not)")
    args = ap.parse_args(argv)
    from bench_scene_load import string_scene
    load = os.getloadavg()
    print(f"cores {os.cpu_count()}, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; "
          f"'hapsim check' on a {args.beads}-bead string, alone then {args.together} at once")
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
        fh.write(string_scene(args.beads))
    worst = 0.0
    try:
        base = {k: v for k, v in os.environ.items()
                if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
        runs = [("pools sized by hapsim", base)]
        if args.threads:
            runs.append((f"OPENBLAS_NUM_THREADS={args.threads} (forced)",
                         {**base, "OPENBLAS_NUM_THREADS": str(args.threads)}))
        for name, env in runs:
            alone, each = measure(fh.name, args.together, env)
            ratios = [t / alone for t in each]
            print(f"  {name:38s} alone {alone:6.2f} s; together "
                  + ", ".join(f"{t:6.2f} s ({r:.2f}x)" for t, r in zip(each, ratios)))
            if name.startswith("pools sized"):
                worst = max(ratios)
    finally:
        os.unlink(fh.name)
    print(f"worst ratio with hapsim's pools: {worst:.2f}x (target <= 1.5x)")
    return 0 if worst <= 1.5 else 1


if __name__ == "__main__":
    sys.exit(main())

"""Whole delays give the numbers of an earlier commit bit for bit (issue 29 item 3).

Usage::

    python tools/integer_delay_identity.py --base COMMIT [--loops 300] [--seed 2026]

Exports ``COMMIT`` with ``git archive`` into a temporary folder, then runs the same two
measurements under that tree and under this one, each in its own ``python`` process:

- seeded random loops (m 0.02-2 kg, b0 0-5 N s/m, 250 Hz-10 kHz, d 0-7; ideal hold one
  in five, a prediction correction or a hand behind a grip in some): ``stability_limit``,
  ``render``'s (k, b, spectral radius), every closed-loop pole and ``calibrate``'s (K, B),
  printed as ``float.hex``;
- ``hapsim check --json`` of every ``configs/*.yaml`` whose text is the same in both
  trees: every number both outputs hold (keys that only one holds, from another change
  of the output's schema, are not compared).

Prints how many lines differ (0: bit for bit) and the first differences. A measurement
program, not a test; progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

LOOPS = r'''
import math, sys
import numpy as np
from hapsim.analysis import LoopModel, calibrate, closed_loop_poles, render, stability_limit
from hapsim.analysis.corrections import Correction
rng = np.random.default_rng(int(sys.argv[2]))
for i in range(int(sys.argv[1])):
    m = float(10 ** rng.uniform(-1.7, 0.3)); b0 = float(rng.uniform(0, 5))
    rate = float(10 ** rng.uniform(2.4, 4)); d = int(rng.integers(0, 8))
    hold = "ideal" if i % 5 == 0 else "zoh"
    kw = {}
    if i % 7 == 3 and hold == "zoh":
        kw["correction"] = Correction.from_dict({"kind": "prediction"})
    if i % 7 == 5 and hold == "zoh":
        kw.update(hand_mass=0.3 * m, hand_damping=0.0, grip_stiffness=3000.0,
                  grip_damping=2.0)
    try:
        lp = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d, hold=hold, **kw)
        B = float(rng.uniform(0, 0.2)) * m * rate / (1 + d)
        km = stability_limit(lp, B)
        K = 0.5 * (km if math.isfinite(km) and km > 0 else m * rate * rate)
        r = render(lp, K, B)
        z = closed_loop_poles(lp, K, B)
        vals = [km, r.k, r.b, r.spectral_radius] + [v for q in z for v in (q.real, q.imag)]
        if math.isfinite(r.k):
            c = calibrate(lp, r.k, r.b)
            vals += [c.K, c.B]
        print(" ".join(float(v).hex() for v in vals))
    except Exception as e:
        print(f"error {type(e).__name__}: {e}")
'''


def _run(tree: str, args: list[str]) -> str:
    env = dict(os.environ, PYTHONPATH=tree)
    return subprocess.run([sys.executable, *args], env=env, cwd=tempfile.gettempdir(),
                          capture_output=True, text=True, check=False).stdout


def _numbers(text: str) -> dict:
    """Every number of a JSON document by its path (keys another change added are left
    out of the comparison by the caller: only the paths both outputs hold count)."""
    out = {}

    def walk(o, path):
        if isinstance(o, dict):
            for k, v in o.items():
                walk(v, f"{path}.{k}")
        elif isinstance(o, list):
            for i, v in enumerate(o):
                walk(v, f"{path}[{i}]")
        elif isinstance(o, (int, float)) and not isinstance(o, bool):
            out[path] = float(o).hex()
    try:
        walk(json.loads(text), "")
    except ValueError:
        pass
    return out


def main(argv=None) -> int:
    """Compare (module docstring).

    Parameters
    ----------
    argv : list of str, optional

    Returns
    -------
    int
        0 when every line is identical, 1 otherwise.
    """
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", required=True, help="the earlier commit")
    p.add_argument("--loops", type=int, default=300)
    p.add_argument("--seed", type=int, default=2026)
    a = p.parse_args(argv)
    diffs, total = [], 0
    with tempfile.TemporaryDirectory() as base:
        arc = subprocess.run(["git", "-C", ROOT, "archive", a.base], capture_output=True,
                             check=True).stdout
        subprocess.run(["tar", "-x", "-C", base], input=arc, check=True)
        print(f"integer_delay_identity: {a.loops} random loops ...", file=sys.stderr)
        old = _run(base, ["-c", LOOPS, str(a.loops), str(a.seed)]).splitlines()
        new = _run(ROOT, ["-c", LOOPS, str(a.loops), str(a.seed)]).splitlines()
        total += len(new)
        diffs += [f"loop {i}" for i, (x, y) in enumerate(zip(old, new)) if x != y]
        if len(old) != len(new):
            diffs.append(f"loops: {len(old)} lines against {len(new)}")
        configs = sorted(f for f in os.listdir(os.path.join(ROOT, "configs"))
                         if f.endswith(".yaml"))
        for f in configs:
            paths = [os.path.join(t, "configs", f) for t in (base, ROOT)]
            if not os.path.exists(paths[0]):
                continue
            texts = [open(q, encoding="utf-8").read() for q in paths]
            if texts[0] != texts[1]:
                print(f"integer_delay_identity: {f} differs between the trees: skipped",
                      file=sys.stderr)
                continue
            print(f"integer_delay_identity: check {f} ...", file=sys.stderr)
            # the same file for both (its path is in the output; the texts are equal)
            outs = [_run(t, ["-m", "hapsim", "check", paths[1], "--json"])
                    for t in (base, ROOT)]
            total += 1
            nums = [_numbers(o) for o in outs]
            common = set(nums[0]) & set(nums[1])
            bad = sorted(k for k in common if nums[0][k] != nums[1][k])
            if bad or not common:
                diffs.append(f"check {f} ({', '.join(bad[:3]) or 'no output'})")
    print(f"{total} comparisons, {len(diffs)} differ" + (": " + ", ".join(diffs[:10])
                                                         if diffs else " (bit for bit)"))
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())

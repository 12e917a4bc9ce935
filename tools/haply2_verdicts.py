"""How often the 2DIY run's verdict is right: random measurements through the emulated
board's bytes (both pantograph scenes, both generations, encoders of 2^17..2^23 counts per
revolution, excitations of 10 to 5000 reading steps, 150 or 300 samples) on a correct loop,
counted by verdict and by statement (the felt matrices and the principal directions:
:func:`hapsim.analysis.felt_matrices.felt_verdict`), with the largest deviation over the stated
uncertainty of a stated quantity (a correct loop must never be "differs").

    python tools/haply2_verdicts.py [--cases 60] [--seed 7]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from hapsim.emulated.haply2_lockstep import measure_felt_haply2
from hapsim.kinematics import device
from hapsim.lockstep import identification_plan
from hapsim.scene import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def main() -> int:
    """Run the cases; print one line each, then the counts (exit 1 on a "differs")."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=60)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    plans, counts, per, worst = {}, {}, {}, 0.0
    for _ in range(args.cases):
        name = str(rng.choice(["wall", "circle"]))
        gen = str(rng.choice(["gen2", "gen3"]))
        bits = int(rng.integers(17, 24))
        quanta = math.exp(rng.uniform(math.log(10), math.log(5000)))
        N = int(rng.choice([150, 300]))
        if (name, N) not in plans:
            sc = load_scene_nd(CONFIGS / f"pantograph_{name}.yaml")
            plans[name, N] = (sc, identification_plan(sc, N))
        sc, plan = plans[name, N]
        J = device("pantograph", sc.device.geometry).jacobian(sc.device.joints)
        a = min(quanta * np.linalg.norm(J, 2) * 2 * math.pi / 2.0 ** bits, 4.5e-4)
        r = measure_felt_haply2(sc, gen, amplitude=a, cpr=2.0 ** bits, samples=N, plan=plan)
        counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
        w = r["wire"]
        stated = [s for s in r["statements"] if s["verdict"] != "not measurable"]
        for s in r["statements"]:
            kind = "matrix" if s["direction"] is None else "direction"
            key = (kind, s["verdict"])
            per[key] = per.get(key, 0) + 1
        ratio = None
        if stated:
            ratio = max(s["deviation"] / s["uncertainty"] for s in stated)
            worst = max(worst, ratio)
        print(f"{name} {gen} 2^{bits} N={N} a={a:.2e} m: {r['verdict']}; wire "
              f"{w['felt_stiffness']:.2e} / {w['felt_damping']:.2e}; stated "
              f"{len(stated)} of {len(r['statements'])}"
              + (f"; deviation / uncertainty {ratio:.3f}" if ratio is not None else ""),
              flush=True)
    print(f"verdicts: {counts}; statements: "
          + ", ".join(f"{k[0]} {k[1]} {v}" for k, v in sorted(per.items()))
          + f"; largest deviation / uncertainty of a stated one: {worst:.3f}")
    return 1 if counts.get("differs") else 0


if __name__ == "__main__":
    raise SystemExit(main())

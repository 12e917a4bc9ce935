"""How often the 2DIY run's verdict is right: random measurements through the emulated
board's bytes (both pantograph scenes, both generations, encoders of 2^17..2^23 counts per
revolution, excitations of 10 to 5000 reading steps, 150 or 300 samples) on a correct loop,
counted by verdict and by statement (the felt matrices and the principal directions:
:func:`hapsim.analysis.felt_matrices.felt_verdict`), with the largest deviation over the stated
uncertainty of a stated quantity (a correct loop must never be "differs").

    python tools/haply2_verdicts.py [--cases 60] [--seed 7]
    python tools/haply2_verdicts.py --clock wall [--cases 8] [--seed 2]

``--clock wall``: each case is ``hapsim run SCENE --driver haply`` as users run it, the
emulated 2DIY on its own clock behind a pty, twice: on a board that matches the scene and
on one with 30 % more joint inertia and hand mass hidden in it (the prediction keeps the
scene's). The scenes are configs/pantograph_wall.yaml with the press and the wall drawn
(stiffness, damping), the press's anchor moved so that the handle rests 0.5 mm in the
wall, the joint friction 1-3e-3 N m s/rad. A matching board must never "differ", nor
any of its statements; a heavier one never be "within", nor any statement whose true
deviation (the same measurement in lockstep, the heavier board as its plant) is beyond
twice the uncertainty stated: a statement "within" nearer than that is true (exit 1 on
either); "not measurable" with its reason is an honest answer.
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


def wall_scenes(rng, cases: int, folder: Path) -> list:
    """``cases`` pairs of scene files (the run's, the hidden board's): module notes."""
    import copy

    import yaml
    base = yaml.safe_load((CONFIGS / "pantograph_wall.yaml").read_text())
    out = []
    for c in range(cases):
        sc = copy.deepcopy(base)
        kp, kw = float(rng.uniform(50, 500)), float(rng.uniform(300, 3000))
        sc["links"][0].update(stiffness=kp, damping=float(rng.uniform(0.1, 2.0)))
        sc["planes"][0].update(stiffness=kw, damping=float(rng.uniform(0.5, 5.0)))
        # at rest: the press holds the handle 0.5 mm into the wall (the shipped scene's
        # rest), its anchor where its force balances the wall's
        depth = 0.5e-3
        rest_y = sc["planes"][0]["offset"] - depth
        sc["masses"][1]["x0"] = [sc["masses"][1]["x0"][0], rest_y - kw * depth / kp]
        fr = float(rng.uniform(1e-3, 3e-3))
        sc["device"]["joint_friction"] = [fr, fr]
        heavy = copy.deepcopy(sc)
        heavy["device"]["joint_inertia"] = [1.3 * v for v in sc["device"]["joint_inertia"]]
        heavy["device"]["hand_mass"] = 1.3 * sc["device"]["hand_mass"]
        pair = []
        for name, doc in ((f"case{c}.yaml", sc), (f"case{c}_heavier.yaml", heavy)):
            (folder / name).write_text(yaml.safe_dump(doc))
            pair.append(str(folder / name))
        out.append((pair, kp, kw, fr))
    return out


def _truth(run: str, heavier: str, generation: str) -> dict:
    """Each statement's true deviation of the heavier board's loop from the scene's
    prediction: the same measurement in lockstep on a clean stream
    (:func:`hapsim.emulated.haply2_lockstep.measure_felt_haply2` with the heavier board's
    scene as its plant, the run's encoder), by statement name."""
    from hapsim.commands.run_haply2 import HAPLY_CPR
    from hapsim.scene import load_scene_nd
    r = measure_felt_haply2(load_scene_nd(run), generation, cpr=HAPLY_CPR,
                            plant=load_scene_nd(heavier))
    return {st["name"]: float(st["deviation"]) for st in r["statements"]}


def main_wall(args) -> int:
    """``--clock wall`` (module notes): one line per run, then the counts."""
    import contextlib
    import io
    import json
    import tempfile

    import hapsim.pipeline.haply2_embedded as embedded
    from hapsim.cli import main as cli
    rng = np.random.default_rng(args.seed)
    board = {"scene": None}
    real = embedded.Embedded2DIY

    class Hidden(real):                      # the board's scene, not the run's
        def __init__(self, scene_path, *a, **kw):
            super().__init__(board["scene"] or scene_path, *a, **kw)

    embedded.Embedded2DIY = Hidden
    counts, wrong = {}, 0
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as undo:
        undo.callback(setattr, embedded, "Embedded2DIY", real)
        for (run, heavier), kp, kw, fr in wall_scenes(rng, args.cases, Path(tmp)):
            for side, path in (("matching", None), ("heavier", heavier)):
                board["scene"] = path
                out, err = io.StringIO(), io.StringIO()
                with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                    code = cli(["run", run, "--driver", "haply", "--json"])
                try:
                    rep = json.loads(out.getvalue())
                    v, why = rep["verdict"], rep.get("reason", "")
                    said = [st["verdict"] for st in rep.get("statements", [])]
                except ValueError:
                    v, why = f"exit {code}", err.getvalue().strip().splitlines()[-1:]
                    said = []
                # (each statement too: a matching board's statement never "differs"; a
                # heavier board's "within" is wrong where its loop's true deviation along
                # it is beyond twice the uncertainty stated: the measurement then left its
                # uncertainty, as tests/test_wire_rounding.py's leg-inertia property
                # reads it. A 30 % heavier 2DIY moves each felt quantity ~0.23 (the poles
                # over the scene's mass), and a damping the records hardly fix is stated
                # with more: "within" it is then true, as the 1-D fuzz's verdict is)
                if side == "matching":
                    bad = v == "differs" or "differs" in said
                else:
                    truth = _truth(run, heavier, rep.get("generation", "gen3"))
                    far = [st["name"] for st in rep.get("statements", [])
                           if st["verdict"] == "within"
                           and truth.get(st["name"], 0.0) > 2.0 * st["uncertainty"]]
                    bad = v == "within" or bool(far)
                wrong += bad
                counts[side, v] = counts.get((side, v), 0) + 1
                print(f"press {kp:.0f} N/m, wall {kw:.0f} N/m, friction {fr:.2g}, {side}: "
                      f"{v}{'  WRONG' if bad else ''}"
                      + ("" if v in ("within", "differs") else f" ({str(why)[:160]})"),
                      flush=True)
    print("; ".join(f"{side} {v} {n}" for (side, v), n in sorted(counts.items()))
          + f"; wrong verdicts: {wrong}")
    return 1 if wrong else 0


def main() -> int:
    """Run the cases; print one line each, then the counts (exit 1 on a "differs")."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=None,
                    help="cases (default 60 in lockstep, 8 on the wall clock)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--clock", choices=("lockstep", "wall"), default="lockstep",
                    help="lockstep (a correct loop, default) or the board's own clock "
                         "(hapsim run, a matching and a heavier board)")
    args = ap.parse_args()
    if args.clock == "wall":
        args.cases = 8 if args.cases is None else args.cases
        return main_wall(args)
    args.cases = 60 if args.cases is None else args.cases
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

"""The figures of the wire's rounding term of the n-D felt matrices (issue 29,
:mod:`hapsim.analysis.wire_rounding`): how much real rounding moves each statement, against
the worst case over the errors' box and the first-order figures.

Usage::

    python tools/rounding_figures.py falcon [--scene configs/falcon_spring.yaml]
                                            [--draws 400] [--emulated 60]
    python tools/rounding_figures.py falcon-coverage [--seeds 0 ... 39] [--samples 300]
    python tools/rounding_figures.py haply2 [--scene configs/pantograph_wall.yaml]
    python tools/rounding_figures.py haply2-lossy [--seeds 1 ... 10]
    ... [--json PATH]

``falcon``: on the scene at its largest start (:func:`hapsim.emulated.falcon_felt.
felt_feasibility`'s), ``--draws`` draws of the Falcon's rounding (the counts' and the motor
commands' phases) through the predicted loop (:func:`hapsim.analysis.wire_rounding.
rounded_records`), each refitted by the run's fit: the median, 95th and 99th percentiles
and the largest change of each statement, relative (the matrices' largest entry over the
predicted one's, each principal direction over its predicted value); the same with the
roundings applied to the exact records afterwards (no loop gain), with the readings alone
and with the commands alone; the draws that lost a pair or rendered a noise pair, with and
without :data:`hapsim.analysis.pencil.MODE_FLOOR`'s floor; the signed bias of each
direction; beside them the first-order worst case about the exact records, Widrow &
Kollar's standard deviation (:func:`hapsim.emulated.falcon_felt.quantiser_terms`) and the
worst case over the errors' box at the exact records and at the emulated Falcon's own
records (:func:`hapsim.lockstep.wire_terms_nd` with ``box=True``); with ``--emulated K``,
K runs of the emulated Falcon itself (its packets, the delta's joint-space dynamics) with
its encoders' index at uniform sub-count offsets, their change from the joint-space exact
records' fit against the model's.

``falcon-coverage``: over seeded random spring fields on the Falcon (legs' inertia and
friction, the field's stiffness and damping: ``tests/test_wire_box_devices.py``'s
family), each at its largest start with a random encoder offset, the matching device's
statements and verdict as the run states them, and each statement's rounding change on
the emulated Falcon over the model's largest (the margin's measurement).

``haply2``, ``haply2-lossy``: the 2DIY (emulated board in lockstep, 2^22 counts) without
loss, and with 1 byte in 200 lost each way (seeded), the wire's term as stated and its
parts.

A measurement program, lockstep throughout (no wall clock): its figures are the same on
any machine up to the BLAS's round-off.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

NAMES = ("stiffness", "damping")


def _rel(chk, wc):
    """Per statement, relative: [k, b, k along e_i..., b along e_i...]."""
    from hapsim.lockstep import relative_terms
    r = relative_terms(chk, wc)
    return ([r["felt_stiffness"], r["felt_damping"]] + r["directions"]["felt_stiffness"]
            + r["directions"]["felt_damping"])


def _labels(n):
    return (["k", "b"] + [f"k{i + 1}" for i in range(n)] + [f"b{i + 1}" for i in range(n)])


def _changes_rel(fit, ref, chk):
    from hapsim.analysis.wire_rounding import _changes
    return _rel(chk, _changes(fit, ref, np.asarray(chk.render.directions, float)))


def falcon(args) -> dict:
    """The Falcon's figures on one scene (module notes)."""
    from hapsim.analysis.pencil import MODE_FLOOR, fit_felt_nd
    from hapsim.analysis.wire_rounding import (Rounding, exact_loop, noise_pair,
                                               rounded_records, virtual_response)
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    from hapsim.emulated.falcon_felt import felt_feasibility, quantiser_terms
    from hapsim.kinematics import device
    from hapsim.lockstep import LockstepND, excitation_starts, identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(args.scene)
    plan = identification_plan(sc)
    chk, order, N = plan
    t0 = time.process_time()
    f = felt_feasibility(sc, plan)
    a = f["amplitude_m"]
    out = {"scene": args.scene, "amplitude_m": a, "samples": N,
           "feasibility": {k: f.get(k) for k in ("verdict", "stated", "not_stated",
                                                   "lockstep")},
           "feasibility_cpu_s": time.process_time() - t0}
    q0 = np.asarray(sc.device.joints, float)
    J = device("delta", sc.device.geometry).jacobian(q0)
    q = math.radians(DEG_PER_TICK)
    mass, T = sc.device.mass, sc.period

    def fit(recs, floor=None):
        return fit_felt_nd([r - recs[0] for r in recs[1:]], mass, T, order, floor=floor)
    floor = MODE_FLOOR * float(np.linalg.norm(np.abs(J) @ np.full(3, q / 2))) * 2
    exact = exact_loop(sc, a, N)
    ref = fit([X for X, _ in exact])
    V = virtual_response(sc, N)
    E = np.asarray(chk.render.directions, float)
    labels = _labels(3)
    cases = {"in the loop": (Rounding(J, q0, q, command=TORQUE_PER_COUNT), True),
             "afterwards (no loop gain)": (Rounding(J, q0, q, command=TORQUE_PER_COUNT),
                                           False),
             "readings alone": (Rounding(J, q0, q), True),
             "commands alone": (Rounding(J, q0, q * 1e-9, command=TORQUE_PER_COUNT), True)}
    out["draws"] = {}
    for name, (rd, fb) in cases.items():
        Ys = rounded_records(sc, rd, exact, args.draws, 1, feedback=fb, V=V)
        C, lost, noise, lost_f, signed = [], 0, 0, 0, []
        for r in range(args.draws):
            recs = [Y[r] for Y in Ys]
            g = fit(recs)
            if g["felt_stiffness"] is None:
                lost += 1
                continue
            noise += bool(noise_pair(g, ref))
            lost_f += fit(recs, floor)["felt_stiffness"] is None
            C.append(_changes_rel(g, ref, chk))
            signed.append([float(E[:, i] @ g[qq] @ E[:, i] / (E[:, i] @ ref[qq] @ E[:, i])
                                 - 1.0) for qq in ("felt_stiffness", "felt_damping")
                           for i in range(3)])
        C = np.array(C)
        S = np.array(signed)
        out["draws"][name] = {
            "draws": args.draws, "lost": lost, "noise": noise,
            "lost_with_floor": int(lost_f),
            **{stat: dict(zip(labels, map(float, fn(C))))
               for stat, fn in (("median", lambda c: np.median(c, 0)),
                                ("q95", lambda c: np.quantile(c, 0.95, 0)),
                                ("q99", lambda c: np.quantile(c, 0.99, 0)),
                                ("largest", lambda c: c.max(0)))},
            "bias_along_directions": dict(zip(labels[2:], map(float, S.mean(0)))),
            "sd_along_directions": dict(zip(labels[2:], map(float, S.std(0))))}
    t = quantiser_terms(sc, a, plan)
    out["first_order_worst_exact"] = t["worst"]
    out["widrow_kollar_sd"] = t["widrow_kollar"]
    # the box's worst case at the exact records and at the emulated Falcon's records
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    from hapsim.lockstep import wire_terms_nd
    errors = [("reading", J, np.full(3, q / 2)),
              ("force", np.linalg.inv(J).T, np.full(3, TORQUE_PER_COUNT / 2))]
    box_exact = wire_terms_nd(sc, [X - exact[0][0] for X, _ in exact[1:]], chk, order,
                              errors, box=True)
    m = measure_felt_falcon(sc, a, plan=plan)
    x_eq = device("delta", sc.device.geometry).forward(q0)
    pos = [np.asarray(r, float) for r in m.get("positions", [])] or None
    out["box_at_exact_records"] = {k: box_exact[k] for k in ("felt_stiffness",
                                                             "felt_damping", "directions")}
    out["run_lockstep"] = {"verdict": m["verdict"], "deviation": m["deviation"],
                           "wire": {k: m["wire"][k] for k in ("felt_stiffness",
                                                             "felt_damping", "directions")},
                           "statements": [(s["name"], s["deviation"], s["uncertainty"],
                                           s["verdict"]) for s in m["statements"]]}
    del pos, x_eq
    if args.emulated:
        from hapsim.lockstep import LockstepND as L
        exact_j = [L(sc, x0=x0, v0=v0, joint_space=True).step(N, record=True)
                   for x0, v0 in excitation_starts(3, a, sc.period)]
        ref_j = fit(exact_j)
        out["joint_space_exact_deviation"] = _changes_rel(ref_j, ref, chk)
        rng = np.random.default_rng(5)
        C = []
        for _ in range(args.emulated):
            off = rng.uniform(-0.5, 0.5, 3)
            recs = _falcon_records(sc, a, N, off)
            g = fit(recs)
            C.append(_changes_rel(g, ref_j, chk) if g["felt_stiffness"] is not None
                     else [math.inf] * 8)
        C = np.array(C)
        big = np.array([out["draws"]["in the loop"]["largest"][k] for k in labels])
        out["emulated"] = {"runs": args.emulated,
                           "median": dict(zip(labels, map(float, np.median(C, 0)))),
                           "largest": dict(zip(labels, map(float, C.max(0)))),
                           "largest_over_model_largest": dict(zip(
                               labels, map(float, C.max(0) / big)))}
    del LockstepND
    return out


def _falcon_records(sc, a, N, offset, plant=None, max_step=8):
    """The emulated Falcon's 7 records (lockstep) with its encoders at ``offset``,
    displacements from the operating point [m]."""
    from hapsim.drivers.falcon import DevicePacketDecoder, LED_BLUE, LED_GREEN
    from hapsim.emulated.falcon_device import FalconDevice, drive_falcon, home, load_firmware
    from hapsim.kinematics import device
    from hapsim.lockstep import excitation_starts
    x_eq = device("delta", sc.device.geometry).forward(np.asarray(sc.device.joints, float))
    out = []
    for x0, v0 in excitation_starts(3, a, sc.period):
        dev = FalconDevice(plant if plant is not None else sc, clock="lockstep",
                           encoder_offset=offset)
        load_firmware(dev, b"\x00" * 16)
        home(dev.feed, LED_BLUE, decoder=DevicePacketDecoder())
        dev.let_go(x0, v0)
        r = drive_falcon(dev.feed, sc, N, leds=LED_GREEN,
                         decoder=DevicePacketDecoder(max_step))
        out.append(np.asarray(r["position"], float) - x_eq)
    return out


def falcon_coverage(args) -> dict:
    """The matching device's statements over random spring fields (module notes)."""
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from test_wire_box_devices import _falcon_loop
    from hapsim.emulated.falcon_felt import felt_feasibility, measure_felt_falcon
    from hapsim.lockstep import identification_plan
    rows = []
    for seed in args.seeds:
        sc, rng = _falcon_loop(seed)
        plan = identification_plan(sc, args.samples)
        f = felt_feasibility(sc, plan)
        if f["amplitude_m"] <= 0:
            continue
        off = rng.uniform(-0.5, 0.5, 3)
        m = measure_felt_falcon(sc, f["amplitude_m"], plan=plan, encoder_offset=off)
        rd = m["wire"].get("rounding") or {}
        big = rd.get("largest")
        row = {"seed": seed, "verdict": m["verdict"], "stated_before": f["stated"],
               "statements": []}
        for s in m["statements"]:
            row["statements"].append({k: s[k] for k in ("name", "verdict", "deviation",
                                                        "uncertainty", "linearisation",
                                                        "wire")})
        if big:
            row["largest"] = big
        rows.append(row)
        print(seed, m["verdict"], [(s["name"][:22], s["verdict"][:6],
                                    round(s["deviation"], 3),
                                    None if s["uncertainty"] is None
                                    else round(s["uncertainty"], 3))
                                   for s in m["statements"] if s["verdict"] != "not measurable"],
              flush=True)
    stated = [s for r in rows for s in r["statements"] if s["verdict"] != "not measurable"]
    return {"samples": args.samples, "seeds": list(args.seeds), "runs": rows,
            "stated": len(stated), "differs": sum(s["verdict"] == "differs" for s in stated),
            "verdicts": {v: sum(r["verdict"] == v for r in rows)
                         for v in ("within", "partly within", "differs", "not measurable")},
            "largest_share": max((s["deviation"] / s["uncertainty"] for s in stated),
                                 default=None)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("falcon", "falcon-coverage"))
    p.add_argument("--scene", default="configs/falcon_spring.yaml")
    p.add_argument("--draws", type=int, default=400)
    p.add_argument("--emulated", type=int, default=0)
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(40)))
    p.add_argument("--samples", type=int, default=None)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    t0 = time.process_time()
    out = {"falcon": falcon, "falcon-coverage": falcon_coverage}[args.what](args)
    out["cpu_s"] = time.process_time() - t0
    text = json.dumps(out, indent=1, default=float)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

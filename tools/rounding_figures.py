"""The figures of the wire's rounding term of the n-D felt matrices (issue 29,
:mod:`hapsim.analysis.wire_rounding`): how much real rounding moves each statement,
against the worst case over the errors' box and the first-order figures, and whether the
term covers the devices' own rounding.

Usage::

    python tools/rounding_figures.py falcon [--scene configs/falcon_spring.yaml]
                                            [--draws 400] [--emulated 60] [--json PATH]
    python tools/rounding_figures.py falcon-coverage [--seeds 0 ... 19] [--samples 300]
                                            [--offsets 5] [--loss 0] [--json PATH]
    python tools/rounding_figures.py haply2 [--seeds 1 ... 10] [--loss 0.005] [--json PATH]

``falcon``: on the scene at its largest start (the run's, :func:`hapsim.emulated.
falcon_felt.felt_feasibility`), ``--draws`` draws of the Falcon's rounding (the counts'
and the motor commands' phases) through the predicted loop (:func:`hapsim.analysis.
wire_rounding.rounded_records`), each refitted by the run's fit: the median, 95th and
99th percentiles and the largest change of each statement, relative (a matrix's largest
entry over the predicted one's, a principal direction's over its predicted value), the
signed bias and the spread along each direction; the same with the roundings applied to
the exact records afterwards (no loop gain), with the readings alone and the commands
alone; the draws that lost a pair or rendered a noise pair, and those that would lose a
pair under :data:`hapsim.analysis.pencil.MODE_FLOOR`'s floor; beside them the first-order
worst case about the exact records and Widrow & Kollar's standard deviation
(:func:`hapsim.emulated.falcon_felt.quantiser_terms`) and the worst case over the errors'
box at the exact records (:func:`hapsim.lockstep.wire_terms_nd` with ``box=True``); the
run's own lockstep statement; with ``--emulated K``, K runs of the emulated Falcon itself
(its packets, the delta's joint-space dynamics) with its encoders' index at uniform
sub-count offsets, each statement's change from the same records through an encoder 64
times finer, over the largest change of the run's draws (the margin's measurement).

``falcon-coverage``: seeded random spring fields on the Falcon (legs' inertia and
friction, the field's stiffness and damping: ``tests/test_wire_box_devices.py``'s
family) at their largest start, ``--offsets`` encoder offsets each, ``--loss`` bytes lost
each way (seeded): the matching device's verdicts, its rounding change over the draws'
largest (as ``--emulated``), and a device with 30-45 % more leg inertia's verdict.

``haply2``: the 2DIY on configs/pantograph_wall.yaml at its default start, the emulated
board in lockstep (2^22 counts), ``--loss`` bytes lost each way: the verdicts, the wire's
term as stated, the worst case over the errors' box of the same rounding (the term stated
before) and of the estimated samples alone; a board with 30 % more joint inertia.

A measurement program, lockstep throughout (no wall clock; the 2DIY's host waits for
lost replies on its own clock, which moves no figure): the same figures on any machine
up to the BLAS's round-off.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from provenance import command_line  # noqa: E402  (tools/, beside this file)

#: Encoder 64 times finer than the Falcon's: the reference the emulated rounding's change
#: is taken against (its own rounding 1/64 of the Falcon's).
FINER = 64


def _labels(n: int) -> list:
    return ["k", "b"] + [f"k{i + 1}" for i in range(n)] + [f"b{i + 1}" for i in range(n)]


def _flat(rel: dict) -> list:
    """A :func:`hapsim.lockstep.relative_terms` dict as [k, b, k along e_i, b along e_i]."""
    return ([rel["felt_stiffness"], rel["felt_damping"]] + rel["directions"]["felt_stiffness"]
            + rel["directions"]["felt_damping"])


def _change(fit, ref, chk) -> np.ndarray:
    """Each statement's change between two fits, relative."""
    from hapsim.analysis.wire_rounding import _changes
    from hapsim.lockstep import relative_terms
    return np.array(_flat(relative_terms(chk, _changes(fit, ref, np.asarray(
        chk.render.directions, float)))))


def _named(labels, values) -> dict:
    return {k: float(v) for k, v in zip(labels, values)}


def _emulated(sc, a, plan, offset, *, plant=None, finer=1.0, faults=None):
    """The run's statement on the emulated Falcon's records in lockstep
    (:func:`hapsim.emulated.falcon_felt.measure_felt_falcon`), its encoder ``finer`` times
    the Falcon's (its zero moved to 20 deg so the counts stay in int16)."""
    import hapsim.drivers.falcon as falcon
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    saved = (falcon.DEG_PER_TICK, falcon.THETA_OFFSET_DEG, falcon.START_STEP)
    if finer != 1.0:
        falcon.DEG_PER_TICK /= finer
        falcon.THETA_OFFSET_DEG = 20.0
        falcon.START_STEP = int(falcon.START_STEP * finer)
    try:
        return measure_felt_falcon(sc, a, plan=plan, encoder_offset=offset, plant=plant,
                                   max_step=int(8 * finer), faults=faults)
    finally:
        falcon.DEG_PER_TICK, falcon.THETA_OFFSET_DEG, falcon.START_STEP = saved


def _ratio(m, fine, chk):
    """The emulated rounding's change over the run's draws' largest, per statement (None
    when either fit has no felt matrices or the two cut other rows)."""
    rd = m["wire"].get("rounding")
    if (not rd or m["measured"] is None or fine["measured"] is None
            or m["measured"]["felt_stiffness"] is None
            or fine["measured"]["felt_stiffness"] is None
            or m["fitted_rows"] != fine["fitted_rows"]):
        return None
    return _change(m["measured"], fine["measured"], chk) / np.array(_flat(rd["largest"]))


def falcon(args) -> dict:
    """The Falcon's figures on one scene (module notes)."""
    from hapsim.analysis.pencil import MODE_FLOOR, fit_felt_nd
    from hapsim.analysis.wire_rounding import (Rounding, exact_loop, noise_pair,
                                               rounded_records, virtual_response)
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    from hapsim.emulated.falcon_felt import felt_feasibility, quantiser_terms
    from hapsim.lockstep import identification_plan, wire_terms_nd
    from hapsim.kinematics import device
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
    # the 2DIY's floor rule (its records' bound times MODE_FLOOR, twice in a difference)
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
        C, lost, noise, lost_floor, signed = [], 0, 0, 0, []
        for r in range(args.draws):
            recs = [Y[r] for Y in Ys]
            g = fit(recs)
            if g["felt_stiffness"] is None:
                lost += 1
                continue
            noise += bool(noise_pair(g, ref))
            lost_floor += fit(recs, floor)["felt_stiffness"] is None
            C.append(_change(g, ref, chk))
            signed.append([float(E[:, i] @ g[k] @ E[:, i] / (E[:, i] @ ref[k] @ E[:, i])
                                 - 1.0) for k in ("felt_stiffness", "felt_damping")
                           for i in range(3)])
        C, S = np.array(C), np.array(signed)
        out["draws"][name] = {
            "draws": args.draws, "lost": lost, "noise": noise,
            "lost_under_the_floor": int(lost_floor),
            "median": _named(labels, np.median(C, 0)),
            "q95": _named(labels, np.quantile(C, 0.95, 0)),
            "q99": _named(labels, np.quantile(C, 0.99, 0)),
            "largest": _named(labels, C.max(0)),
            "bias_along_directions": _named(labels[2:], S.mean(0)),
            "sd_along_directions": _named(labels[2:], S.std(0))}
    t = quantiser_terms(sc, a, plan)
    out["first_order_worst_exact"] = t["worst"]
    out["widrow_kollar_sd"] = t["widrow_kollar"]
    errors = [("reading", J, np.full(3, q / 2)),
              ("force", np.linalg.inv(J).T, np.full(3, TORQUE_PER_COUNT / 2))]
    box = wire_terms_nd(sc, [X - exact[0][0] for X, _ in exact[1:]], chk, order, errors,
                        box=True)
    out["box_at_exact_records"] = _named(labels, _flat(box))
    m = _emulated(sc, a, plan, np.zeros(3))
    out["run_lockstep"] = {
        "verdict": m["verdict"], "deviation": m["deviation"],
        "wire": _named(labels, _flat(m["wire"])),
        "statements": [{k: s[k] for k in ("name", "verdict", "deviation", "uncertainty",
                                          "linearisation", "wire")}
                       for s in m["statements"]]}
    if args.emulated:
        rng = np.random.default_rng(5)
        R = []
        for _ in range(args.emulated):
            off = rng.uniform(-0.5, 0.5, 3)
            r = _ratio(_emulated(sc, a, plan, off), _emulated(sc, a, plan, off,
                                                              finer=FINER), chk)
            if r is not None:
                R.append(r)
        R = np.array(R)
        out["emulated"] = {"runs": args.emulated, "compared": len(R),
                           "change_over_draws_largest": {
                               "median": _named(labels, np.median(R, 0)),
                               "largest": _named(labels, R.max(0))},
                           "above_the_largest": int(np.sum(R > 1.0))}
    return out


def falcon_coverage(args) -> dict:
    """The matching and a heavier device's statements over random spring fields (module
    notes)."""
    sys.path.insert(0, ROOT)
    from tests.test_wire_box_devices import _falcon_loop
    from hapsim.drivers.falcon import ENVELOPE_RAD
    from hapsim.emulated.driver_mock import ByteFaults
    from hapsim.lockstep import identification_plan, largest_start
    rows, R = [], []
    stated = differs = heavy_runs = heavy_differs = 0
    share = 0.0
    for seed in args.seeds:
        sc, rng = _falcon_loop(seed)
        heavy, _ = _falcon_loop(seed, inertia=float(
            np.random.default_rng(seed).uniform(1.3, 1.45)))
        plan = identification_plan(sc, args.samples)
        chk = plan[0]
        a = largest_start(sc, plan[2], ENVELOPE_RAD)[0]

        def faults(k):
            return (ByteFaults({"drop_rx": args.loss, "drop_tx": args.loss,
                                "seed": 100 + 10 * seed + k}) if args.loss else None)
        for k in range(args.offsets):
            off = rng.uniform(-0.5, 0.5, 3)
            m = _emulated(sc, a, plan, off, faults=faults(k))
            made = [s for s in m["statements"] if s["verdict"] != "not measurable"]
            stated += len(made)
            differs += sum(s["verdict"] == "differs" for s in made)
            share = max([share] + [s["deviation"] / s["uncertainty"] for s in made])
            r = _ratio(m, _emulated(sc, a, plan, off, finer=FINER, faults=faults(k)), chk)
            if r is not None:
                R.append(r)
            row = {"seed": seed, "offset": off.tolist(), "verdict": m["verdict"],
                   "stated": len(made), "missing": m["missing"],
                   "ratio_largest": None if r is None else float(r.max())}
            if k == 0:
                h = _emulated(sc, a, plan, off, plant=heavy, faults=faults(k))
                heavy_runs += 1
                heavy_differs += h["verdict"] == "differs"
                row["heavier"] = h["verdict"]
            rows.append(row)
            print(seed, k, row["verdict"], row["stated"], row.get("heavier"),
                  row["ratio_largest"], flush=True)
    R = np.array(R)
    labels = _labels(3)
    return {"samples": args.samples, "loss": args.loss, "offsets": args.offsets,
            "seeds": list(args.seeds), "runs": rows, "stated": stated, "differs": differs,
            "largest_deviation_over_uncertainty": share,
            "heavier": {"runs": heavy_runs, "differs": heavy_differs},
            "change_over_draws_largest": {"compared": len(R),
                                          "largest": _named(labels, R.max(0)),
                                          "above_the_largest": int(np.sum(R > 1.0)),
                                          "statements": int(R.size)}}


def haply2(args) -> dict:
    """The 2DIY's verdicts and wire terms (module notes)."""
    from dataclasses import replace
    import hapsim.pipeline.haply2_host as host
    from hapsim.commands.run_haply2 import designed_start
    from hapsim.emulated.driver_mock import ByteFaults
    from hapsim.emulated.haply2_board import Haply2DIYBoard
    from hapsim.emulated.links import BoardLink
    from hapsim.emulated.haply2_verdict import felt_verdict_of_runs
    from hapsim.lockstep import identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(os.path.join(ROOT, "configs", "pantograph_wall.yaml"))
    heavy = replace(sc, device=replace(sc.device,
                                       joint_inertia=sc.device.joint_inertia * 1.3))
    a = designed_start(sc)[0]
    N = 200
    plan = identification_plan(sc, N)
    seen = {}

    def keep(scene, runs, plan_, resolution, amplitude, **kw):
        seen.update(runs=copy.deepcopy(runs), resolution=resolution)
        return felt_verdict_of_runs(scene, runs, plan_, resolution, amplitude, **kw)

    def run(seed, plant):
        board = Haply2DIYBoard(plant, "gen3", cpr=2.0 ** 22, amplitude=a, clock="lockstep")
        f = ByteFaults({"drop_rx": args.loss, "drop_tx": args.loss, "seed": seed})
        return host.measure_felt_haply2_port(BoardLink(board, f.rx, f.tx), sc, "gen3",
                                             amplitude=a,
                                             resolution=2.0 ** 22, samples=N, plan=plan,
                                             probe_wiring=False, lockstep_board=True)
    real = host.felt_verdict_of_runs
    host.felt_verdict_of_runs = keep
    rows = []
    try:
        for seed in args.seeds:
            m = run(seed, sc)
            made = [s for s in m["statements"] if s["verdict"] != "not measurable"]
            row = {"seed": seed, "verdict": m["verdict"], "estimated": sum(m["estimated"]),
                   "resyncs": sum(m["resyncs"]),
                   "statements": [{k: s[k] for k in ("name", "verdict", "deviation",
                                                    "uncertainty", "wire")} for s in made],
                   "wire": {k: m["wire"][k] for k in ("felt_stiffness", "felt_damping")},
                   "largest_deviation_over_uncertainty": max(
                       (s["deviation"] / s["uncertainty"] for s in made), default=None)}
            row["box_rounding"] = _box_rounding(sc, seen["runs"], plan, seen["resolution"],
                                                a)
            row["heavier"] = run(seed, heavy)["verdict"]
            rows.append(row)
            print(seed, row["verdict"], row["wire"], row["box_rounding"], row["heavier"],
                  flush=True)
    finally:
        host.felt_verdict_of_runs = real
    return haply2_summary({"loss": args.loss, "amplitude_m": a, "samples": N,
                           "runs": rows})


def haply2_summary(out: dict) -> dict:
    """``out`` with its summary over the runs: the verdicts, the heavier board's, and the
    range of the wire's term stated, of the box's over the same rounding and of the
    departure over the uncertainty."""
    rows = out["runs"]

    def span(get):
        vals = [get(r) for r in rows if get(r) is not None]
        return [min(vals), max(vals)] if vals else None
    out["verdicts"] = {v: sum(r["verdict"] == v for r in rows)
                       for v in ("within", "partly within", "differs", "not measurable")}
    out["heavier"] = {v: sum(r["heavier"] == v for r in rows)
                      for v in ("within", "partly within", "differs", "not measurable")}
    out["span"] = {"wire_k": span(lambda r: r["wire"]["felt_stiffness"]),
                   "wire_b": span(lambda r: r["wire"]["felt_damping"]),
                   "box_rounding_k": span(lambda r: r["box_rounding"]["rounding"]
                                          ["felt_stiffness"]),
                   "box_rounding_b": span(lambda r: r["box_rounding"]["rounding"]
                                          ["felt_damping"]),
                   "deviation_over_uncertainty": span(
                       lambda r: r["largest_deviation_over_uncertainty"]),
                   "estimated": span(lambda r: r["estimated"])}
    return out


def _box_rounding(sc, runs, plan, resolution, a) -> dict:
    """The worst case over the errors' box of the 2DIY's rounding (half a count plus a
    binary32 ulp per reading, the torque's binary32 rounding) at these records, as the
    verdict stated it before its rounding term, and of the estimated samples alone."""
    from hapsim.analysis.felt_records import wire_terms_records
    from hapsim.emulated.haply2_verdict import _without_estimates
    from hapsim.analysis.felt_records import within_excursion
    from hapsim.kinematics import device
    chk, order, N = plan
    q = np.asarray(sc.device.joints, float)
    kin = device("pantograph", sc.device.geometry)
    J, x_eq = kin.jacobian(q), kin.forward(q)
    d = int(math.ceil(float(sc.device.delay)))
    own = within_excursion(sc, [r["position"] - x_eq for r in runs],
                           [_without_estimates(r, N, d) for r in runs], a)
    ang = np.max([np.nanmax(np.abs(r["joints"]), axis=0) for r in runs], axis=0)
    delta = math.pi / resolution + np.radians(
        np.spacing(np.float32(np.degrees(ang))).astype(float))
    from hapsim.analysis.pencil import MODE_FLOOR
    floor = MODE_FLOOR * float(np.linalg.norm(np.abs(J) @ delta))
    keep = [np.where(u[:, None], 1.0, 0.0) for u in own]
    rounding = [("reading", J, [k * delta for k in keep]),
                ("force", np.linalg.inv(J).T,
                 [k * 2.0 ** -24 * np.abs(r["torque"]) for k, r in zip(keep, runs)])]
    out = {}
    for name, errors in (("rounding", rounding),
                         ("estimated", [("reading", np.eye(2),
                                         [k * r.get("bounds", np.zeros(2))
                                          for k, r in zip(keep, runs)])])):
        w = wire_terms_records(sc, [r["position"] for r in runs], chk, order, errors,
                               usable=own, floor=floor)
        out[name] = {k: w[k] for k in ("felt_stiffness", "felt_damping")}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("falcon", "falcon-coverage", "haply2"))
    p.add_argument("--scene", default="configs/falcon_spring.yaml")
    p.add_argument("--draws", type=int, default=400)
    p.add_argument("--emulated", type=int, default=0)
    p.add_argument("--seeds", type=int, nargs="+", default=None)
    p.add_argument("--samples", type=int, default=300)
    p.add_argument("--offsets", type=int, default=5)
    p.add_argument("--loss", type=float, default=None)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    if args.seeds is None:
        args.seeds = list(range(20)) if args.what != "haply2" else list(range(1, 11))
    if args.loss is None:
        args.loss = 0.005 if args.what == "haply2" else 0.0
    t0 = time.process_time()
    out = {"falcon": falcon, "falcon-coverage": falcon_coverage, "haply2": haply2}[
        args.what](args)
    out["cpu_s"] = time.process_time() - t0
    out["command"] = command_line(__file__, argv)
    text = json.dumps(out, indent=1, default=float)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

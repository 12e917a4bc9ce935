"""What a Falcon run will state of the felt matrices, predicted before its loop
(:func:`hapsim.emulated.falcon_felt.felt_feasibility`, issues 29 and 31 item 4), agrees
with what the run states.

The prediction is the run's own statement on the run's own records (the emulated Falcon
in lockstep, named: deterministic; the wire's rounding term drawn with a fixed seed,
:mod:`hapsim.analysis.wire_rounding`). Before, it was the first-order term about the exact
records, which said "measurable" on configs/falcon_spring.yaml where the run, over the
errors' box, stated nothing. Here, the class: over seeded random spring fields on the
Falcon (:func:`tests.test_wire_box_devices._falcon_loop`: legs' inertia and friction, the
field's stiffness and damping drawn) and encoders from 4 times coarser than the
Falcon's to 22 times finer (drawn), what the prediction says is stated is what the
lockstep run states, statement by statement, and what it says is not stated the run
never says "within" or "differs" of; and the early stop of the box's sampling (which the
2DIY's and the pantograph firmware's terms still use) never changes which statements
are beyond a limit.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hapsim.kinematics import device
from hapsim.lockstep import LockstepND, excitation_starts, identification_plan, wire_terms_nd
from tests.test_wire_box_devices import _falcon_loop

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: Rows per record in the property tests (the shipped runs take the plan's 300; fewer
#: keep each loop's full box under a second).
N = 60


def _finer(monkeypatch, finer: float) -> int:
    """The emulated Falcon's encoder (and the driver's reading of it) ``finer`` times
    finer, its zero moved to 20 deg so that the legs' counts stay in the packets' int16
    (tests/test_falcon_spring.py's fixture); returns the decoder's plausible step."""
    import hapsim.drivers.falcon as falcon
    monkeypatch.setattr(falcon, "DEG_PER_TICK", falcon.DEG_PER_TICK / finer)
    monkeypatch.setattr(falcon, "THETA_OFFSET_DEG", 20.0)
    monkeypatch.setattr(falcon, "START_STEP", int(math.ceil(falcon.START_STEP * finer)))
    return int(math.ceil(8 * finer))


def _stated(v) -> list:
    return [s["name"] for s in v["statements"] if s["verdict"] != "not measurable"]


def test_the_prediction_is_what_the_lockstep_run_states(monkeypatch):
    """Seeded random spring fields, the encoder 4 times coarser than the Falcon's (its
    rounding term beyond the limit: nothing stated) and from the Falcon's own to 22 times
    finer (drawn; something stated): the prediction's statements are the lockstep run's
    (:func:`hapsim.emulated.falcon_felt.measure_felt_falcon` at the prediction's start,
    the rounding's draws seeded), name by name; a statement it says is not stated is "not
    measurable" in the run; its sentence before the run names them."""
    from hapsim.emulated.falcon_felt import felt_feasibility, measure_felt_falcon
    seen = {"measurable": 0, "not measurable": 0}
    for seed, finer in ((3, 0.25), (4, 2.0 ** np.random.default_rng(4).uniform(0.0, 4.5))):
        with monkeypatch.context() as mp:
            step = _finer(mp, finer)
            sc, _ = _falcon_loop(seed)
            plan = identification_plan(sc, N)
            f = felt_feasibility(sc, plan, max_step=step)
            run = measure_felt_falcon(sc, f["amplitude_m"], plan=plan, max_step=step)
        seen[f["verdict"]] += 1
        assert f["stated"] == _stated(run), (seed, finer, f["reason"], run["reason"])
        for st in run["statements"]:
            if st["name"] in f["not_stated"]:
                assert st["verdict"] == "not measurable", (seed, st)
        if f["not_stated"]:
            assert all(name in f["statement"] for name in f["not_stated"]) or not f["stated"]
            assert "predicted before the run" in f["statement"]
        else:
            assert f["statement"] is None
        if not f["stated"]:
            assert run["verdict"] == "not measurable", (seed, run["verdict"])
    assert seen["measurable"] >= 1 and seen["not measurable"] >= 1, seen


def test_the_box_stopped_early_answers_as_the_full_box():
    """Seeded random spring fields' exact records (no rounding), the errors half of a
    count 8 to 32 times finer than the Falcon's and half a motor command: at a limit
    drawn under every statement's full term (the sampling stops early) and one drawn
    among them (it cannot: some statement stays under), each statement is beyond the
    limit exactly when the full box's term is; the early terms are no larger than the
    full ones (a maximum over fewer points, each point the same); a complete sampling is
    the full one bit for bit."""
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    from hapsim.lockstep import beyond
    for seed in (1, 2):
        sc, rng = _falcon_loop(seed)
        plan = identification_plan(sc, N)
        chk, order, _ = plan
        a = float(rng.uniform(1e-3, 3.4e-3))
        recs = [LockstepND(sc, x0=x0, v0=v0).step(N, record=True)
                for x0, v0 in excitation_starts(3, a, sc.period)]
        diffs = [r - recs[0] for r in recs[1:]]
        J = device("delta", sc.device.geometry).jacobian(np.asarray(sc.device.joints))
        dq = math.radians(DEG_PER_TICK) / 2.0 / 2.0 ** rng.uniform(3, 5)
        errors = [("reading", J, np.full(3, dq)),
                  ("force", np.linalg.inv(J).T, np.full(3, TORQUE_PER_COUNT / 2.0))]
        full = wire_terms_nd(sc, diffs, chk, order, errors, box=True)
        terms = _terms(full)
        low = float(terms.min()) * rng.uniform(0.3, 0.95)
        mid = float(np.sort(terms)[terms.size // 2]) * rng.uniform(0.98, 1.02)
        for limit, early in ((low, True), (mid, False)):
            got = wire_terms_nd(sc, diffs, chk, order, errors, box=True, settle=limit)
            assert got["box_complete"] is (not early), (seed, limit)
            assert np.array_equal(_terms(got) > limit, terms > limit), (seed, limit)
            assert np.all(_terms(got) <= terms)
            if not early:
                assert np.array_equal(_terms(got), terms)
        # beyond(): the same question asked of the worst cases' layout
        wc = np.zeros(2 * 9 + 6)
        assert not beyond(chk, wc, 0.0).any() and beyond(chk, wc + np.inf, 0.0).all()


def _terms(w) -> np.ndarray:
    """A wire term's statements, relative: the two matrices, then each direction's."""
    d = w["directions"]
    return np.array([w["felt_stiffness"], w["felt_damping"]]
                    + list(d["felt_stiffness"]) + list(d["felt_damping"]))


def test_a_large_loop_says_before_the_run_that_it_is_not_measured():
    """configs/delta_mesh.yaml (162 states, more than a run computes the feasibility of):
    the prediction is "not measured" with the reason, and a sentence the run says before
    its loop; nothing is computed (no figures)."""
    from hapsim.pipeline.falcon_run import FEASIBILITY_STATES, felt_prediction
    from hapsim.scene import load_scene_nd
    p = felt_prediction(load_scene_nd(CONFIGS / "delta_mesh.yaml"))
    assert p["verdict"] == "not measured" and p["states"] > FEASIBILITY_STATES
    assert p["statement"].startswith("felt matrices not measured, said before the run")
    assert p["statement"].endswith(p["reason"]) and "worst" not in p


def test_a_run_never_makes_a_statement_its_prediction_excluded():
    """A run on the Falcon's own clock fits records its host's timing may have cut, whose
    term over the box differs from the complete lockstep records' the prediction took
    (:func:`hapsim.pipeline.falcon_run.felt_statement` passes the prediction's
    ``not_stated``): over random terms, deviations and exclusions (seeded), a statement
    excluded is "not measurable" with the exclusion's reason, every other statement is
    what it is without the exclusion, and the verdict is the conjunction of what is
    stated."""
    from hapsim.analysis.felt_matrices import FELT_QUANTITIES, felt_verdict
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.analysis.scene_check import check_scene_nd
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(CONFIGS / "falcon_spring.yaml")
    chk = check_scene_nd(sc)
    bound = linearisation_bound(sc, 1e-4, chk.render.rendered_poles)
    E = np.asarray(chk.render.directions, float)
    rng = np.random.default_rng(31)
    for _ in range(40):
        dev = {q: float(rng.uniform(0.0, 0.3)) for q in FELT_QUANTITIES}
        wire = {q: float(rng.uniform(0.0, 0.4)) for q in FELT_QUANTITIES}
        wire["directions"] = {q: list(rng.uniform(0.0, 0.4, 3)) for q in FELT_QUANTITIES}
        dirs = {"directions": [E[:, i] for i in range(3)], "damping_factor": [1.0] * 3,
                "largest": {q: 1.0 for q in FELT_QUANTITIES}}
        for q in FELT_QUANTITIES:
            dirs[q] = [{"predicted": 1.0, "measured": 1.0 + d, "deviation": abs(d)}
                       for d in rng.uniform(-0.3, 0.3, 3)]
        free = felt_verdict(dev, bound, wire, directions=dirs)
        names = [s["name"] for s in free["statements"]]
        out = [n for n in names if rng.random() < 0.3]
        got = felt_verdict(dev, bound, wire, directions=dirs,
                           excluded={n: "excluded before the run" for n in out})
        for a, b in zip(free["statements"], got["statements"]):
            if a["name"] in out:
                assert b["verdict"] == "not measurable"
                assert b["reason"] == "excluded before the run"
            else:
                assert b == a
        stated = [s for s in got["statements"] if s["verdict"] != "not measurable"]
        if not stated:
            assert got["verdict"] == "not measurable"
            if out:
                assert got["reason"].startswith("excluded before the run: ")
        elif any(s["verdict"] == "differs" for s in stated):
            assert got["verdict"] == "differs"
        else:
            assert got["verdict"] == ("partly within" if got["not_stated"] else "within")


def test_a_spring_field_not_at_rest_says_so_and_leaves_no_start():
    """configs/falcon_spring.yaml with its anchor moved 6 mm along z (the rest joints
    kept): the field pulls the handle away from the joints the scene names, and the
    record from rest alone drifts past 0.9 of the legs' envelope (3.8 mm at the handle).
    The prediction says why before any run ("not at rest at its joints"), with no start
    left; before, the start ignored the drift and, once it counted, a start of 0 divided
    by zero in the verdict. At 2 mm a start is left for the drift."""
    import dataclasses
    from hapsim.drivers.falcon import ENVELOPE_RAD
    from hapsim.emulated.falcon_felt import felt_feasibility
    from hapsim.lockstep import largest_start
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(CONFIGS / "falcon_spring.yaml")

    def moved(dz):
        return dataclasses.replace(sc, masses=[
            dataclasses.replace(m, x0=np.asarray(m.x0) + [0.0, 0.0, dz])
            if m.kind == "ground" else m for m in sc.masses])
    far = moved(6e-3)
    f = felt_feasibility(far)
    assert f["verdict"] == "not measurable" and f["amplitude_m"] == 0.0
    assert "not at rest at its joints" in f["reason"], f["reason"]
    assert "not at rest at its joints" in f["statement"]
    near = moved(2e-3)
    a, by, _ = largest_start(near, identification_plan(near)[2], ENVELOPE_RAD)
    assert by == "envelope" and 0.0 < a < largest_start(sc, identification_plan(sc)[2],
                                                          ENVELOPE_RAD)[0]

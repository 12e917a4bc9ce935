"""configs/falcon_spring.yaml: the Novint Falcon's felt matrices measured through its
counts (issue 29), where configs/delta_sphere.yaml's 0.5 mm contact leaves them "not
measurable" (tests/test_falcon_felt.py). At the Falcon's own counts the wire's rounding
term (the run's fit over draws of the encoders' phase through the loop,
:mod:`hapsim.analysis.wire_rounding`) states the felt stiffness, as a matrix and along
each principal direction, and tells a device with 30-45 % more leg inertia; the damping
stays not measurable.

A spring field (a 3-D spring-damper of rest length 0 from the handle to an anchor where
it rests) has no contact to open, so the hand's start is limited by the run's envelope
(:data:`hapsim.drivers.falcon.ENVELOPE_RAD` at a leg), millimetres at the handle, about
100 encoder counts. The emulated Falcon runs on its lockstep clock here (named:
deterministic records, one period a packet), the hand starting each record
(:meth:`hapsim.emulated.falcon_device.FalconDevice.let_go`), its encoders' index at a
seeded sub-count offset (:class:`hapsim.emulated.falcon_device.FalconDevice`'s
``encoder_offset``: where the counts' edges fall, which the draws of the term take as
unknown); the prediction is the n-D loop's (:func:`hapsim.analysis.scene_check.
check_scene_nd`), the records the emulated legs' own physics
(:class:`hapsim.joint_device.LocalJointDeviceND`) read through the packets' whole counts.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: A firmware image the emulated loader accepts (any bytes: the emulator echoes them).
IMAGE = bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8))


@pytest.fixture(scope="module", autouse=True)
def _feasibility_once():
    """configs/falcon_spring.yaml's feasibility computed once for the module's four
    askers (this module's fixture, a real Falcon's statement, `hapsim run`'s prediction
    twice): tests/falcon_memo.py, each a copy of exactly what it computed alone."""
    from tests.falcon_memo import feasibility_once
    with feasibility_once():
        yield


@pytest.fixture(scope="module")
def spring(_feasibility_once):
    """configs/falcon_spring.yaml, its identification plan and its feasibility."""
    from hapsim.emulated.falcon_felt import felt_feasibility
    from hapsim.lockstep import identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(CONFIGS / "falcon_spring.yaml")
    plan = identification_plan(sc)
    return sc, plan, felt_feasibility(sc, plan)


def _comments() -> str:
    text = (CONFIGS / "falcon_spring.yaml").read_text()
    return " ".join(line.split("#", 1)[1].strip() for line in text.splitlines()
                    if line.startswith("#"))


def _heavier(sc, factor):
    return replace(sc, device=replace(sc.device,
                                      joint_inertia=sc.device.joint_inertia * factor))


def _stated_within(r):
    """Every statement made (not "not measurable") is within its stated uncertainty."""
    for st in r["statements"]:
        if st["verdict"] != "not measurable":
            assert st["verdict"] == "within", st
            assert st["deviation"] <= st["uncertainty"], st


def test_the_figures_in_its_comments(spring):
    """The comments' figures, each recomputed: the largest start the envelope allows
    (3.8 mm, ~95 counts), the draws' largest change of the felt stiffness there (0.083)
    and the term stated, 1.5 times it (0.12, below the 0.25 a statement allows: the
    feasibility says the stiffness is stated), the first-order worst case over every sign
    (0.19), the damping's largest change (0.93: never stated), the stiffness limit along
    the lightest mass axis (2029 N/m, 1000 N/m being 0.5 of it), and the loop stable with
    one period more of delay (a lost packet's hold: the records do not grow when the link
    loses bytes)."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.analysis.scene_check import check_scene_nd
    from hapsim.analysis.wire_rounding import ROUNDING_DRAWS, ROUNDING_MARGIN
    sc, plan, f = spring
    c = _comments()
    assert f["verdict"] == "measurable" and "envelope" in f["limited_by"]
    assert "felt stiffness" in f["stated"] and "felt damping" in f["not_stated"]
    assert f["statement"].startswith("felt matrices partly measurable")
    assert "measures and states the felt stiffness" in c
    a = f["amplitude_m"]
    counts = f["reason"].split(" mm, about ")[1].split(" counts")[0]
    assert f"({a * 1e3:.1f} mm here, about {counts}" in c
    lo, hi = f["count_at_handle_m"]
    assert f"counts of {lo * 1e6:.0f}-{hi * 1e6:.0f} um" in c
    rd, w = f["lockstep"]["rounding"], f["lockstep"]["wire"]
    assert rd["draws"] == ROUNDING_DRAWS and f"drawn at {ROUNDING_DRAWS} phases" in c
    big_k, big_b = rd["largest"]["felt_stiffness"], rd["largest"]["felt_damping"]
    assert f"stiffness by {big_k:.3f} of itself at most" in c
    assert f"states {ROUNDING_MARGIN:g} times that, {w['felt_stiffness']:.2f}" in c
    assert w["felt_stiffness"] <= MEASURABLE_WIRE
    assert f"the {MEASURABLE_WIRE:g} a statement allows" in c
    assert f"{f['worst']['felt_stiffness']:.2f} at first order" in c
    assert "damping is not measurable at any start" in c and w["felt_damping"] > MEASURABLE_WIRE
    assert f"the draws move it by {big_b:.2f}" in c
    lims = check_scene_nd(sc).stiffness_limits
    kmax = float(np.min(lims))
    K = sc.links[0].stiffness
    assert f"{K:g} N/m is {K / kmax:.1f} of the stiffness" in c and f"({kmax:.0f} N/m)" in c
    one_more = replace(sc, device=replace(sc.device, delay=sc.device.delay + 1))
    assert "stable with one period more of delay" in c
    assert check_scene_nd(one_more).stable


def _stiffness_stated(r):
    """The stiffness statements made: the matrix's and each principal direction's."""
    return [s for s in r["statements"]
            if "stiffness" in s["name"] and s["verdict"] != "not measurable"]


def test_a_matching_falcon_states_its_stiffness_within_and_never_differs(spring):
    """Seeded hand starts of 0.85-1 times the largest, the encoders' index at seeded
    sub-count offsets: the matching device is "partly within" (its felt stiffness stated,
    as a matrix and along the principal directions the rounding term allows, each within
    its stated uncertainty; the damping not measurable, its term beyond the limit) and
    never "differs"; the legs stay in the run's envelope."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.drivers.falcon import ENVELOPE_RAD
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(2029)
    for a in rng.uniform(0.85, 1.0, 2) * f["amplitude_m"]:
        r = measure_felt_falcon(sc, a, plan=plan, encoder_offset=rng.uniform(-0.5, 0.5, 3))
        assert r["missing"] == 0 and r["clamped"] == 0
        assert r["verdict"] == "partly within", (a, r["reason"])
        _stated_within(r)
        assert "felt stiffness" in [s["name"] for s in _stiffness_stated(r)]
        assert r["wire"]["felt_damping"] > MEASURABLE_WIRE
        assert "felt damping" in r["not_stated"]
        assert r["excursion_rad"] < ENVELOPE_RAD          # the run's envelope kept


def test_more_leg_inertia_differs_at_the_falcons_counts(spring):
    """At the Falcon's own counts and the largest start, a device whose legs carry 30 %
    more inertia, and 30-45 % more (seeded), "differs" in the felt stiffness beyond its
    stated uncertainty (measured at 3.77 mm, 30 % more: along the heaviest principal
    direction 0.155 off against 0.085 stated); the encoders' index at a seeded offset."""
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(30)
    a = f["amplitude_m"]
    for factor in (1.3, rng.uniform(1.3, 1.45)):
        r = measure_felt_falcon(sc, a, plant=_heavier(sc, factor), plan=plan,
                                encoder_offset=rng.uniform(-0.5, 0.5, 3))
        assert r["verdict"] == "differs", (factor, a, r["reason"])
        assert any(s["verdict"] == "differs" and s["deviation"] > s["uncertainty"]
                   for s in r["statements"] if "stiffness" in s["name"])


def test_the_run_states_what_its_prediction_says(spring):
    """`hapsim run --driver falcon`'s statement (:func:`hapsim.pipeline.falcon_run.
    felt_statement`): the 7 records through pyftdi and the emulated FT232R (lockstep by
    name), each from a hand's start, state what the prediction made before the run says
    they state (:func:`hapsim.pipeline.falcon_run.felt_prediction`: the same records,
    taken directly; the rounding's draws seeded, so the same term), statement by
    statement, the matching device within; what it excludes is "not measurable" with the
    prediction's reason; on a real Falcon (no image) "not measured", saying why."""
    import json
    from hapsim.pipeline.falcon_run import felt_statement
    sc, plan, f = spring
    s = felt_statement(sc, IMAGE, clock="lockstep", predicted=f)
    assert s["verdict"] == "partly within", s["reason"]
    assert len(s["records"]) == 2 * 3 + 1 and s["missing"] == 0
    stated = [st["name"] for st in s["statements"] if st["verdict"] != "not measurable"]
    assert stated == f["stated"]
    assert all(st["verdict"] == "within" for st in s["statements"]
               if st["name"] in stated)
    assert s["stated_before_run"] == f["statement"]
    json.dumps(s)
    real = felt_statement(sc)
    assert real["verdict"] == "not measured" and real["stated_before_run"]


def test_hapsim_run_says_before_its_loop_what_it_cannot_state(capsys, tmp_path):
    """`hapsim run configs/falcon_spring.yaml --driver falcon --firmware FILE --json` on
    the emulated Falcon, on its own clock (the wall clock: real time, as a user runs it):
    exit 0; on stderr, before anything of the loop, that the felt damping will not be
    stated at the Falcon's counts, with the reason; the felt matrices measured on the
    Falcon's clock, never "differs" (the matching device; a host so late that rows are
    cut states less, never more than the prediction); ``--json`` holds the sentence
    (``felt_matrices.stated_before_run``)."""
    import json
    from hapsim.cli import main
    fw = tmp_path / "falcon.bin"
    fw.write_bytes(IMAGE)
    argv = ["run", str(CONFIGS / "falcon_spring.yaml"), "--driver", "falcon",
            "--firmware", str(fw), "--packets", "40", "--json"]
    assert main(argv) == 0
    cap = capsys.readouterr()
    said = [x for x in cap.err.splitlines() if "predicted before the run" in x]
    assert len(said) == 1 and "felt matrices partly measurable" in said[0]
    assert "not stated: felt damping" in said[0]
    assert said[0].endswith("the run goes on (exit code 0: not a device fault)")
    felt = json.loads(cap.out)["felt_matrices"]
    assert felt["verdict"] != "differs", felt["reason"]
    assert "felt stiffness" in felt["stated"]
    made = [st["name"] for st in felt["statements"] if st["verdict"] != "not measurable"]
    assert set(made) <= set(felt["stated"])
    assert felt["stated_before_run"].startswith("felt matrices partly measurable")

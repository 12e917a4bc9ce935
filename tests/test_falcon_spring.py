"""configs/falcon_spring.yaml: the Novint Falcon's felt matrices measured through its own
counts (issue 29), where configs/delta_sphere.yaml's 0.5 mm contact leaves them "not
measurable" (tests/test_falcon_felt.py).

A spring field (a 3-D spring-damper of rest length 0 from the handle to an anchor where
it rests) has no contact to open, so the hand's start is limited by the run's envelope
(:data:`hapsim.drivers.falcon.ENVELOPE_RAD` at a leg), millimetres at the handle, about
100 encoder counts. The emulated Falcon runs on its lockstep clock here (named:
deterministic records, one period a packet), the hand starting each record
(:meth:`hapsim.emulated.falcon_device.FalconDevice.let_go`); the prediction is the n-D
loop's (:func:`hapsim.analysis.scene_check.check_scene_nd`), the records the emulated
legs' own physics (:class:`hapsim.joint_device.LocalJointDeviceND`) read through the
packets' whole counts.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: A firmware image the emulated loader accepts (any bytes: the emulator echoes them).
IMAGE = bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8))


@pytest.fixture(scope="module")
def spring():
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


def _no_stated_damping(r):
    """The damping is never stated on this scene (the feasibility's figures)."""
    assert all(s["verdict"] == "not measurable" for s in r["statements"]
               if "damping" in s["name"])


def _stated_within(r):
    """Every statement made (not "not measurable") is within its stated uncertainty."""
    for st in r["statements"]:
        if st["verdict"] != "not measurable":
            assert st["verdict"] == "within", st
            assert st["deviation"] <= st["uncertainty"], st


def test_the_figures_in_its_comments(spring):
    """The comments' figures, each recomputed: the largest start the envelope allows
    (3.8 mm, ~95 counts), the rounding's worst case there on the felt stiffness (0.19,
    below the 0.25 a statement allows) and on the damping (above it: never stated, the
    start already the largest), the stiffness limit along the lightest mass axis (2029 N/m,
    1000 N/m being 0.5 of it), and the loop stable with one period more of delay (a lost
    packet's hold: the records do not grow when the link loses bytes)."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.analysis.scene_check import check_scene_nd
    sc, plan, f = spring
    c = _comments()
    assert f["verdict"] == "measurable" and "envelope" in f["limited_by"]
    a = f["amplitude_m"]
    counts = f["reason"].split(" mm, about ")[1].split(" counts")[0]
    assert f"({a * 1e3:.1f} mm here, about {counts}" in c
    lo, hi = f["count_at_handle_m"]
    assert f"counts of {lo * 1e6:.0f}-{hi * 1e6:.0f} um" in c
    wk, wb = f["worst"]["felt_stiffness"], f["worst"]["felt_damping"]
    assert f"at most {wk:.2f} of itself" in c and wk <= MEASURABLE_WIRE
    assert f"the {MEASURABLE_WIRE:g} a statement allows" in c
    assert "damping is not measurable at any start" in c and wb > MEASURABLE_WIRE
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


def test_a_matching_falcon_states_the_stiffness_within_over_seeded_starts(spring):
    """Seeded hand starts of 0.85-1 times the largest: the matching device's felt
    stiffness is stated (along the heaviest principal direction at least: the records'
    own wire term on the whole matrix is ~0.3, above the exact records' 0.19) and within
    its stated uncertainty, everything stated is within, nothing "differs"; the damping
    is "not measurable", its wire term over the limit, as the feasibility's figures say."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.drivers.falcon import ENVELOPE_RAD
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(2029)
    for a in rng.uniform(0.85, 1.0, 2) * f["amplitude_m"]:
        r = measure_felt_falcon(sc, a, plan=plan)
        assert r["missing"] == 0 and r["clamped"] == 0
        assert r["verdict"] == "partly within", (a, r["reason"])
        assert _stiffness_stated(r), (a, r["reason"])
        _stated_within(r)
        assert "felt damping" in r["not_stated"]
        assert r["wire"]["felt_damping"] > MEASURABLE_WIRE
        assert r["excursion_rad"] < ENVELOPE_RAD          # the run's envelope kept


def test_a_falcon_with_more_leg_inertia_differs(spring):
    """The same records from a device whose legs carry 30 % more inertia than the scene
    states, and 30-45 % more (seeded), each from a seeded start of 0.9-1 times the
    largest: "differs", the felt stiffness along the heaviest principal direction beyond
    its stated uncertainty (0.15-0.22 off against 0.12-0.13 stated; at 20-25 % more it is
    0.10-0.13 off, inside the uncertainty: "partly within", measured on this scene)."""
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(30)
    for factor in (1.3, rng.uniform(1.3, 1.45)):
        a = rng.uniform(0.9, 1.0) * f["amplitude_m"]
        r = measure_felt_falcon(sc, a, plant=_heavier(sc, factor), plan=plan)
        assert r["verdict"] == "differs", (factor, a, r["reason"])
        assert any(s["verdict"] == "differs" and s["deviation"] > s["uncertainty"]
                   for s in r["statements"] if "stiffness" in s["name"])
        _no_stated_damping(r)


def test_the_run_measures_them_on_the_emulated_falcon_only(spring):
    """`hapsim run --driver falcon`'s statement (:func:`hapsim.pipeline.falcon_run.
    felt_statement`): on the emulated Falcon (lockstep by name) the 7 records through
    pyftdi and the emulated FT232R, each from a hand's start, measured: the stiffness
    within, nothing missing, the JSON-able summary; on a real Falcon (no image) "not
    measured", saying why."""
    import json
    from hapsim.pipeline.falcon_run import felt_statement
    sc, plan, f = spring
    s = felt_statement(sc, IMAGE, clock="lockstep")
    assert s["verdict"] == "partly within", s["reason"]
    assert len(s["records"]) == 2 * 3 + 1 and s["missing"] == 0 and s["late_rows"] == 0
    assert s["amplitude_m"] == f["amplitude_m"]
    assert _stiffness_stated(s)
    _stated_within(s)
    json.dumps(s)
    real = felt_statement(sc)
    assert real["verdict"] == "not measured" and "real Falcon" in real["reason"]


def test_hapsim_run_prints_the_measured_felt_matrices(capsys, tmp_path):
    """`hapsim run configs/falcon_spring.yaml --driver falcon --firmware FILE` on the
    emulated Falcon, on its own clock (the wall clock: real time, as a user runs it):
    exit 0, the seven records' account printed (the start, the rows missing and after a
    host stall, both cut), each felt quantity's deviation and stated uncertainty, and a
    verdict that is never "differs" of the scene's own device (a loaded machine's stalls
    may cut the records to "not measurable": then said)."""
    from hapsim.cli import main
    fw = tmp_path / "falcon.bin"
    fw.write_bytes(IMAGE)
    assert main(["run", str(CONFIGS / "falcon_spring.yaml"), "--driver", "falcon",
                 "--firmware", str(fw), "--packets", "40"]) == 0
    out = capsys.readouterr().out
    assert "felt matrices measured: 7 records of the hand let go 3.77 mm from rest" in out
    assert "    felt stiffness: measured - predicted " in out
    assert "    felt damping: measured - predicted " in out
    line = next(x for x in out.splitlines() if x.startswith("  felt matrices: "))
    assert line.split(": ")[1] in ("partly within", "within", "not measurable"), line

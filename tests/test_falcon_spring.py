"""configs/falcon_spring.yaml: the Novint Falcon's felt matrices measured through its
counts (issue 29), where configs/delta_sphere.yaml's 0.5 mm contact leaves them "not
measurable" (tests/test_falcon_felt.py). At the Falcon's own counts the wire's term over
the error box (hapsim.analysis.wire_box) states nothing here either; an encoder 10 times
finer states the stiffness and tells a heavier device.

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
    (3.8 mm, ~95 counts), the rounding's first-order worst case about the exact records
    there on the felt stiffness (0.19, below the 0.25 a statement allows) and on the
    damping (above it: never stated, the start already the largest), the feasibility's
    verdict on the run's own records over the error box (nothing stated: every statement
    beyond the limit, said before the run), the stiffness limit along the lightest mass
    axis (2029 N/m, 1000 N/m being 0.5 of it), and the loop stable with one period more of
    delay (a lost packet's hold: the records do not grow when the link loses bytes)."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.analysis.scene_check import check_scene_nd
    sc, plan, f = spring
    c = _comments()
    assert f["verdict"] == "not measurable" and "envelope" in f["limited_by"]
    assert f["stated"] == [] and f["statement"].startswith("felt matrices not measurable")
    assert "says before its loop that nothing will be stated" in c
    a = f["amplitude_m"]
    counts = f["reason"].split(" mm, about ")[1].split(" counts")[0]
    assert f"({a * 1e3:.1f} mm here, about {counts}" in c
    lo, hi = f["count_at_handle_m"]
    assert f"counts of {lo * 1e6:.0f}-{hi * 1e6:.0f} um" in c
    wk, wb = f["worst"]["felt_stiffness"], f["worst"]["felt_damping"]
    assert f"by {wk:.2f} of itself at first order" in c and wk <= MEASURABLE_WIRE
    assert f"the {MEASURABLE_WIRE:g} a statement allows" in c
    w = f["lockstep"]["wire"]
    assert min(w["felt_stiffness"], *w["directions"]["felt_stiffness"]) > MEASURABLE_WIRE
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


#: How much finer than the Falcon's the emulated encoder of :func:`finer_counts` is: at
#: its own counts nothing is stated over the error box; 10 times finer the stiffness is.
FINER = 10


@pytest.fixture
def finer_counts(monkeypatch):
    """The emulated Falcon's encoder (and the driver's reading of it) :data:`FINER` times
    finer, its zero moved to 20 deg so that the legs' counts (15-25 deg, 0.1 rad of
    envelope) stay in the packets' int16, the decoder's first plausible step scaled with
    the count (as tests/test_falcon_felt.py's). Returns the decoder's plausible step."""
    import hapsim.drivers.falcon as falcon
    monkeypatch.setattr(falcon, "DEG_PER_TICK", falcon.DEG_PER_TICK / FINER)
    monkeypatch.setattr(falcon, "THETA_OFFSET_DEG", 20.0)
    monkeypatch.setattr(falcon, "START_STEP", falcon.START_STEP * FINER)
    return 8 * FINER


def test_a_matching_falcon_is_never_differs_and_its_counts_state_nothing(spring):
    """Seeded hand starts of 0.85-1 times the largest: the matching device is never
    "differs"; the wire's term over the error box (hapsim.analysis.wire_box) is beyond the
    limit of a statement for the stiffness and the damping, as matrices and along every
    direction, so the verdict is "not measurable" with the reason. The first-order term at
    the records stated the stiffness along the heaviest direction (under 0.25), which
    errors within the counts' bounds move 2.2 times as far
    (tests/test_wire_box_devices.py): a "differs" built on it could be wrong."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.drivers.falcon import ENVELOPE_RAD
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(2029)
    for a in rng.uniform(0.85, 1.0, 2) * f["amplitude_m"]:
        r = measure_felt_falcon(sc, a, plan=plan)
        assert r["missing"] == 0 and r["clamped"] == 0
        assert r["verdict"] == "not measurable", (a, r["reason"])
        assert not any(s["verdict"] == "differs" for s in r["statements"])
        w, first = r["wire"], r["wire"]["first_order"]
        assert min(w["felt_stiffness"], *w["directions"]["felt_stiffness"]) > MEASURABLE_WIRE
        assert min(first["directions"]["felt_stiffness"]) <= MEASURABLE_WIRE
        assert "over the errors' box" in r["reason"]
        assert r["excursion_rad"] < ENVELOPE_RAD          # the run's envelope kept


def test_finer_counts_state_the_stiffness_and_more_leg_inertia_differs(spring, finer_counts):
    """The encoder 10 times finer than the Falcon's (the rest as the run: the emulated
    Falcon's records, the box's term), a seeded start of 0.9-1 times the largest: the
    matching device's stiffness is stated and within (the damping not measurable), and a
    device whose legs carry 30 % more inertia, and 30-45 % more (seeded), "differs" in the
    felt stiffness, beyond its stated uncertainty (measured at 3.4 mm, 30 % more: along two
    principal directions 0.11-0.16 off against 0.085-0.099 stated)."""
    from hapsim.emulated.falcon_felt import measure_felt_falcon
    sc, plan, f = spring
    rng = np.random.default_rng(30)
    a = rng.uniform(0.9, 1.0) * f["amplitude_m"]
    same = measure_felt_falcon(sc, a, plan=plan, max_step=finer_counts)
    assert same["verdict"] in ("within", "partly within"), (a, same["reason"])
    assert _stiffness_stated(same)
    _stated_within(same)
    for factor in (1.3, rng.uniform(1.3, 1.45)):
        r = measure_felt_falcon(sc, a, plant=_heavier(sc, factor), plan=plan,
                                max_step=finer_counts)
        assert r["verdict"] == "differs", (factor, a, r["reason"])
        assert any(s["verdict"] == "differs" and s["deviation"] > s["uncertainty"]
                   for s in r["statements"] if "stiffness" in s["name"])


def test_the_run_states_what_its_prediction_says(spring):
    """`hapsim run --driver falcon`'s statement (:func:`hapsim.pipeline.falcon_run.
    felt_statement`): the 7 records through pyftdi and the emulated FT232R (lockstep by
    name), each from a hand's start, state nothing over the error box at the Falcon's
    counts (never "differs"), which is what the prediction made before the run says
    (:func:`hapsim.pipeline.falcon_run.felt_prediction`: the same records, taken
    directly): the run does not measure them again and says the prediction's sentence;
    on a real Falcon (no image) "not measured", saying why."""
    import json
    from hapsim.pipeline.falcon_run import felt_statement, measure_felt_emulated
    sc, plan, f = spring
    m = measure_felt_emulated(sc, IMAGE, f["amplitude_m"], plan=plan, clock="lockstep")
    assert m["verdict"] == "not measurable", m["reason"]
    assert len(m["records"]) == 2 * 3 + 1 and m["missing"] == 0
    assert not any(st["verdict"] != "not measurable" for st in m["statements"])
    s = felt_statement(sc, IMAGE, clock="lockstep", predicted=f)
    assert s["verdict"] == "not measurable" and "records" not in s
    assert s["stated_before_run"] == f["statement"]
    json.dumps(s)
    real = felt_statement(sc)
    assert real["verdict"] == "not measurable" and real["stated_before_run"]


def test_hapsim_run_says_before_its_loop_what_it_cannot_state(capsys, tmp_path):
    """`hapsim run configs/falcon_spring.yaml --driver falcon --firmware FILE` on the
    emulated Falcon, on its own clock (the wall clock: real time, as a user runs it):
    exit 0; on stderr, before anything of the loop, that the felt matrices will not be
    stated at the Falcon's counts, with the reason; the report's felt matrices "not
    measurable" with the same reason, never "within" or "differs"; ``--json`` holds the
    sentence (``felt_matrices.stated_before_run``)."""
    import json
    from hapsim.cli import main
    fw = tmp_path / "falcon.bin"
    fw.write_bytes(IMAGE)
    argv = ["run", str(CONFIGS / "falcon_spring.yaml"), "--driver", "falcon",
            "--firmware", str(fw), "--packets", "40"]
    assert main(argv) == 0
    cap = capsys.readouterr()
    said = [x for x in cap.err.splitlines() if "predicted before the run" in x]
    assert len(said) == 1 and "felt matrices not measurable" in said[0]
    assert said[0].endswith("the run goes on (exit code 0: not a device fault)")
    line = next(x for x in cap.out.splitlines() if x.startswith("  felt matrices: "))
    assert line.startswith("  felt matrices: not measurable: "), line
    assert line.split(": ", 2)[2] in said[0]
    assert main(argv + ["--json"]) == 0
    felt = json.loads(capsys.readouterr().out)["felt_matrices"]
    assert felt["verdict"] == "not measurable" and felt["stated"] == []
    assert felt["stated_before_run"].startswith("felt matrices not measurable")

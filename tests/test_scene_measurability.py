"""Every shipped scene with a port measures what it states, or says before running what it
cannot measure and why (issue 31, item 4); the pre-run prediction of comparability
(hapsim/pipeline/precheck.py) agrees with what the run finds.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hapsim.pipeline.options import RunOptions
from hapsim.pipeline.precheck import predict_comparable
from hapsim.pipeline.runner import prepare_run, run_scene
from hapsim.scene import load_scene, parse_scene
from hapsim.scene import scene_dimension, scene_has_ports

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _with_port(dim: int) -> list:
    out = []
    for path in sorted(CONFIGS.glob("*.yaml")):
        if scene_dimension(path) != dim or scene_has_ports(path):
            continue
        if "kind: port" in path.read_text():
            out.append(path)
    return out


@pytest.mark.xdist_group("shipped_lockstep")
@pytest.mark.parametrize("path", _with_port(1), ids=lambda p: p.name)
def test_every_shipped_1d_scene_measures_or_says_so_before_running(path, shipped_lockstep_run):
    """In lockstep, in process: either a verdict with numbers (measured k, b, the stated
    interval, "within"), or the run said before the loop started (``on_precheck``) that it
    cannot measure, with the contact and the sample, and the report says the same. Never a
    silent "not comparable" after the fact. (The runs are shared with
    test_contact_verdict: conftest.shipped_lockstep_run.)"""
    rep, said = shipped_lockstep_run(path)
    m = rep["measured"]
    assert rep["exit_code"] == 0, path.name
    if "k" in m:
        assert not said, (path.name, said)
        assert math.isfinite(m["k"]) and math.isfinite(m["b"])
        assert m["k_interval"] > 0 and m["b_interval"] > 0
        assert m["within"] is True, (path.name, m.get("verdict"))
    else:
        assert m.get("comparable") is False, (path.name, m)
        assert len(said) == 1, (path.name, m.get("verdict"))
        assert said[0] == m["stated_before_run"]
        assert said[0].endswith(m["reason"])        # the same contact, the same sample
        assert f"contact '{m['open_contact']}'" in said[0]
        assert f"sample {m['first_open_sample']}" in said[0]
    if path.name == "string.yaml":                  # issue 31: made to measure
        assert "k" in m and m["within"] is True
        # measured 9.6e-14 relative (generic 4.1e-13), margin 2.4e6
        assert m["k"] == pytest.approx(rep["predicted"]["k"], rel=1e-6)
        # measured 3.5e-11 relative (generic 2.3e-10), margin 4300
        assert m["b"] == pytest.approx(rep["predicted"]["b"], rel=1e-6)


@pytest.mark.parametrize("path", _with_port(2) + _with_port(3), ids=lambda p: p.name)
def test_every_shipped_nd_scene_measures_in_lockstep(path):
    """2-D and 3-D: the lockstep run (``hapsim.api.run_nd``, what ``hapsim run SCENE
    --lockstep`` does) gives a verdict with numbers: every stated direction within."""
    from hapsim.api import run_nd
    r = run_nd(str(path))
    assert r.stable
    assert r.deviation is not None and all(
        v is None or math.isfinite(v) for v in r.deviation.values()), r.deviation
    assert r.within is True, (path.name, r.verdict, r.reason)
    assert r.statements and all(s["verdict"] == "within" for s in r.statements)


@pytest.mark.parametrize("path", [p for p in sorted(CONFIGS.glob("*.yaml"))
                                  if scene_has_ports(p)], ids=lambda p: p.name)
def test_every_shipped_scene_of_several_ports_measures_in_lockstep(path):
    """Several ports (docs/ports.md): the lockstep run (``hapsim run SCENE --lockstep``,
    each port its own device model) measures the felt matrices across the ports within
    the linear loop's round-off allowance (LinearisationBound.roundoff, derived there) of
    the prediction, on a stable loop: verdict "within"."""
    from hapsim.lockstep_ports import measure_felt_ports
    from hapsim.scene import load_scene_ports
    res = measure_felt_ports(load_scene_ports(path))
    assert res["predicted"].stable
    assert res["verdict"]["verdict"] == "within", res["verdict"]
    assert max(res["deviation"].values()) <= res["bound"].roundoff <= 1e-6


def test_string_preload_figures_of_its_comments():
    """configs/string.yaml's comment figures: the rest (hapsim.analysis.network.
    rest_position) and the pre-load of the three springs in series, and the smallest
    compression of the contact over the measured free response (the pre-run simulation)."""
    from hapsim.analysis.virtual_network import rest_position
    c = " ".join(line.split("#", 1)[1].strip()
                 for line in (CONFIGS / "string.yaml").read_text().splitlines() if "#" in line)
    for fig in ("2000/25 + 2000/26 = 156.9 N/m", "pre-load 0.136 N", "compressed 0.68 mm",
                "hand at -0.453 mm", "bead at +0.867 mm", "1141 samples",
                "smallest compression is 0.035 mm > 0"):
        assert fig in c, fig
    sc = load_scene(str(CONFIGS / "string.yaml"))
    kmid = 2000 / 25 + 2000 / 26
    assert round(kmid, 1) == 156.9
    pre = 0.002 / (1 / 300 + 1 / 200 + 1 / kmid)
    assert round(pre, 3) == 0.136 and round(pre / 200 * 1e3, 2) == 0.68
    assert round(rest_position(sc) * 1e3, 3) == round(-pre / 300 * 1e3, 3) == -0.453
    assert round(pre / kmid * 1e3, 3) == 0.867
    prep = prepare_run(sc, RunOptions(lockstep=True).check())
    res = predict_comparable(prep)
    assert res["comparable"] and res["samples"] == 1141
    assert res["closed_samples"] >= res["needed"]


# a 3-bead string held by the finger: the property test's scene (small, so each case is
# a short lockstep run); its threshold (the pre-load) and the hand's start are drawn
SMALL = """
rate_hz: 1000
masses:
  - {{name: left, kind: ground}}
  - {{name: s1, kind: mass, mass: 0.01}}
  - {{name: s2, kind: mass, mass: 0.01}}
  - {{name: s3, kind: mass, mass: 0.01}}
  - {{name: right, kind: ground}}
  - {{name: hand, kind: port}}
links:
  - {{name: hold, kind: spring_damper, between: [hand, left], stiffness: 300.0, damping: 0.5}}
  - {{name: seg1, kind: spring_damper, between: [left, s1], stiffness: 200.0, damping: 0.001}}
  - {{name: seg2, kind: spring_damper, between: [s1, s2], stiffness: 200.0, damping: 0.001}}
  - {{name: seg3, kind: spring_damper, between: [s2, s3], stiffness: 200.0, damping: 0.001}}
  - {{name: seg4, kind: spring_damper, between: [s3, right], stiffness: 200.0, damping: 0.001}}
  - {{name: pluck, kind: contact, between: [hand, s2], stiffness: 200.0, damping: 0.5, threshold: {thr!r}}}
device: {{mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}}
excitation: {{x0: {x0!r}}}
"""


def test_prediction_agrees_with_the_run_over_random_preloads_and_amplitudes():
    """Random pre-loads (threshold 0 to 0.6 mm) and amplitudes (x0 -5 to 5 mm) of a contact
    scene: the pre-run prediction (comparable or not, the contact and the sample) is what
    the lockstep run finds. Both cases must occur among the draws (seeded)."""
    rng = np.random.default_rng(31)
    seen = {True: 0, False: 0}
    for _ in range(16):
        thr = float(rng.uniform(0.0, 0.6e-3))
        x0 = float(rng.uniform(-5e-3, 5e-3))
        text = SMALL.format(thr=round(thr, 6), x0=round(x0, 6))
        prep = prepare_run(parse_scene(text), RunOptions(lockstep=True).check())
        pre = predict_comparable(prep)
        said = []
        rep = run_scene(parse_scene(text), transport="inprocess", lockstep=True,
                        handle_signals=False, on_precheck=said.append)
        m = rep["measured"]
        got = bool(m.get("comparable"))
        assert pre["comparable"] == got, (thr, x0, pre, m.get("verdict"))
        seen[got] += 1
        if got:
            assert "k" in m and m["within"] is True, (thr, x0, m.get("verdict"))
            assert not said
        else:
            assert said and pre["first_open_sample"] == m["first_open_sample"]
            assert pre["open_contact"] == m["open_contact"] == "pluck"
            assert pre["closed_samples"] == m["closed_samples"]
    assert seen[True] >= 3 and seen[False] >= 3, seen

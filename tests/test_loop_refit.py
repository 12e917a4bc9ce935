"""Known inputs taken out through the loop the record measures (issue 29, the wrong-verdict
class; :mod:`hapsim.pipeline.loop_refit`).

The Hapkit sketch cuts every force to one of 256 square-root levels: a known input the
measurement takes out as the loop's response to it. Through the *predicted* loop, a
device that differs from the scene keeps part of that response at the predicted poles,
which pulls the fitted pair toward the prediction; cut into stretches where a loaded
host's writes came late (the rows the host marks), the pull grew to 0.2 N s/m on a
0.3 N s/m hidden friction, with half-widths of 0.01-0.03 stated, and beside a
CPU-bound process the wall-clock test of a hidden friction
(tests/test_hapkit_serial_tick.py) said "within" 3 times in about 7 suite runs.

Here the THS is closed on a SIMULATED clock (the sketch on its own tick,
:func:`hapsim.emulated.hapkit_serial_board.hapkit_serial_offline_loop`; deterministic),
random paddles and loops of tests/test_unseen_holds.py, 3 to 15 random rows marked by the
host as its late writes are (cut out), and no hold the board mistimed: the record with
those cuts is still one free response of one loop. Before the change, on these seeds the
cut record's pair moved from the uncut one's by up to 10 of its stated half-widths.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hapsim.analysis.prediction import predict
from hapsim.drivers.hapkit_serial import RENDER_S
from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
from hapsim.pipeline.render_latency import timed_scene
from seeds import seeds  # same directory (prepend mode)
from test_unseen_holds import _measure, _random_case

pytestmark = pytest.mark.xdist_group("test_unseen_holds")


def _cut(cols, drv, seed):
    rng = np.random.default_rng(500 + seed)
    rows = rng.choice(cols["seq"][20:-5], size=int(rng.integers(3, 16)), replace=False)
    drv.mistimed_seqs = {int(s) for s in rows}
    drv.own_tick = seed % 4 == 1       # the unseen holds' search on a quarter of them
    return drv


@pytest.mark.parametrize("seed", seeds(range(8), kept=(0, 1, 2, 5)))
def test_a_device_that_differs_is_never_within_wherever_the_host_cut(seed, tmp_path):
    """A paddle with 0.3 N s/m of friction the scene does not state (even seeds) or 30 %
    more mass (odd ones): "differs" or not measurable, never "within"; the board's own
    loop's felt pair inside the stated half-widths of both records; and the cut record
    measures the pair the uncut record does, within the two records' stated half-widths
    and the fixed point's own settling (:data:`hapsim.pipeline.loop_refit.SETTLED` of the
    first measurements' half-widths, each way)."""
    from hapsim.pipeline.loop_refit import SETTLED
    prep, n, _ = _random_case(seed, tmp_path)
    dev = prep.scene.device
    wrong = (dataclasses.replace(dev, friction=dev.friction + 0.3) if seed % 2 == 0
             else dataclasses.replace(dev, mass=1.3 * dev.mass))
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, device=wrong)
    whole = _measure(prep, cols, drv)
    cut = _measure(prep, cols, _cut(cols, drv, seed))
    info = {q: (whole.get(q), cut.get(q)) for q in ("k", "b", "k_unc", "b_unc", "verdict",
                                                    "error", "loop_refit")}
    assert not str(cut.get("verdict")).startswith("measured = predicted"), info
    assert "k" in whole, info
    # what is felt: the board's own loop (its render latency, RENDER_S), its pole's pair
    # stated with the scene's mass as the measurement states it (k = m |s|^2, b = -2 m
    # Re s), inside the stated half-widths whatever latency the search picked (before
    # they were widened to the latency's bounds: up to ~100 half-widths off, the fixed
    # point's b at the picked latency, on these records)
    truth = predict(timed_scene(dataclasses.replace(prep.scene, device=wrong), RENDER_S))
    for m in (whole, cut):
        if "k" not in m:
            continue
        for q in ("k", "b"):
            felt = truth[q] * dev.mass / wrong.mass
            assert abs(m[q] - felt) <= m[f"{q}_interval"], (q, felt, info)
    if "k" not in cut:                  # not measurable, with its reason
        assert cut.get("error"), info
        return
    for q in ("k", "b"):
        first = sum(m.get("loop_refit", {}).get("first_unc", [0, 0])[q == "b"] for m in
                    (whole, cut))
        slack = cut[f"{q}_unc"] + whole[f"{q}_unc"] + SETTLED * first
        # (the fixed points settle to SETTLED of the first half-widths; a pair's
        # round-off floor: 1e-6 of it, the device search's own precision)
        assert abs(cut[q] - whole[q]) <= slack + 1e-6 * abs(whole[q]), (q, info)


@pytest.mark.parametrize("seed", [0, 1, 2, 5])
def test_a_matching_paddle_stays_within_wherever_the_host_cut(seed, tmp_path):
    """The paddle the scene states, the same cuts: within (the correction through the loop
    it measures changes nothing there but the fixed point's gain in the half-widths)."""
    prep, n, _ = _random_case(seed, tmp_path)
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n)
    m = _measure(prep, cols, _cut(cols, drv, seed))
    assert m.get("within") is True, {q: m.get(q) for q in (
        "k", "b", "k_unc", "b_unc", "verdict", "error", "loop_refit")}
    assert "loop_refit" in m


def test_a_loop_that_measures_nothing_says_why_in_the_error():
    """Near the loop the record measures, the fit may measure nothing (a heavily cut record
    with its damping corrected up decays below the level it counts cycles above: beside a
    load, "no device near the pair ... gives a measurement", no more said). The error now
    carries the fit's own reason at the last loop tried."""
    from hapsim.analysis.network import device_body
    from hapsim.analysis.prediction import prepare_scene
    from hapsim.pipeline.loop_refit import pair_of, through_measured_loop
    from hapsim.scene import load_scene
    scene = prepare_scene(load_scene("configs/hapkit_serial.yaml"))[0]
    mass = device_body(scene.device)[0]
    p0 = pair_of(scene, mass)
    why = "only 1.2 oscillation cycles above 5 x the fit's rms residual"

    def fit_at(device):
        p = pair_of(dataclasses.replace(scene, device=device), mass)
        if p[1] > p0[1] + 0.05:             # the record's damping: too few cycles there
            return {"error": why}
        return {"k": p[0], "b": p[1] + 0.1, "k_unc": 0.01, "b_unc": 0.002}
    out = through_measured_loop(scene, {"k": p0[0], "b": p0[1] + 0.1, "k_unc": 0.01,
                                        "b_unc": 0.002}, fit_at)
    assert "b" not in out and f"(there: {why})" in out["error"], out.get("error")


def _edge_case(seed):
    """A random framed spring-damper loop whose device has little or no friction, the
    device the record measures (no friction: on the edge of the devices a scene may
    state) and the correction's pull toward the loop it is taken through."""
    from hapsim.analysis.network import device_body
    from hapsim.analysis.prediction import prepare_scene
    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.loop import LoopModel
    from hapsim.pipeline.loop_refit import pair_of
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(900 + seed)
    rate = float(rng.choice([250.0, 500.0, 1000.0, 2000.0]))
    m = float(10 ** rng.uniform(-1.7, 0.3))
    b0 = 0.0 if seed % 2 == 0 else float(rng.uniform(0.0, 0.05))
    d = int(rng.integers(1, 3))
    B = float(rng.uniform(0.5, 4.0))
    km = stability_limit(LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d,
                                   hold="zoh"), B)
    K = float(rng.uniform(0.1, 0.7)) * km
    scene = prepare_scene(parse_scene(
        f"rate_hz: {rate}\nmasses:\n  - {{name: handle, kind: port}}\n"
        f"  - {{name: wall, kind: ground, x0: 0.0}}\nlinks:\n"
        f"  - {{name: spring, kind: spring_damper, between: [handle, wall], "
        f"stiffness: {K!r}, damping: {B!r}}}\n"
        f"device: {{mass: {m!r}, friction: {b0!r}, delay: {d}, hold: zoh, "
        f"force_limit: 1000.0}}\nexcitation: {{x0: 0.005}}\n"))[0]
    mass = device_body(scene.device)[0]
    # the record's device: the scene's (a matching one), or up to 40 % more or less
    # mass, without friction
    share = 1.0 if seed % 3 == 0 else float(rng.choice([rng.uniform(0.8, 0.95),
                                                        rng.uniform(1.05, 1.4)]))
    true = dataclasses.replace(scene.device, mass=share * m, friction=0.0)
    p_true = pair_of(dataclasses.replace(scene, device=true), mass)
    return scene, mass, p_true, float(rng.uniform(0.2, 0.8))


@pytest.mark.parametrize("seed", range(12))
def test_a_loop_without_friction_is_found_where_its_neighbours_need_a_negative_one(seed):
    """The fixed point of a record whose loop has no friction (a frictionless device, as
    a scene may state it, or a heavier or lighter one): the slopes' steps and Broyden's
    steps around it ask for pairs that only a negative friction renders, which no scene
    states. Before the change, ``device_at_pair`` found no device for the first slope's
    step (+k) and the measurement was lost ("no device near the pair ... gives a
    measurement"): a wall-clock fuzz (``python tools/verdict_fuzz.py --clock wall --cases 15
    --seed 7``: framed, Haply, Hapkit sketch, FireFader loops on the devices' own clocks)
    lost 17 of 150 verdicts so, 14 of them of a device with 30 % more mass. Now Newton's
    iterates halve a step to a negative friction, a slope steps the other way where +h
    has no device, and a Broyden step no fraction of which has one goes to the
    frictionless loop nearest it.

    The record here is synthetic and exact to first order: measured through the loop of
    pair ``p``, the pair is ``p* + c (p - p*)`` (the predicted loop's pull, ``c`` its
    share, module notes of :mod:`hapsim.pipeline.loop_refit`), ``p*`` the true loop's.
    The fixed point must be ``p*``, to its stated half-widths."""
    from hapsim.pipeline.loop_refit import pair_of, through_measured_loop
    scene, mass, p_true, c = _edge_case(seed)
    unc = np.abs(p_true) * 1e-4

    def fit_at(device):
        p = pair_of(dataclasses.replace(scene, device=device), mass)
        got = p_true + c * (p - p_true)
        return {"k": got[0], "b": got[1], "k_unc": unc[0], "b_unc": unc[1]}

    out = through_measured_loop(scene, fit_at(scene.device), fit_at)
    assert "k" in out, out.get("error")
    # (the fixed point settles to SETTLED = 0.1 of the half-widths; its gain widens them)
    assert abs(out["k"] - p_true[0]) <= out["k_unc"], (out["k"], p_true, out["k_unc"])
    assert abs(out["b"] - p_true[1]) <= out["b_unc"], (out["b"], p_true, out["b_unc"])

"""The default run records the free response while it says something (issue 29: a run's
verdict, measured as a user runs it): with a position sensor that has a step, until the
predicted envelope falls below the level the measurement counts cycles above, and one
cycle more (:func:`hapsim.pipeline.measure.informative_s`).

Below that level the record spans a few sensor steps, its quantisation error follows
the signal (Widrow & Kollar 2008, ch. 4-5) and the fit of the felt pair is biased by it:
on ``configs/firefader.yaml`` (0.39 mm counts) the ten cycles the default run took before
measured k 0.3-0.4 % high against a stated 0.5 %, and one run in ten beside two CPU-bound
processes said "differs" of the scene's own fader. Here the FireFader's firmware loop is
closed offline (:func:`hapsim.emulated.driver_mock.firefader_offline_loop`: lockstep by
name, deterministic) on random faders and springs.
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from hapsim.emulated.driver_mock import firefader_offline_loop
from hapsim.errors import UnstableConfigError
from hapsim.pipeline.measure import identify_run
from hapsim.pipeline.options import RunOptions
from hapsim.pipeline.runner import prepare_run
from hapsim.scene import load_scene

YAML = """rate_hz: 250
masses:
  - {{name: knob, kind: port}}
  - {{name: anchor, kind: ground, x0: 0.0}}
links:
  - {{name: spring, kind: spring_damper, between: [knob, anchor], stiffness: {K},
     damping: {B}}}
device:
  protocol: firefader
  mass: {m}
  friction: {b0}
  delay: 0.725
  hold: zoh
  force_limit: 0.38
excitation:
  x0: {x0}
"""


def _measure(prep, cols, drv, rows, trim=True):
    """The measurement of the record's first ``rows``; ``trim=False``: with its tail
    below the sensor's level (``informative_s`` infinite: the code before)."""
    c = {k: v[:rows] for k, v in cols.items()}
    tel = types.SimpleNamespace(wrapped=False, n=rows, head=rows, columns=lambda *a: c)
    return identify_run(dataclasses.replace(prep, pred=dict(prep.pred),
                                            informative_s=None if trim else float("inf")),
                        tel, None, driver=drv)


def _case(seed, tmp_path):
    """A random fader and spring whose loop is stable, oscillates and falls below the
    level within ten cycles (else its default record is the ten cycles, as before),
    prepared as ``hapsim run --driver firefader`` prepares it; and the ten cycles' rows."""
    rng = np.random.default_rng(seed)
    path = tmp_path / f"fader{seed}.yaml"
    for _ in range(200):
        K = float(rng.uniform(8.0, 25.0))
        path.write_text(YAML.format(K=K, B=float(rng.uniform(0.0, 0.15)),
                                    m=float(rng.uniform(0.04, 0.1)),
                                    b0=float(rng.uniform(0.05, 0.15)),
                                    x0=min(float(rng.uniform(0.008, 0.02)), 0.3 / K)))
        try:
            prep = prepare_run(load_scene(str(path)),
                               RunOptions(driver="firefader", rt_priority=0,
                                          handle_signals=False))
        except UnstableConfigError:
            continue
        if prep.pred.get("f0_hz"):
            ten = int(round((10.0 / prep.pred["f0_hz"]) * prep.scene.rate_hz))
            if prep.n_window < ten:
                return prep, ten
    raise AssertionError("no fader of 200 drawn has a default record shorter than ten "
                         "cycles")


@pytest.mark.parametrize("seed", range(6))
def test_the_default_record_keeps_what_the_response_says_and_no_more(seed, tmp_path):
    """The default record holds the cycles the ten-cycle one held (at least 98 % of them:
    what it leaves out is below the level cycles are counted above), and is within; the
    ten-cycle record, as a user's longer ``--duration`` gives it, is measured over its
    informative head (the rows past it left out and counted) and is within too. (The
    tail's bias has no fixed sign over random faders: on the shipped one it is k high,
    the test below.)"""
    prep, ten = _case(seed, tmp_path)
    cols, drv, _ = firefader_offline_loop(prep.scene, ten)
    short, full = (_measure(prep, cols, drv, n) for n in (prep.n_window, ten))
    assert full.get("within") is True and full.get("tail_left_out", 0) > 0, full
    info = {q: (short.get(q), full.get(q)) for q in ("k", "k_unc", "b", "b_unc", "cycles",
                                                      "verdict")}
    assert short.get("within") is True, info
    assert short["cycles"] >= 0.98 * full["cycles"], info


def test_the_shipped_fader_is_measured_as_predicted_at_its_default_length():
    """``configs/firefader.yaml``: the default record (1.96 s, ten cycles were 3.61 s)
    measures k within a tenth of its stated uncertainty of the prediction; the ten-cycle
    record measured it more than half of it high (0.048 of 0.083 N/m)."""
    prep = prepare_run(load_scene("configs/firefader.yaml"),
                       RunOptions(driver="firefader", rt_priority=0, handle_signals=False))
    ten = int(round((10.0 / prep.pred["f0_hz"]) * prep.scene.rate_hz))
    cols, drv, _ = firefader_offline_loop(prep.scene, ten)
    short, full = (_measure(prep, cols, drv, n) for n in (prep.n_window, ten))
    # measured 0.12 of the stated uncertainty (deterministic, offline), margin 1.7
    assert abs(short["k"] - prep.pred["k"]) <= 0.2 * short["k_unc"], short
    # the ten cycles, as a user's --duration gives them: the tail below the level left
    # out (hapsim.pipeline.measure.informative_s), the default record's measurement; with
    # the tail in, k measured 0.58 of its stated uncertainty high (the bias the tail adds)
    assert full["tail_left_out"] == ten - prep.n_window, full
    assert (full["k"], full["b"]) == (short["k"], short["b"]), (full, short)
    whole = _measure(prep, cols, drv, ten, trim=False)
    assert whole["k"] - prep.pred["k"] >= 0.4 * whole["k_unc"], whole   # margin 1.45

"""``predict(scene, limit=False)``: the render-latency search's predictions leave out the
stiffness limit (the report's K_max, two thirds of a prediction's time; the search and its
spread predict at ~20 latencies a run and read the pair and the stability only). Every
other field is the whole prediction's, bit for bit, and the run's own prediction keeps
its limit."""

from __future__ import annotations

import glob
import math

import pytest

from hapsim.analysis.prediction import predict, prepare_scene, timed_scene
from hapsim.errors import ConfigError
from hapsim.scene import load_scene


def _one_d_scenes():
    out = []
    for path in sorted(glob.glob("configs/*.yaml")):
        try:
            scene = load_scene(path)
        except ConfigError:                 # a 2-D / 3-D or a two-port scene
            continue
        if scene.device is not None:
            out.append(path)
    return out


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a.hex() == b.hex() if not (math.isnan(a) and math.isnan(b)) else True
    return a == b


@pytest.mark.parametrize("path", _one_d_scenes())
def test_a_prediction_without_its_limit_is_the_whole_one_less_the_limit(path):
    """On every shipped 1-D scene, at its own delay and with a quarter period of render
    latency (its targets calibrated): the same keys, the same values to the bit,
    ``stiffness_limit`` None where the whole prediction has a number."""
    scene = prepare_scene(load_scene(path))[0]
    for at in (scene, timed_scene(scene, 0.25 * scene.period)):
        whole, part = predict(at), predict(at, limit=False)
        assert whole.keys() == part.keys()
        assert part["stiffness_limit"] is None
        assert whole["stiffness_limit"] is not None and whole["stiffness_limit"] > 0, path
        for q in whole:
            if q != "stiffness_limit":
                assert _same(whole[q], part[q]), (path, q, whole[q], part[q])


def test_the_runs_prediction_after_the_search_keeps_its_limit():
    """The shipped Hapkit sketch scene's run prediction (its driver's render latency
    searched, tests/test_unseen_holds.py's offline board): the prediction the report
    shows is the whole one at the latency found, its K_max included."""
    import types

    from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import identify_run, prepare_run
    prep = prepare_run(load_scene("configs/hapkit_serial.yaml"),
                       RunOptions(driver="hapkit-serial", rt_priority=0,
                                  handle_signals=False, duration=1.0))
    n = int(round(1.0 * prep.scene.rate_hz))
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n)
    tel = types.SimpleNamespace(wrapped=False, n=n, head=n, columns=lambda *a: cols)
    m = identify_run(prep, tel, None, driver=drv)
    assert "render_latency_s" in m, m.get("error")
    found = timed_scene(prep.scene, m["render_latency_s"])
    assert prep.pred["stiffness_limit"] == predict(found)["stiffness_limit"] > 0

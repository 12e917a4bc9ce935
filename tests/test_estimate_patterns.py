"""``hapsim.analysis.missing_replies`` (``tools/estimate_patterns.py`` charts it): the 1-D loop as a switched system over a request-reply
driver's fresh, estimated and skipped ticks. Its loop with every reading on time is an
implementation independent of :mod:`hapsim.analysis.stability` (a state matrix per tick
against the characteristic polynomial's damping limits), and the two must agree on where
the loop becomes unstable; the finding it was written for (configs/haply.yaml: sporadic
missing replies grow a loop ``check`` calls stable) is held here too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis.loop import LoopModel
from hapsim.analysis.stability import damping_limits

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("seed", range(6))
def test_every_reading_on_time_is_checks_loop_at_a_sub_sample_delay(seed):
    """The same at real delays of 0.3-3 periods: the split hold of the tick matrices
    against ``check``'s modified z-transform (:mod:`hapsim.analysis.subsample`), two
    implementations of the same loop, crossing 1 at the same damping to 1 %."""
    import hapsim.analysis.missing_replies as tool
    from hapsim.analysis.stability import stability_limit
    rng = np.random.default_rng(100 + seed)
    m, b0 = float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.0, 1.0))
    d, T = float(rng.uniform(0.3, 3.0)), 1e-3
    lm = LoopModel(mass=m, friction=b0, rate_hz=1.0 / T, delay=d, hold="zoh")
    K = stability_limit(lm, 0.0) / 3
    bmax = max(hi for _, hi in damping_limits(lm, K))
    below = tool.growth(tool.tick_matrices(m, b0, T, d, K, 0.99 * bmax), ["F"])
    above = tool.growth(tool.tick_matrices(m, b0, T, d, K, 1.01 * bmax), ["F"])
    assert below < 1.0 < above, (m, b0, d, K, bmax, below, above)


@pytest.mark.parametrize("seed", range(6))
def test_every_reading_on_time_is_checks_loop(seed):
    """Random devices, walls and delays 1-3: the state matrix of a fresh tick has its
    spectral radius cross 1 at ``check``'s upper damping limit (1 % either side: the
    limit is a simple root of the radius's crossing, found to 1e-12 by
    :func:`hapsim.analysis.stability.damping_limits`, and the radius moves by far more
    than its round-off, ~1e-15, over 1 % of B)."""
    import hapsim.analysis.missing_replies as tool
    rng = np.random.default_rng(seed)
    m, b0 = float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.0, 1.0))
    d, T = int(rng.integers(1, 4)), 1e-3
    lm = LoopModel(mass=m, friction=b0, rate_hz=1.0 / T, delay=d, hold="zoh")
    # a stiffness the loop holds over a range of damping (a third of the stiffness limit)
    from hapsim.analysis.stability import stability_limit
    K = stability_limit(lm, 0.0) / 3
    lims = damping_limits(lm, K)
    assert lims, (m, b0, d, K)
    bmax = max(hi for _, hi in lims)
    below = tool.growth(tool.tick_matrices(m, b0, T, d, K, 0.99 * bmax), ["F"])
    above = tool.growth(tool.tick_matrices(m, b0, T, d, K, 1.01 * bmax), ["F"])
    assert below < 1.0 < above, (m, b0, d, K, bmax, below, above)


def test_sporadic_missing_replies_grow_a_haply_loop_check_calls_stable():
    """configs/haply.yaml's joint at 0.9 of check's damping limit: two missing replies in
    eight, each stepped with today's extrapolated estimate, grow the loop (the switched
    system's product over the pattern has a spectral radius above 1 per tick), and the
    shipped damping (0.001 N m s/rad) holds every pattern the tool tries."""
    import hapsim.analysis.missing_replies as tool
    from hapsim.scene import load_scene
    sc = load_scene(str(ROOT / "configs" / "haply.yaml"))
    dev, lk = sc.device, sc.links[0]
    lm = LoopModel(mass=dev.mass, friction=dev.friction, rate_hz=sc.rate_hz,
                   delay=int(dev.delay), hold="zoh")
    bmax = max(hi for _, hi in damping_limits(lm, lk.stiffness))
    mats = tool.tick_matrices(dev.mass, dev.friction, sc.period, int(dev.delay),
                              lk.stiffness, 0.9 * bmax)
    assert tool.growth(mats, ["F"]) < 1.0
    assert tool.growth(mats, list("FF") + ["E1"] + list("FFF") + ["E1", "F"]) > 1.0
    shipped = tool.tick_matrices(dev.mass, dev.friction, sc.period, int(dev.delay),
                                 lk.stiffness, lk.damping)
    assert max(tool.growth(shipped, p) for p in tool.patterns(("E1", "E2"), 8)) < 1.0


def test_a_real_time_run_says_when_missing_replies_grow_its_loop(tmp_path):
    """``prepare_run`` of a Haply scene at 0.7 N m s/rad (between the 0.587 that sporadic
    missing replies hold and check's 0.828) warns, naming the pattern and its growth,
    and goes on (a warning, not a refusal); the shipped scene (0.001), the same scene in
    lockstep (a mock waits for each command: no reply is missing) and a framed wall (no
    request-reply driver) do not."""
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    text = (ROOT / "configs" / "haply.yaml").read_text()
    assert "damping: 0.001" in text
    path = tmp_path / "haply_damped.yaml"
    path.write_text(text.replace("damping: 0.001", "damping: 0.7"))

    def said(p, lockstep=False, driver="haply"):
        prep = prepare_run(load_scene(str(p)), RunOptions(driver=driver, lockstep=lockstep,
                                                          handle_signals=False))
        return prep.pred.get("missing_reply_warning"), prep.pred.get("missing_reply_unstable")

    w, u = said(path)
    assert w is not None and u["growth_per_tick"] > 1.0 and "E" in u["pattern"], (w, u)
    assert u["pattern"] in w and "go missing now and then" in w
    assert said(ROOT / "configs" / "haply.yaml") == (None, None)
    assert said(path, lockstep=True) == (None, None)
    assert said(ROOT / "configs" / "first_wall.yaml", driver=None) == (None, None)
    # the FireFader's knob (delay 0.725 periods and its board's render latency, a split
    # hold) at 0.9 of check's damping limit, and as shipped (0.1 N s/m)
    ff = (ROOT / "configs" / "firefader.yaml").read_text()
    assert "damping: 0.1}" in ff
    path = tmp_path / "firefader_damped.yaml"
    path.write_text(ff.replace("damping: 0.1}", "damping: 11.0}"))
    w, u = said(path, driver="firefader")
    assert w is not None and u["growth_per_tick"] > 1.0, (w, u)
    assert said(ROOT / "configs" / "firefader.yaml", driver="firefader") == (None, None)


def test_check_says_it_too(tmp_path):
    """``hapsim check --json`` of the same scenes: the board's ``missing_reply_unstable``
    and its warning for 0.7 N m s/rad (the verdict still "stable": a warning, as the run's),
    nothing for the shipped scene."""
    import json

    from inproc import hapsim_main  # same directory (pytest prepend import mode)
    text = (ROOT / "configs" / "haply.yaml").read_text()
    path = tmp_path / "haply_damped.yaml"
    path.write_text(text.replace("damping: 0.001", "damping: 0.7"))
    code, out, err = hapsim_main(["check", str(path), "--json"])
    assert code == 0, err
    rep = json.loads(out)
    bd = rep["board"]
    assert rep["stable"] and bd["missing_reply_unstable"]["growth_per_tick"] > 1.0, bd
    assert bd["missing_reply_unstable"]["pattern"] in bd["missing_reply_warning"]
    code, out, err = hapsim_main(["check", str(ROOT / "configs" / "haply.yaml"), "--json"])
    assert code == 0, err
    assert "missing_reply_unstable" not in (json.loads(out)["board"] or {})

"""``hapsim advise`` of a 2-D or 3-D scene (issue 30 item 2): the lowest rate of the ladder
whose felt matrices are within the tolerance of what the port links ask, ``(K, B + B0)``,
with the loop stable at ``(K, B) / margin``.

Checked against the 1-D analysis: a Cartesian device with two identical, uncoupled axes and
an isotropic spring feels on each axis the 1-D loop's pair, so the advised rate must be the
first rate at which the 1-D felt pair (``hapsim.check`` of the one-axis scene) is within
the tolerance and the 1-D loop stable at the margin: another code path (the 1-D network's
closed loop and its rendered pair), not the n-D one.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

import hapsim
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.loop_poles import closed_loop_poles
from hapsim.bench.advise import RATES, advise_scene, felt_pair_error
from hapsim.cli import main


def _scenes(m, b0, d, K, B):
    two = (f"dimension: 2\nrate_hz: 1000\nmasses:\n  - {{name: hand, kind: port}}\n"
           f"  - {{name: c, kind: ground, x0: [0.0, 0.0]}}\nlinks:\n"
           f"  - {{name: s, kind: spring_damper, between: [hand, c], stiffness: {K}, "
           f"damping: {B}}}\ndevice: {{kind: cartesian, mass: {m}, friction: {b0}, "
           f"position: [0.0, 0.0], delay: {d}}}\n")
    one = (f"rate_hz: 1000\nmasses:\n  - {{name: hand, kind: port}}\n"
           f"  - {{name: c, kind: ground, x0: 0.0}}\nlinks:\n"
           f"  - {{name: s, kind: spring_damper, between: [hand, c], stiffness: {K}, "
           f"damping: {B}}}\ndevice: {{mass: {m}, friction: {b0}, delay: {d}, hold: zoh}}\n")
    return two, one


@pytest.mark.parametrize("seed", range(6))
def test_two_uncoupled_axes_advise_the_1d_rate(tmp_path, seed):
    rng = np.random.default_rng(seed)
    m, b0, d = rng.uniform(0.05, 0.3), rng.uniform(0.2, 2), int(rng.integers(0, 3))
    K, B = rng.uniform(50, 400), rng.uniform(1, 5)
    tol = float(rng.choice([0.02, 0.05]))
    two, one = _scenes(m, b0, d, K, B)
    (tmp_path / "two.yaml").write_text(two)
    (tmp_path / "one.yaml").write_text(one)
    adv = advise_scene(hapsim.load_scene(str(tmp_path / "two.yaml")), tol, margin=0.95)
    base = hapsim.load_scene(str(tmp_path / "one.yaml"))
    expect = None
    for r in RATES:
        chk = hapsim.check(base.with_rate(r))
        err = felt_pair_error(chk.k, chk.b, K, B + b0)
        rho = float(np.max(np.abs(closed_loop_poles(LoopModel(m, b0, r, d, "zoh"),
                                                    K / 0.95, B / 0.95))))
        if err <= tol and rho < 1:
            expect = r
            break
    assert adv.ok == (expect is not None)
    assert adv.rate_hz == expect, (adv.rate_hz, expect, adv.reason)


def test_the_pantograph_spring_and_a_refusal(tmp_path):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["advise", "configs/pantograph_spring.yaml", "--json"])
    d = json.loads(out.getvalue())
    assert code == 0 and d["ok"] and d["integrator"] == "centred"
    assert d["error"] <= d["tolerance"]
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["advise", "configs/delta_mesh.yaml"]) == 2
    assert "links: a port link ends on the moving mass" in err.getvalue()

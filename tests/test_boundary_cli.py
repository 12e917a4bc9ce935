"""Wrong answers and tracebacks an independent model found (issue 22), each through the CLI
with its message and exit code."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from hapsim.cli import main

AT_REST = """rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
"""


def test_run_on_a_scene_at_rest_reports_no_measurement_and_why(tmp_path, capsys):
    """A scene without excitation is valid: exit 0, JSON intact, the measurement says the
    loop never moved (it raised ValueError: math domain error in measure_felt)."""
    f = tmp_path / "rest.yaml"
    f.write_text(AT_REST)
    rc = main(["run", str(f), "--lockstep", "--json", "--duration", "0.2"])
    out = capsys.readouterr().out
    assert rc == 0
    rep = json.loads(out)
    assert rep["measured"]["at_rest"] is True
    assert "never moved" in rep["measured"]["error"]
    assert "k" not in rep["measured"]


@pytest.mark.parametrize("offset", [False, True])
def test_measure_felt_on_a_constant_record_is_an_answer(offset):
    """The class behind it: any constant record (x0 = 0, no excitation, a loop resting at
    an offset) gives ``error`` and ``at_rest``, never an exception."""
    from hapsim.analysis.identify import measure_felt
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.loop_poles import closed_loop_poles
    z = closed_loop_poles(LoopModel(mass=0.1, friction=0.5), 1000.0, 1.5)
    felt = z[np.argmax(np.where(z.imag > 0, np.abs(z), -1))]
    y = np.full(500, 0.003 if offset else 0.0)
    for quantum in (0.0, 1e-5):
        res = measure_felt(y, 1e-3, 0.1, z[np.abs(z) > 0], felt, offset=offset,
                           quantum=quantum)
        assert res["at_rest"] and "never moved" in res["error"]


FELT_WALL = open("configs/felt_wall.yaml").read()
WALL = open("configs/wall.yaml").read()


def _string_damping(value: str) -> str:
    text = open("configs/string.yaml").read()
    return re.sub(r"(name: seg1, .*?damping: )[^,}]+", r"\g<1>" + value, text, count=1)


@pytest.mark.parametrize("name,text,line,key,what", [
    ("felt_k", FELT_WALL.replace("target: {k: 1000.0, b: 3.0}", "target: {k: 1e12, b: 3.0}"),
     None, "links[0].target.k", "k T^2/m"),
    ("felt_friction", re.sub(r"friction: 0\.5 ", "friction: 1e30 ", FELT_WALL), None,
     "device.friction", "b0 T/m"),
    ("wall_friction", re.sub(r"friction: 0\.5 ", "friction: 1e30 ", WALL), None,
     "device.friction", "b0 T/m"),
    ("string_damping", _string_damping("1e308"), None, "links[0].damping", "B T/m"),
])
def test_out_of_range_loop_products_are_refused_alike_by_every_command(
        tmp_path, capsys, name, text, line, key, what):
    """One validator (the scene's) for every command: check, simulate, run, family refuse a
    value whose loop product leaves the range with exit 2, one line naming file, line and
    key (simulate once ran a string with a segment's damping 1e308; a felt target's
    calibration named no file, line or key)."""
    f = tmp_path / f"{name}.yaml"
    f.write_text(text)
    want_line = next(i for i, ln in enumerate(text.splitlines(), 1)
                     if key.split(".")[-1].split("[")[0] in ln and (
                         "1e12" in ln or "1e30" in ln or "1e308" in ln))
    for argv in (["check", str(f)], ["simulate", str(f), "-n", "10", "--out",
                                      str(tmp_path / "x.npz")],
                 ["run", str(f), "--lockstep"], ["family", str(f)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert f"{f}:{want_line}: {key}: " in err and what in err, (argv, err)

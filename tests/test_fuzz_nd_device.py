"""Absurd but finite device values in a 2-D/3-D scene are refused with file, line and key,
never a later error without them (issue 31 item 6; the fuzz's class).

A hand_damping of 1e308 made the device's Cartesian friction inf: the reader passed it
(its product check compared NaN), and `hapsim check` failed later with "friction: must be
finite", no file, no line.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from hapsim.cli import main

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"error: .+\.yaml:\d+: device\.[a-z_]+")


@pytest.mark.parametrize("scene, anchor", [
    ("pantograph_wall.yaml", "hand_mass: 0.05, delay: 1}"),
])
def test_huge_device_values_are_refused_with_file_line_and_key(scene, anchor, tmp_path,
                                                              capsys):
    """Property over seeded exponents 1e30..1e308 for hand_damping, hand_mass and the
    joint friction's diagonal: `check` either runs (exit 0) or refuses with exit 2 and
    'FILE:LINE: device.KEY'; never another exit, never a traceback."""
    text = (ROOT / "configs" / scene).read_text()
    assert anchor in text
    rng = np.random.default_rng(31)
    seen = {0: 0, 2: 0}
    # the fuzz's value and the double range's edge first (only there does the mapped
    # friction overflow: below, the product rule refuses it), then seeded exponents
    fixed = ["1.0e308", "1.7e308", "1.0e308"]
    for i in range(15):
        e = float(rng.uniform(30.0, 308.0))
        v = fixed[i] if i < len(fixed) else f"{10.0 ** (e - int(e)):.3f}e{int(e)}"
        which = ("hand_damping", "hand_mass", "joint_friction")[i % 3]
        if which == "joint_friction":
            t = text.replace("joint_friction: [1.0e-3, 1.0e-3]", f"joint_friction: [{v}, {v}]")
            assert t != text
        else:
            t = text.replace(anchor, anchor.replace("hand_mass: 0.05",
                                                    f"hand_mass: 0.05, {which}: {v}")
                             if which == "hand_damping" else
                             anchor.replace("hand_mass: 0.05", f"hand_mass: {v}"))
        path = tmp_path / f"s{i}.yaml"
        path.write_text(t)
        code = main(["check", str(path)])
        err = capsys.readouterr().err
        assert code in (0, 2), (which, v, code, err)
        assert "Traceback" not in err
        if code == 2:
            assert LINE.search(err), (which, v, err)
        seen[code] += 1
    assert seen[2] > 0

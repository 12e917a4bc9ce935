"""Joint angles beyond one turn are refused (issue 23, item 3: workspace limits refused with
a clear error): the audit found ``hapsim kinematics pantograph --joints 1e308 50`` and a
delta at (200, 200, 200) deg taken. A revolute joint's angle is periodic, so one turn
either way loses nothing; beyond it the value is a mistake, and past ~1e16 rad its sine
has no correct digit. Checked over random angles against the periodic identity, through
the classes, the vectorised map, the CLI and the scene reader."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapsim.errors import ConfigError, KinematicsError
from hapsim.kinematics import JOINT_TURN, device

_OUT = st.floats(min_value=JOINT_TURN * (1 + 1e-12), max_value=1e308,
                 allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(big=_OUT, sign=st.sampled_from((-1.0, 1.0)), which=st.integers(0, 1))
def test_pantograph_beyond_one_turn_is_refused(big, sign, which):
    pan = device("pantograph", "haply")
    q = [math.radians(130.0), math.radians(50.0)]
    q[which] = sign * big
    for f in (pan.forward, pan.jacobian):
        with pytest.raises(ConfigError) as exc:
            f(q)
        assert exc.value.key == "joints" and "one turn" in str(exc.value)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(big=_OUT, which=st.integers(0, 2))
def test_delta_beyond_one_turn_is_refused(big, which):
    dlt = device("delta", "falcon")
    q = [0.3, 0.3, 0.3]
    q[which] = big
    with pytest.raises(ConfigError) as exc:
        dlt.forward(q)
    assert exc.value.key == "joints" and "one turn" in str(exc.value)
    with pytest.raises(ConfigError):
        dlt.forward_many(np.array([q]))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(q1=st.floats(math.radians(100), math.radians(160)),
       q2=st.floats(math.radians(20), math.radians(80)))
def test_within_one_turn_the_periodic_angle_is_the_same_pose(q1, q2):
    """The limit refuses nothing a turn can give: ``q - 2 pi`` (inside the turn) is the
    same pose as ``q`` to round-off (the closed form is periodic)."""
    pan = device("pantograph", "haply")
    try:
        p = pan.forward([q1, q2])
    except KinematicsError:
        return
    p2 = pan.forward([q1 - 2 * math.pi, q2 - 2 * math.pi])
    # measured 7.1e-17 abs, 3.1e-14 rel (generic 7.1e-17, 3.1e-14), margin 14000
    assert np.allclose(p, p2, rtol=0, atol=1e-12)


@pytest.mark.parametrize("argv", [
    ["kinematics", "pantograph", "--joints", "1e308", "50", "--json"],
    ["kinematics", "pantograph", "--joints", "130", "-361", "--json"],
    ["kinematics", "delta", "--joints", "400", "20", "30", "--json"],
])
def test_cli_refuses_beyond_one_turn(argv, capsys):
    from hapsim.cli import main
    import json
    assert main(argv) == 2
    err = json.loads(capsys.readouterr().out)["error"]      # --json: the error as JSON
    assert err["key"] == "joints" and "one turn" in err["message"]
    assert main(argv[:-1]) == 2                              # and in words on stderr
    cap = capsys.readouterr()
    assert cap.out == "" and "one turn" in cap.err and "joints" in cap.err


def test_scene_reader_refuses_beyond_one_turn(tmp_path):
    """A scene's ``device.joints`` beyond one turn: refused naming the file, line and key."""
    from pathlib import Path

    from hapsim.scene import load_scene_nd
    src = Path(__file__).resolve().parents[1] / "configs" / "pantograph_wall.yaml"
    text = src.read_text()
    import re
    new, n = re.subn(r"(joints:\s*\[)\s*[-0-9.eE+]+", r"\g<1>1e308", text, count=1)
    assert n == 1, "the scene's joints line moved"
    f = tmp_path / "far.yaml"
    f.write_text(new)
    with pytest.raises(ConfigError) as exc:
        load_scene_nd(f)
    msg = str(exc.value)
    assert "joints" in msg and "far.yaml" in msg and "one turn" in msg

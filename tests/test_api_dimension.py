"""``hapsim.load_scene`` reads a scene in the dimension its ``dimension`` key declares
(issue 23): a 1-D scene exactly as before (the 1-D reader's Scene), a 2-D or 3-D one as
the n-D reader's SceneND; check and run take every dimension (issue 30), family refuses
an n-D scene by name."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import hapsim
from hapsim.errors import ConfigError
from hapsim.scene import Scene
from hapsim.scene import load_scene as load_1d
from hapsim.scene import (SceneND, ScenePorts, load_scene_nd, load_scene_ports, scene_dimension,
                          scene_has_ports)

CONFIGS = sorted((Path(__file__).resolve().parent.parent / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_load_scene_picks_the_dimension(path):
    """Every shipped scene: the type follows the file's dimension, and the result equals
    the dimension's own reader's."""
    s = hapsim.load_scene(path)
    if scene_has_ports(path):                   # several ports: tests/test_ports.py
        assert type(s) is ScenePorts and s == load_scene_ports(path) and s.dimension == 1
    elif scene_dimension(path) == 1:
        assert type(s) is Scene and s == load_1d(str(path)) and s.dimension == 1
    else:
        assert type(s) is SceneND
        np.testing.assert_equal(dataclasses.asdict(s), dataclasses.asdict(load_scene_nd(path)))
        assert s.dimension == scene_dimension(path) in (2, 3)


def test_check_and_run_take_every_dimension():
    """hapsim.check and hapsim.run take a 2-D or 3-D scene (path or object; issue 30: "the
    same API function takes a 1-D, a 2-D, a 3-D scene"): their results are the n-D
    functions' (check_nd with a port, modes_nd without one, run_nd in lockstep), to the
    bit (the same computation); a 1-D scene gets the 1-D reports as before."""
    root = Path(__file__).resolve().parent.parent / "configs"
    p = root / "pantograph_wall.yaml"
    for scene in (p, hapsim.load_scene(p)):
        assert hapsim.check(scene).to_dict() == hapsim.check_nd(scene).to_dict()
    m = root / "membrane.yaml"
    assert hapsim.check(m).to_dict() == hapsim.modes_nd(m).to_dict()
    r = hapsim.run(p, lockstep=True)
    assert type(r) is hapsim.RunReportND
    assert r.to_dict() == hapsim.run_nd(p).to_dict()
    assert type(hapsim.check(root / "wall.yaml")) is hapsim.CheckReport


def test_what_an_n_d_run_does_not_take_is_refused_by_name():
    """A 1-D run option on a 2-D scene, a driver from Python, an amplitude on a 1-D
    scene, and family (no n-D family yet): ConfigError naming the option."""
    root = Path(__file__).resolve().parent.parent / "configs"
    p = root / "pantograph_wall.yaml"
    with pytest.raises(ConfigError, match="duration") as e:
        hapsim.run(p, duration=1.0)
    assert e.value.key == "duration"
    with pytest.raises(ConfigError, match="command line") as e:
        hapsim.run(p, driver="haply")
    assert e.value.key == "driver"
    with pytest.raises(ConfigError) as e:
        hapsim.run(root / "wall.yaml", amplitude=1e-3)
    assert e.value.key == "amplitude"
    with pytest.raises(ConfigError, match="family") as e:
        hapsim.family(p)
    assert e.value.key == "dimension"


def test_a_bad_dimension_is_the_n_d_reader_s_error(tmp_path):
    """dimension: 4 is refused with the file, line and key (the n-D reader's message)."""
    f = tmp_path / "four.yaml"
    f.write_text("dimension: 4\nrate_hz: 1000\nmasses: []\nlinks: []\n")
    with pytest.raises(ConfigError) as e:
        hapsim.load_scene(f)
    assert e.value.key == "dimension" and "four.yaml" in str(e.value)


def test_scene_dimension_follows_the_file_s_text_not_its_name(tmp_path):
    """scene_dimension keeps its answers by the file's text (a command asked two or three
    times and parsed the whole file each time): the same file rewritten is read again, and
    a text it cannot parse stays the 1-D reader's to refuse."""
    f = tmp_path / "s.yaml"
    for text, want in [("dimension: 2\nrate_hz: 1000\n", 2), ("dimension: 3\nrate_hz: 1000\n", 3),
                       ("dimension: 2\nrate_hz: [1000\n", 1), ("dimension: true\n", 1),
                       ("dimension: 2\nrate_hz: 1000\n", 2), ("# dimension\nrate_hz: 1\n", 1)]:
        f.write_text(text)
        assert scene_dimension(f) == want, text
        assert scene_dimension(str(f)) == want, text

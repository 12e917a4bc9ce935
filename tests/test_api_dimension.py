"""``hapsim.load_scene`` reads a scene in the dimension its ``dimension`` key declares
(issue 23): a 1-D scene exactly as before (the 1-D reader's Scene), a 2-D or 3-D one as
the n-D reader's SceneND; the 1-D functions refuse an n-D scene, naming the function
that takes it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import hapsim
from hapsim.errors import ConfigError
from hapsim.scene import Scene
from hapsim.scene import load_scene as load_1d
from hapsim.scene_nd import SceneND, load_scene_nd, scene_dimension

CONFIGS = sorted((Path(__file__).resolve().parent.parent / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_load_scene_picks_the_dimension(path):
    """Every shipped scene: the type follows the file's dimension, and the result equals
    the dimension's own reader's."""
    s = hapsim.load_scene(path)
    if scene_dimension(path) == 1:
        assert type(s) is Scene and s == load_1d(str(path)) and s.dimension == 1
    else:
        assert type(s) is SceneND
        np.testing.assert_equal(dataclasses.asdict(s), dataclasses.asdict(load_scene_nd(path)))
        assert s.dimension == scene_dimension(path) in (2, 3)


def test_one_d_functions_refuse_an_n_d_scene_by_name():
    """check and run on a 2-D scene (path or object): ConfigError naming check_nd / run_nd
    and the key dimension."""
    p = Path(__file__).resolve().parent.parent / "configs" / "pantograph_wall.yaml"
    for scene in (p, hapsim.load_scene(p)):
        with pytest.raises(ConfigError, match="check_nd") as e:
            hapsim.check(scene)
        assert e.value.key == "dimension"
        with pytest.raises(ConfigError, match="run_nd"):
            hapsim.run(scene)


def test_a_bad_dimension_is_the_n_d_reader_s_error(tmp_path):
    """dimension: 4 is refused with the file, line and key (the n-D reader's message)."""
    f = tmp_path / "four.yaml"
    f.write_text("dimension: 4\nrate_hz: 1000\nmasses: []\nlinks: []\n")
    with pytest.raises(ConfigError) as e:
        hapsim.load_scene(f)
    assert e.value.key == "dimension" and "four.yaml" in str(e.value)

"""``--rate`` on a 2-D or 3-D scene (issue 23 item 5): the loop at another rate than the
scene file's, its prediction at that rate, measured = predicted in-process and through the
n-axis mock, whose physics follows the CONFIG's rate."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from hapsim.cli import main
from hapsim.emulated.mock import MockDeviceND
from hapsim.pipeline.felt_port import measure_felt_port
from hapsim.emulated.links import InProcessTransport
from hapsim.scene import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_run_lockstep_at_another_rate(capsys):
    """``run --lockstep --rate 2000``: the prediction is the loop's at 2 kHz (the felt
    damping of the sampled loop changes with the period), and the measurement equals it
    to 1e-6."""
    from hapsim.analysis.scene_check import check_scene_nd
    scene = str(CONFIGS / "pantograph_wall.yaml")
    assert main(["run", scene, "--lockstep", "--rate", "2000", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    b1 = check_scene_nd(load_scene_nd(scene)).render.felt_damping      # at 1 kHz
    b2 = np.array(out["predicted"]["felt_damping"])
    assert np.abs(b2 - b1).max() > 0.1 * np.abs(b1).max()
    assert max(out["deviation"].values()) < 1e-6


def test_the_nd_mock_follows_the_configs_rate():
    """The mock built from the 1 kHz scene file, the host at 2 kHz (CONFIG's rate): its
    joint-space physics runs at 2 kHz and the felt matrices measured through the protocol
    are the 2 kHz prediction's to 1e-6 (it refused such a CONFIG before)."""
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    fast = dataclasses.replace(sc, rate_hz=2000.0)
    mock = MockDeviceND(sc, lockstep=True)
    res = measure_felt_port(InProcessTransport(mock), fast, samples=150)
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]
    assert mock.rate_hz == 2000.0 and not mock.stats.faults

"""``hapsim simulate``: file formats, shapes, row convention."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.engine import Engine
from hapsim.scene import load_scene


def test_npz_layout_and_row_convention(tmp_path):
    out = tmp_path / "osc.npz"
    assert main(["simulate", "configs/oscillator.yaml", "--steps", "100", "--out", str(out)]) == 0
    data = np.load(out)
    assert data["time"].shape == (101,)
    assert data["position"].shape == (101, 2)
    assert list(data["names"]) == ["anchor", "bob"]
    assert data["time"][0] == 0.0 and data["time"][1] == pytest.approx(1e-3)
    assert data["position"][0, 1] == 0.01          # row 0: initial state
    _, ref = Engine(load_scene("configs/oscillator.yaml")).run(100)
    np.testing.assert_array_equal(data["position"], ref)


def test_csv_with_record_order(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["simulate", "configs/string.yaml", "--steps", "50", "--out", str(out),
                 "--record", "s25", "s1", "--json"]) == 0
    header = out.read_text().splitlines()[0]
    assert header == "time,s25,s1"
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert data.shape == (51, 3)
    assert '"recorded": 2' in capsys.readouterr().out
    # the port presses the middle bead up through the contact, so s25 moves first
    assert data[5, 1] > 0 and abs(data[5, 2]) < abs(data[5, 1])


def test_unknown_extension_is_exit_2(tmp_path, capsys):
    assert main(["simulate", "configs/oscillator.yaml", "--steps", "10", "--out", str(tmp_path / "x.txt")]) == 2
    assert "valid: .npz, .csv" in capsys.readouterr().err

"""``hapsim identify --driver haply --added-mass`` end to end (issue 20): the emulated
Haply board (firmware V1.5's bytes, :class:`hapsim.driver_mock.HaplyDevice`) with an
encoder whose true counts per revolution the host does not know (a seeded random one,
the host assuming 4880). Through a wrong resolution the joint's angle is read ``g =
cpr / 4880`` times too large, so the identified inertia is ``m / g``
(:mod:`hapsim.analysis.calibration`); two identifications, without and with a known
added inertia, give ``g`` and so the true resolution, written to the device file's
protocol_options."""

from __future__ import annotations

import json

import numpy as np
import pytest

#: The joint's inertia in configs/haply.yaml [kg m^2] and the inertia added [kg m^2].
INERTIA = 0.001
ADDED = 0.002


def test_added_mass_finds_the_true_resolution(tmp_path, capsys):
    """The resolution found has an interval that holds the true one, the device's inertia
    in its own units an interval that holds 0.001 kg m^2, the direction probe ran first
    (the motor byte of this wiring: 0), and the device file's protocol_options hold the
    resolution found (what ``run`` then sends in its set-up)."""
    from hapsim.cli import main
    from hapsim.device_file import load_device
    from hapsim.drivers import get_driver
    cpr = float(np.random.default_rng(2026).integers(2500, 12000))
    out = tmp_path / "dev.yaml"
    argv = ["identify", "--driver", "haply", "--mock-scene", "configs/haply.yaml",
            "--force-limit", "0.1", "--envelope", "1", "--rate", "250", "--duration", "4",
            "--max-delay", "4", "--protocol-option", "resolution=4880",
            "--mock-option", f"cpr={cpr:g}", "--added-mass", str(ADDED), "--lockstep",
            "--out", str(out), "--json"]
    code = main(argv)
    rep = json.loads(capsys.readouterr().out)
    sc = rep["scale"]
    assert code == 0, rep
    assert sc["option"] == "resolution" and sc["added_mass"] == ADDED
    assert sc["lo"] <= cpr <= sc["hi"], (cpr, sc)
    assert sc["gain"] == pytest.approx(sc["value"] / 4880.0, rel=1e-12)
    m = rep["device"]["mass"]
    assert m["lo"] <= INERTIA <= m["hi"], m
    assert rep["loop"]["direction_probe"]["motor_direction"] == 0
    d = load_device(out)
    assert d.protocol == "haply"
    # (the file holds 6 digits: far inside the interval)
    assert d.protocol_options["resolution"] == pytest.approx(sc["value"], rel=1e-5)
    assert get_driver("haply", **d.protocol_options).options()["resolution"] == \
        pytest.approx(sc["value"], rel=1e-5)
    assert "resolution found with 0.002 kg added" in out.read_text()

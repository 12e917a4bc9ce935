"""A framed device whose delay is under one period cannot be closed in real time by
hapsim's mock (its delay line is whole periods). ``run`` refused it, but only after its
early-started mock had printed a refusal of its own beside it ("d = 0", the delay
truncated); ``identify --mock-scene`` started that mock and then said the port had failed
(a DeviceError, exit 1: the shipped FireFader scene, d = 0.725, gave it). Both now refuse
it in one line naming the file and the key, exit 2, before any device starts; in lockstep
and with the driver's own board (d < 1 by its timing) it is taken. ``identify
--mock-scene`` also takes the scene's rate, as ``run`` does."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from hapsim.cli import main

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _scene(tmp_path, d: float) -> Path:
    text = (CONFIGS / "wall.yaml").read_text()
    old = "  delay: 1  "
    assert old in text
    path = tmp_path / "wall.yaml"
    path.write_text(text.replace(old, f"  delay: {d!r}  "))
    return path


@pytest.mark.parametrize("seed", range(3))
def test_run_and_identify_refuse_a_delay_under_one_period_in_one_line(tmp_path, capfd, seed):
    """Random d in (0, 1): ``run`` and ``identify --mock-scene`` exit 2 with one line on
    stderr (the child's own refusal would be a second) naming the file, ``device.delay``
    and d; ``--lockstep`` is not refused for it."""
    d = round(random.Random(seed).uniform(0.05, 0.95), 3)
    path = _scene(tmp_path, d)
    for argv in (["run", str(path)], ["identify", "--mock-scene", str(path)]):
        assert main(argv) == 2, argv
        err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
        assert len(err) == 1, err
        assert f"{path}: device.delay: device delay d = {d:g} < 1 period" in err[0], err
    assert main(["run", str(path), "--lockstep", "--duration", "0.05"]) in (0, 1)
    assert "device.delay" not in capfd.readouterr().err


def test_the_shipped_firefader_scene_on_the_framed_mock_names_its_driver():
    """configs/firefader.yaml (d = 0.725, the board's own timing) under identify with the
    framed mock asked for by name (``--driver framed``: without it the scene's
    device.protocol is taken, tests/test_identify_scene_defaults.py): the refusal names
    its delay and says to give the board's driver."""
    import contextlib
    import io
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["identify", "--mock-scene", str(CONFIGS / "firefader.yaml"),
                     "--driver", "framed"]) == 2
    assert "--driver" in err.getvalue() and "d = 0.725" in err.getvalue()


def test_identify_takes_the_mock_scenes_rate(tmp_path, capsys):
    """``identify --mock-scene`` runs at the scene's rate unless ``--rate`` is given (it ran
    at 1000 Hz whatever the scene said: the FireFader's 250 Hz scene with ``--driver
    firefader`` was refused, 1000 Hz being more than its board holds): 1 s of a 500 Hz
    wall in lockstep is 500 samples, and ``--rate 1000`` still 1000."""
    import json
    text = (CONFIGS / "wall.yaml").read_text()
    assert "rate_hz: 1000\n" in text
    path = tmp_path / "wall500.yaml"
    path.write_text(text.replace("rate_hz: 1000\n", "rate_hz: 500\n", 1))
    for extra, samples in (([], 500), (["--rate", "1000"], 1000)):
        assert main(["identify", "--mock-scene", str(path), "--lockstep", "--json",
                     "--duration", "1", *extra]) == 0
        assert json.loads(capsys.readouterr().out)["loop"]["samples"] == samples


def test_a_2d_run_and_the_mock_refuse_it_too(tmp_path, capfd):
    """The pantograph wall at d = 0.5: ``run`` exits 2 in one line naming the file and
    ``device.delay`` (its embedded n-axis mock refused it in its own process, which the
    host reported as "the embedded n-D mock did not start", exit 1, with "d = 0"), and
    ``hapsim mock --scene`` says d = 0.5, not 0."""
    text = (CONFIGS / "pantograph_wall.yaml").read_text()
    assert "delay: 1}" in text
    path = tmp_path / "pantograph_wall.yaml"
    path.write_text(text.replace("delay: 1}", "delay: 0.5}", 1))
    assert main(["run", str(path)]) == 2
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and f"{path}: device.delay: device delay d = 0.5 < 1" in err[0], err
    assert main(["mock", "--scene", str(path), "--once"]) == 2
    assert "device delay d = 0.5 < 1" in capfd.readouterr().err

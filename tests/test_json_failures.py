"""A command asked for ``--json`` that fails prints one JSON object on stdout whatever the
way it fails (``{"error": {...}, "exit": code}`` before it had a result, or its report
with ``error`` after): a script reading stdout is never left with nothing. Before, several
refusals and device failures printed their line on stderr and returned 1 with an empty
stdout: ``play`` refusing an unstable loop, ``simulate --audio`` of a scene that diverged
(its 1-D line even went to stdout, not JSON), a 2-D ``run`` whose device never said HELLO,
the 2DIY's and the Falcon's runs on a device error. The device cases are
``tests/test_run_nd_lost.py`` and ``tests/test_board_lost.py``; these are the others,
each against its own command's exit code and error type."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hapsim.cli import main

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _json(capsys, argv) -> tuple[int, dict, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1, out              # one object, nothing else on stdout
    return code, json.loads(lines[0]), err


def _stiffer(tmp_path, name: str, old: str, new: str) -> Path:
    text = (CONFIGS / name).read_text()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new))
    return path


def test_play_refusing_an_unstable_loop(tmp_path, capsys):
    """The wall at twice its stability limit: exit 1, the error object
    (UnstableConfigError, with the spectral radius), the same line on stderr."""
    path = _stiffer(tmp_path, "wall.yaml", "stiffness: 1000.0", "stiffness: 2000.0")
    code, obj, err = _json(capsys, ["play", str(path), "--sound", "none", "--lockstep",
                                    "--duration", "0.1", "--json"])
    assert code == 1 and obj["exit"] == 1
    assert obj["error"]["type"] == "UnstableConfigError"
    assert obj["error"]["spectral_radius"] > 1.0
    assert "is unstable" in err


@pytest.mark.parametrize("name, old, new", [
    ("audio_string.yaml", "stiffness: 150000.0", "stiffness: 1.5e8"),
    ("membrane.yaml", "stiffness: 16000,", "stiffness: 1.6e12,")], ids=["1-D", "3-D"])
def test_simulate_audio_of_a_scene_that_diverged(tmp_path, capsys, name, old, new):
    """A 1-D string and a 3-D membrane far past their explicit scheme's limit: exit 1, the
    error object saying the sound diverged, and no sound file written."""
    path = _stiffer(tmp_path, name, old, new)
    wav = tmp_path / "out.wav"
    code, obj, err = _json(capsys, ["simulate", str(path), "--audio", str(wav), "--steps",
                                    "20000", "--json"])
    assert code == 1 and obj["exit"] == 1, obj
    assert "diverged" in obj["error"]["message"] and "diverged" in err
    assert not wav.exists()


@pytest.mark.parametrize("name", ["pantograph_wall.yaml", "delta_sphere.yaml"])
def test_an_nd_run_whose_port_does_not_open(tmp_path, capsys, name):
    """A 2-D or 3-D run on a port that is not there fails before its first record: exit 1
    and the DeviceError's object (the n-D run printed its line and left stdout empty, as
    for a device that never says HELLO)."""
    port = tmp_path / "no-such-tty"
    code, obj, err = _json(capsys, ["run", str(CONFIGS / name), "--port", str(port),
                                    "--json"])
    assert code == 1 and obj["exit"] == 1
    assert obj["error"]["type"] == "DeviceError" and str(port) in obj["error"]["message"]

"""configs/pantograph_spring.yaml measured through the Hapkit pantograph's firmware (issue
23, items 6 and 7): the two emulated boards on their TWI bus (lockstep, so independent of
the machine's load), ``hapsim run --port --lockstep --amplitude 5e-3`` over the leader's
UART, and the per-direction verdict (:func:`hapsim.analysis.felt_matrices.felt_verdict`): a scene
whose excitation is large against one sensor count and one PWM step, so that what the
wall scene cannot state is stated here. Skipped, with the reason, only when avr-gcc,
avr-libc or simavr's headers are not installed."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest
from tolerance import rel_tol

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "pantograph_spring.yaml"
pytestmark = pytest.mark.xdist_group("pantograph_firmware")     # one build at a time


@pytest.fixture(scope="module")
def built():
    from hapsim.emulated import hapkit_board as board, pantograph_board
    why = board.missing_tools()
    if why:
        pytest.skip(f"emulated Hapkit pantograph: {why}")
    return pantograph_board.build()


def test_the_firmware_renders_the_spring_within_its_stated_uncertainty(built, capsys):
    """``hapsim run configs/pantograph_spring.yaml --port PTY --lockstep --amplitude
    5e-3 --json`` over the emulated boards: delay 1, no late tick, no torque clamped; the
    felt stiffness (as a matrix and along both principal directions) and the felt damping
    stated "within" their own uncertainty (linearisation bound plus the wire's
    first-order worst case: half a sensor count, half a PWM step), each wire term within
    the measurable limit, the run's verdict "within" with nothing left unstated; the text
    report prints the six statements."""
    from hapsim.cli import main
    from hapsim.emulated.pantograph_board import board_command
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.scene import load_scene_nd
    scene = load_scene_nd(str(SCENE))
    a = 5e-3
    proc = subprocess.Popen(board_command(scene, a), stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("PORT "), line
        port = line.split()[1]
        assert main(["run", str(SCENE), "--port", port, "--lockstep", "--amplitude",
                     repr(a), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert main(["run", str(SCENE), "--port", port, "--lockstep", "--amplitude",
                     repr(a)]) == 0
        text = capsys.readouterr().out
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert out["delay"] == [1] * 5 and out["late"] == 0 and out["port"]["clamped"] == 0
    assert out["linearisation_bound"]["amplitude"] >= a        # at the excursion
    st = out["statements"]
    assert len(st) == 6 and out["not_stated"] == []
    for s in st:
        assert s["verdict"] == "within", s
        assert s["wire"] <= MEASURABLE_WIRE and s["deviation"] <= s["uncertainty"], s
        # the statement's three terms, two sums of positive numbers: derived rel_tol(2)
        assert s["uncertainty"] == pytest.approx(
            s["linearisation"] + s["wire"] + (s["roundoff"] or 0.0), rel=rel_tol(2))
    assert out["verdict"] == "within" and out["within"] is True
    assert text.count("felt stiffness along (") == 2
    assert text.rstrip().splitlines()[-1].startswith("  verdict: within")


def test_a_board_started_at_another_amplitude_is_not_measurable_not_a_traceback(built,
                                                                                capsys):
    """The board's simulated hand moves to the starts of its own amplitude (2e-4 m here);
    a run at 5e-3 m gets its records at starts it did not expect. Before, the joint-level
    wire term read the incomplete result's responses and the run ended in a KeyError
    traceback (exit 1); now: exit 0, "not measurable", the reason naming the amplitude."""
    from hapsim.cli import main
    from hapsim.emulated.pantograph_board import board_command
    from hapsim.scene import load_scene_nd
    scene = load_scene_nd(str(SCENE))
    proc = subprocess.Popen(board_command(scene, 2e-4), stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("PORT "), line
        assert main(["run", str(SCENE), "--port", line.split()[1], "--lockstep",
                     "--amplitude", "5e-3", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert out["verdict"] == "not measurable" and out["within"] is None
    assert "another amplitude" in out["reason"] and "0.005 m" in out["reason"], out["reason"]


def test_check_and_plot_of_the_spring(tmp_path, capsys):
    """``hapsim check configs/pantograph_spring.yaml --json``: stable, two principal
    directions (the device's mass axes at the workspace's centre, x and y); ``--plot``
    draws the workspace and the felt ellipses."""
    pytest.importorskip("matplotlib")
    from hapsim.cli import main
    assert main(["check", str(SCENE), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stable"] and out["dof"] == 2 and len(out["principal_directions"]) == 2
    fig = tmp_path / "spring.png"
    assert main(["check", str(SCENE), "--plot", str(fig)]) == 0
    assert fig.stat().st_size > 10_000

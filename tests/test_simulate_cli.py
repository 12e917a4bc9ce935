"""``hapsim simulate``: file formats, shapes, row convention."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.engine import Engine
from hapsim.scene import load_scene
from tolerance import rel_tol


def test_npz_layout_and_row_convention(tmp_path):
    out = tmp_path / "osc.npz"
    assert main(["simulate", "configs/oscillator.yaml", "--steps", "100", "--out", str(out)]) == 0
    data = np.load(out)
    assert data["time"].shape == (101,)
    assert data["position"].shape == (101, 2)
    assert list(data["names"]) == ["anchor", "bob"]
    # one product or quotient of the step and the period, and the literal: derived
    assert data["time"][0] == 0.0 and data["time"][1] == pytest.approx(1e-3, rel=rel_tol(2))
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


def test_unknown_record_name_blames_the_option_not_the_scene(tmp_path, capsys):
    out = tmp_path / "o.npz"
    code = main(["simulate", "configs/oscillator.yaml", "--steps", "10", "--out", str(out),
                 "--record", "bob", "bobb"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err == ("hapsim simulate: error: --record: no mass named 'bobb'; "
                   "masses are: anchor, bob")
    assert "oscillator.yaml" not in err
    assert not out.exists()


def test_felt_target_is_calibrated_like_the_daemon_and_reported(tmp_path, capsys):
    """configs/felt_wall.yaml (wall given as felt k = 1000 N/m, b = 3 N s/m) used to exit 2
    ('calibrate it first'); simulate now calibrates it and says which (K, B) it used."""
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.ths import render

    out = tmp_path / "felt.npz"
    assert main(["simulate", "configs/felt_wall.yaml", "--steps", "20", "--out", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    (cal,) = summary["calibrations"]
    assert cal["link"] == "wall" and (cal["k"], cal["b"]) == (1000.0, 3.0)
    K, B = cal["K"], cal["B"]
    # independent check through the inverse map: these (K, B) render the felt target
    scene = load_scene("configs/felt_wall.yaml")
    felt = render(LoopModel.from_device(scene.device, scene.rate_hz), K, B)
    # measured 0 (generic 0): exact on both targets
    assert felt.k == pytest.approx(1000.0, rel=1e-9) and felt.b == pytest.approx(3.0, rel=1e-9)
    # ... and the virtual values differ from the felt ones (the THS is not transparent)
    assert abs(K - 1000.0) > 10.0 and abs(B - 3.0) > 0.1
    data = np.load(out)
    assert data["position"].shape == (21, 2)
    assert np.all(data["position"][:, 0] == 0.005)          # port held at excitation.x0

    assert main(["simulate", "configs/felt_wall.yaml", "--steps", "5",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert (f"calibrated link wall: felt k = 1000 N/m, b = 3 N s/m -> virtual K = {K:.6g} N/m, "
            f"B = {B:.6g} N s/m") in text


def test_unrenderable_target_is_exit_1_naming_the_link(tmp_path, capsys):
    path = tmp_path / "hard.yaml"
    path.write_text(
        "rate_hz: 1000\nmasses:\n  - {name: hand, kind: port}\n  - {name: wall, kind: ground}\n"
        "links:\n  - {name: felt, kind: spring_damper, between: [hand, wall],"
        " target: {k: 50000.0, b: 0.01}}\n"
        "device: {mass: 0.1, friction: 0.0, delay: 2, hold: zoh, force_limit: 10.0}\n")
    assert main(["simulate", str(path), "--steps", "5", "--out", str(tmp_path / "o.npz")]) == 1
    err = capsys.readouterr().err
    assert f"{path}:6: links.felt.target: " in err and "not renderable" in err


def test_progress_draws_on_a_terminal_only(tmp_path):
    """The bar is drawn on a real terminal (a pty), not on a pipe or file, and not before
    ``delay`` (0 here, and 10^9 s for the "not yet" case: no wall-clock assertion)."""
    import io
    import os
    import pty
    import select

    from hapsim.progress import Progress

    master, slave = pty.openpty()
    try:
        with os.fdopen(slave, "w", closefd=True) as tty:
            assert tty.isatty()
            with Progress(200, "simulate", unit="samples", stream=tty, delay=0.0) as bar:
                assert bar.enabled
                bar.update(100)
                bar.update(200)
            with Progress(200, "waiting", stream=tty, delay=1e9) as late:
                late.update(100)                 # before its delay: nothing drawn
            drawn = ""
            while not drawn.endswith("\n"):      # the pty may pass the bytes on later
                ready, _, _ = select.select([master], [], [], 10.0)
                assert ready, f"nothing more from the pty after {drawn!r}"
                drawn += os.read(master, 4096).decode()
    finally:
        os.close(master)
    lines = drawn.replace("\r\n", "\n").split("\r")
    assert lines[0] == ""
    assert lines[1].startswith("simulate [" + "#" * 15 + "." * 15 + "]  50.0% 100/200 samples eta")
    assert lines[2].startswith("simulate [" + "#" * 30 + "] 100.0% 200/200 samples eta")
    assert lines[2].endswith("\n") and "waiting" not in drawn
    # not a terminal: nothing, unless forced
    pipe = io.StringIO()
    with Progress(10, "quiet", stream=pipe, delay=0.0) as bar:
        bar.update(5)
    assert pipe.getvalue() == ""
    with Progress(10, "forced", stream=pipe, delay=0.0, force=True) as bar:
        bar.update(5)
    assert pipe.getvalue().startswith("\rforced [" + "#" * 15) and pipe.getvalue().endswith("\n")

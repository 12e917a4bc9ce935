"""A safety stop exits 1 on every route, the report first, as ``hapsim run``'s 1-D, 2-D and
3-D framed runs and the two faders' do: the Haply 2DIY's real-time run whose joints left
the measurement's envelope (braked, then zero torque) and the Falcon's loop stopped on the
motion (a leg beyond its envelope). Before, both exited 0. The stop is made by narrowing
the envelope (the hand's start then leaves it), each against its emulated device."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hapsim.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: An envelope the hand's start leaves within its first ticks [rad].
NARROW_RAD = 1e-5


class _Board:
    """The embedded 2DIY's stand-in: no process (the measurement below takes the board
    in process)."""

    port, clock = "in-process", "lockstep"

    def __init__(self, *a, **k) -> None:
        pass

    def close(self) -> None:
        pass


@pytest.mark.parametrize("as_json", [True, False], ids=["json", "text"])
def test_a_2diy_whose_joints_left_the_envelope_exits_1(as_json, monkeypatch, capsys):
    """``hapsim run --driver haply`` in real time (the records taken from the emulated
    board in process, in lockstep), the envelope narrowed: the joints of each record the
    hand starts moving leave it (four: the record from rest stays), each braking is
    reported, the verdict is "not measurable", exit 1."""
    from hapsim.emulated.haply2_board import Haply2DIYBoard
    from hapsim.pipeline import haply2_embedded, haply2_host, haply2_record
    from test_board_lost import _Haply2Link  # same directory
    real = haply2_host.measure_felt_haply2_port

    def in_process(port, scene, gen, **kw):
        board = Haply2DIYBoard(scene, gen, cpr=kw["resolution"], amplitude=kw["amplitude"],
                               clock="lockstep")
        return real(_Haply2Link(board), scene, gen, **{**kw, "lockstep_board": True,
                                                       "probe_wiring": False})
    monkeypatch.setattr(haply2_embedded, "Embedded2DIY", _Board)
    monkeypatch.setattr(haply2_host, "measure_felt_haply2_port", in_process)
    monkeypatch.setattr(haply2_record, "ENVELOPE_RAD", NARROW_RAD)
    code = main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--driver", "haply",
                 "--amplitude", "1e-4"] + (["--json"] if as_json else []))
    out = capsys.readouterr().out
    assert code == 1, out
    if as_json:
        rep = json.loads(out)
        assert sorted(v >= 0 for v in rep["left"]) == [False] + [True] * 4, rep["left"]
        assert rep["verdict"] == "not measurable"
        assert "left the measurement's envelope" in rep["reason"]
    else:
        assert out.count("the joints out of the envelope at tick") == 4, out
        assert "verdict: not measurable" in out


def test_a_falcon_loop_stopped_on_the_motion_exits_1(monkeypatch, capsys, tmp_path):
    """``hapsim run --driver falcon`` on the emulated Falcon, the legs' envelope narrowed:
    the loop stops on the motion ("safety: leg ..."), the report says so and the run
    exits 1 (a safety stop); the same run with the envelope as shipped exits 0."""
    from hapsim.pipeline import falcon_run
    fw = tmp_path / "falcon.bin"
    fw.write_bytes(bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8)))
    argv = ["run", str(CONFIGS / "delta_sphere.yaml"), "--driver", "falcon", "--firmware",
            str(fw), "--packets", "300", "--json"]
    assert main(argv) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["stopped"] is None, rep["stopped"]
    monkeypatch.setattr(falcon_run, "ENVELOPE_RAD", NARROW_RAD)
    assert main(argv) == 1
    rep = json.loads(capsys.readouterr().out)
    assert rep["stopped"][1].startswith("safety: leg "), rep["stopped"]
    assert "stopped at packet" in rep["reason"] and rep["verdict"] == "degraded"

"""The n-D run over a port under the 1-D fault models (issue 23 item 5: real time as in
1-D): every fault of :mod:`hapsim.emulated.faults` injected by the n-axis mock, seen by the
host through real frames on a virtual clock (:class:`~hapsim.emulated.links.SimTransport`:
seeded, never timed). The records go on through every fault, every row kept is a measured
one (a record stops at the first STATE lost), the device lost with its port is found
again, and the verdict is honest: "within" with the felt matrices = predicted to 1e-6, or
"not measurable" with the reason -- never a wrong "within"."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis.linearisation import linearisation_bound
from hapsim.emulated.faults import FAULT_NAMES, parse_faults
from hapsim.emulated.mock import MockDeviceND, PhysicsND
from hapsim.pipeline.felt_port import measure_felt_port, min_rows, start_of, verdict_nd
from hapsim.emulated.links import InProcessTransport, SimTransport
from hapsim.lockstep import excitation_starts
from hapsim.scene import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: one of every fault, each at a device tick inside the first records (a scheduled wire
#: fault hits the next frame in its direction)
EVERY_FAULT = ("drop@20,corrupt@200,garbage@350,dup@420,reorder@480,spike@530:5ms,"
               "rx.drop@40,rx.corrupt@160,rx.garbage@260,rx.dup@300,rx.reorder@380,"
               "rx.spike@450:5ms,stall@560:200ms,reset@640,vanish@700:300ms")


def _verdict(sc, res, a=1e-8):
    res["bound"] = linearisation_bound(sc, max(a, res["excursion"]),
                                       res["predicted"].render.rendered_poles)
    return verdict_nd(res)


@pytest.mark.parametrize("name", ["pantograph_wall.yaml", "delta_sphere.yaml"])
def test_every_fault_kind_the_records_go_on_and_measure(name):
    """Every fault once on a 2-D and a 3-D scene: the run ends with every start's whole
    record, the loss (the port vanished) found again, the reset and the records cut
    counted, and measured = predicted to 1e-6 (the verdict "within")."""
    sc = load_scene_nd(CONFIGS / name)
    tr = SimTransport(MockDeviceND(sc, lockstep=False), parse_faults(EVERY_FAULT, 1))
    res = measure_felt_port(tr, sc, samples=150)
    injected = tr.device.plan.injected
    assert all(injected[f] == 1 for f in FAULT_NAMES if f != "nohello"), injected
    c = res["counts"]
    assert res["lost"] == c["recovered"] == 1 and tr.reopened >= 1
    assert c["resets"] >= 1 and c["cut"] >= 1 and c["missed"] >= 1
    assert c["configs"] > 2 * sc.dimension + 1
    assert res["rows"] == [150] * (2 * sc.dimension + 1)
    assert res["bad_frames"] >= 2                      # corrupt, garbage
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]
    assert _verdict(sc, res)["verdict"] == "within"


def test_a_lossy_link_is_not_measurable_never_within():
    """STATEs lost at 5 % per frame: no start gets a whole record in 6 CONFIGs, and a
    record stops at its first lost STATE, so the starts lack rows: nothing is fitted and
    the verdict is "not measurable", saying how many starts and why."""
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    tr = SimTransport(MockDeviceND(sc, lockstep=False), parse_faults("drop=0.05", 3))
    res = measure_felt_port(tr, sc, samples=150, max_configs=6)
    assert res["counts"]["configs"] == 6 and res["counts"]["missed"] >= 6
    assert res["deviation"] is None and res["measured"]["felt_stiffness"] is None
    assert any(r < min_rows(150, res["order"], 2) for r in res["rows"])
    v = _verdict(sc, res)
    assert v["verdict"] == "not measurable" and v["within"] is None
    assert "starts got no record" in v["reason"] and "STATEs missed" in v["reason"]


@pytest.mark.parametrize("name", ["pantograph_wall.yaml", "delta_sphere.yaml"])
def test_the_start_is_read_from_the_first_two_samples(name):
    """The device's own physics from each identification start (joint-space: the
    configuration-dependent mass) under zero force over the first period (d >= 1):
    start_of names that start; another amplitude (x 3 or / 3) names none."""
    sc = load_scene_nd(CONFIGS / name)
    n, T, a = sc.dimension, sc.period, 1e-8
    rest = np.asarray(sc.device.position, float)
    for j, (x0, v0) in enumerate(excitation_starts(n, a, T)):
        ph = PhysicsND(sc, x0, v0)
        p0 = np.array(ph.sample())
        ph.advance(np.zeros(n))
        pos = np.array([p0, ph.sample()])
        assert start_of(pos, rest, a, T) == j
        if j:
            assert start_of(pos, rest, 3 * a, T) is None
            assert start_of(pos, rest, a / 3, T) is None


def test_readings_that_cannot_tell_the_starts_follow_the_cycle():
    """The host told a = 3e-8 while the device's hand moves by 1e-8 (as a quantised
    device's readings, no start can be read): every record is placed by the hand's cycle
    and measured = predicted to 1e-6 (free responses fit whatever their amplitude)."""
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    res = measure_felt_port(InProcessTransport(MockDeviceND(sc, lockstep=True)), sc,
                            samples=150, amplitude=3e-8)
    assert res["counts"]["by_order"] == 4 and res["counts"]["configs"] == 5
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]


class _CountsAConfigTwice(MockDeviceND):
    """A device that takes its second CONFIG twice (a duplicated frame on its link): its
    hand skips a start."""

    def _on_config(self, msg, now_us):
        if self.configs_since_hello == 1:
            self.configs_since_hello += 1
        return super()._on_config(msg, now_us)


def test_a_skipped_start_is_found_by_its_samples():
    """The hand skips a start once: the record read at its own start (out of the host's
    turn), the host follows the device's cycle, goes round again for the skipped one,
    and measured = predicted to 1e-6."""
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    res = measure_felt_port(InProcessTransport(_CountsAConfigTwice(sc, lockstep=True)), sc,
                            samples=150)
    assert res["counts"]["out_of_turn"] == 1 and res["counts"]["configs"] > 5
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]


def test_a_device_that_never_says_hello_is_an_error_after_its_time():
    """nohello: HELLO asked, the port opened again with backoff, and after the time
    allowed a DeviceError (exit 1 from the CLI) -- no measurement, no verdict."""
    from hapsim.errors import DeviceError
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    tr = SimTransport(MockDeviceND(sc, lockstep=False), parse_faults("nohello", 0))
    with pytest.raises(DeviceError, match="did not come back"):
        measure_felt_port(tr, sc, samples=150, reconnect_time=2.0)


def test_mock_vanish_needs_a_link(capsys):
    """``hapsim mock --scene 2-D --faults vanish@...`` without --link: exit 2, as 1-D."""
    from hapsim.cli import main
    assert main(["mock", "--scene", str(CONFIGS / "pantograph_wall.yaml"),
                 "--faults", "vanish@100"]) == 2
    assert "--link" in capsys.readouterr().err


def test_cli_run_with_faults_over_the_embedded_mock(capsys):
    """``hapsim run 2-D --faults vanish@400:300ms,drop@100 --fault-seed 1 --json`` in
    real time (embedded mock behind a pty, the link it keeps at the new pty): exit 0, the
    port's loss found again, the faults the mock injected reported, and an honest
    verdict (within, or not measurable with its reason)."""
    from hapsim.cli import main
    scene = str(CONFIGS / "pantograph_wall.yaml")
    assert main(["run", scene, "--faults", "vanish@400:300ms,drop@100", "--fault-seed", "1",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["port"]["faults_injected"] == {"drop": 1, "vanish": 1}
    assert out["lost"] == 1 and out["counts"]["recovered"] == 1
    assert out["verdict"] in ("within", "partly within", "not measurable"), out["reason"]
    if out["verdict"] == "within":
        bound = out["linearisation_bound"]
        assert all(out["deviation"][k] <= bound[k] for k in ("felt_stiffness",
                                                             "felt_damping"))
    elif out["verdict"] == "partly within":
        assert out["within"] is True and out["not_stated"]
    else:
        assert out["incomplete"] and out["deviation"] is None


def test_run_faults_with_a_port_is_refused(capsys):
    """--faults are the embedded mock's: with --port, exit 2 naming --faults."""
    from hapsim.cli import main
    assert main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--port", "/dev/null",
                 "--faults", "drop=0.1"]) == 2
    assert "--faults" in capsys.readouterr().err


"""The n-DoF mock behind the framed protocol and the run over a port (issue 23 item 5): the
joint-space device (quadratic kinematics about the operating point, compiled) against the
exact kinematics; the felt matrices measured through the protocol = predicted to 1e-6, in
lockstep and in real time with seeded late ticks (FORCEs lost and delayed: the device holds
the force before and names it in force_seq; the run subtracts its known disturbance per
axis, and without that subtraction the measurement is far off); a real-time run over a
pseudo-terminal with the mock serving it in a thread."""

from __future__ import annotations

import dataclasses
import os
import pty
import threading
import tty
from pathlib import Path

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.emulated.mock import MockDeviceND
from hapsim.pipeline.felt_port import measure_felt_port
from hapsim.emulated.links import InProcessTransport, SimTransport
from hapsim.joint_device import JointDeviceND, LocalJointDeviceND
from hapsim.scene import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _scene(name):
    return load_scene_nd(CONFIGS / name)


@pytest.mark.parametrize("name", ["pantograph_wall.yaml", "delta_sphere.yaml"])
def test_local_joint_device_is_the_exact_one_to_second_order(name):
    """Quadratic kinematics: the motion under random forces departs from the exact
    kinematics' (Newton forward solves) by the third-order Taylor term, O(|s|^2)
    relative: halving the motion divides it by 8."""
    sc = _scene(name)
    n = sc.dimension
    errs = []
    for scale in (1.0, 0.5):
        rng = np.random.default_rng(1)
        x0 = scale * 1e-4 * rng.normal(size=n)
        v0 = scale * 1e-2 * rng.normal(size=n)
        a = LocalJointDeviceND(sc, x0, v0)
        b = JointDeviceND(sc, sc.device.position + x0, v0)
        # measured 1.4e-17 (generic 1.9e-17), margin 52
        assert np.allclose(a.position(), b.position(), rtol=0, atol=1e-15)
        for _ in range(2 if n == 3 else 40):
            u = scale * 0.02 * rng.normal(size=n)
            a.step(u)
            b.step(u)
        errs.append(np.abs(a.position() - b.position()).max())
    assert errs[0] < 1e-8
    assert 6.0 < errs[0] / errs[1] < 10.0, errs


def test_lockstep_over_the_protocol_measures_the_predicted_felt_matrices():
    """In-process transport, lockstep n-axis mock with the joint-space device: the felt
    matrices to 1e-6 of the prediction; HELLO says 2 axes; no late tick."""
    sc = _scene("pantograph_wall.yaml")
    res = measure_felt_port(InProcessTransport(MockDeviceND(sc, lockstep=True)), sc,
                            samples=150)
    assert res["hello"].n_axes == 2
    assert res["late"] == 0 and res["delay"] == [1] * 5
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]


class _HostileHost:
    """A SimTransport whose host loses a seeded share of its FORCEs and sends another
    share after the device's tick (stale there): late ticks at the device."""

    def __init__(self, inner, seed, lose=0.05, slow=0.05):
        self.inner = inner
        self.rng = np.random.default_rng(seed)
        self.lose, self.slow = lose, slow
        self.info = inner.info

    def send(self, msg):
        if isinstance(msg, fp.Force):
            r = self.rng.random()
            if r < self.lose:
                return
            if r < self.lose + self.slow:
                self.inner.sleep(1.5e-3)            # past tick seq + 1: the device holds
        self.inner.send(msg)

    def receive(self, timeout=0.0):
        return self.inner.receive(timeout)

    def last_frames(self):
        return self.inner.last_frames()


def test_late_ticks_are_accounted_per_axis(monkeypatch, tmp_path):
    """Real-time mock on a virtual clock, a device delay of 2 ticks, FORCEs lost and
    late at random: many late ticks, every one's force named by force_seq; measured =
    predicted to 1e-6. Without subtracting the disturbance's response the same records
    are off by > 1e-3."""
    text = (CONFIGS / "pantograph_wall.yaml").read_text()
    assert "hand_mass: 0.05, delay: 1}" in text
    path = tmp_path / "wall_d2.yaml"
    path.write_text(text.replace("hand_mass: 0.05, delay: 1}", "hand_mass: 0.05, delay: 2}"))
    sc = load_scene_nd(path)

    def run():
        mock = MockDeviceND(sc, lockstep=False)
        return measure_felt_port(_HostileHost(SimTransport(mock), 0), sc, samples=150)
    res = run()
    assert res["late"] > 15
    assert res["delay"] == [2] * 5
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]
    import hapsim.pipeline.felt_port as rn
    monkeypatch.setattr(rn, "disturbance_response_nd",
                        lambda scene, W, A=None: np.zeros_like(W))
    assert max(run()["deviation"].values()) > 1e-3


def test_cli_mock_and_run_over_a_pty(capsys):
    """``hapsim mock --scene configs/pantograph_wall.yaml --once`` (served from a thread:
    the two share one interpreter, so late ticks are likely and accounted) and ``hapsim
    run SCENE --port PATH --json``: exit 0, the device's delay 1 in every record where a
    FORCE came in time, the felt matrices within the stated linearisation bound however
    many ticks were late (the late ticks' known disturbance subtracted); the mock
    ends when the run closes the port."""
    import json

    from hapsim.cli import main
    from hapsim.commands import mock as mock_cmd
    scene = str(CONFIGS / "pantograph_wall.yaml")
    ports = []
    made = threading.Event()

    def new_pty(link, announce):
        master, slave = pty.openpty()
        tty.setraw(slave)
        ports.append(os.ttyname(slave))
        made.set()
        return master, slave
    import argparse
    ap = argparse.ArgumentParser()
    mock_cmd.register(ap.add_subparsers())
    args = ap.parse_args(["mock", "--scene", scene, "--once"])
    from hapsim.commands.mock import run_mock_nd
    th = threading.Thread(target=run_mock_nd, args=(args, new_pty), daemon=True)
    th.start()
    assert made.wait(10)
    capsys.readouterr()
    assert main(["run", scene, "--port", ports[0], "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    th.join(10)
    assert not th.is_alive()
    # -1: a record in which no FORCE came in time (this machine under load); the mock
    # shares this interpreter, so a loaded machine can stall it past the silence allowed:
    # the device is then lost and must be recovered (HELLO again, a new record), never
    # guessed across
    assert out["dof"] == 2 and set(out["delay"]) <= {1, -1}
    assert out["counts"]["recovered"] == out["lost"], out["counts"]
    # the linear prediction holds to the stated linearisation bound, taken at the largest
    # excursion the records reached (late ticks hold old forces and move the handle past
    # the nominal amplitude; the loop's second-order terms grow with it): 1.7e-6 in
    # damping was seen at load ~20 with 433 late ticks, against 3.4e-6 stated; and at
    # that excursion's ratio to the free response left once the held forces' response is
    # taken out (a fresh-clone CI run: 487 late ticks, 1.13 um against 22 nm, the felt
    # stiffness 2.1 times the bound at the excursion alone; test_bound_at_records.py)
    bound = out["linearisation_bound"]
    for key in ("felt_stiffness", "felt_damping"):
        assert out["deviation"][key] <= bound[key], (key, out["deviation"], bound,
                                                     out["late"])
    assert max(out["deviation"].values()) < 1e-4, (out["deviation"], out["late"])
    assert out["verdict"] == "within", out["reason"]


class _WithoutAppliedBit:
    """A device written before STATUS_FORCE_APPLIED existed (PROTOCOL.md §9: added within
    version 1): its STATEs never set the bit; force_seq names the FORCE applied."""

    def __init__(self, inner):
        self.inner = inner
        self.info = getattr(inner, "info", None)

    def send(self, msg):
        self.inner.send(msg)

    def receive(self, timeout=0.0):
        return [dataclasses.replace(m, status=m.status & ~fp.STATUS_FORCE_APPLIED)
                if isinstance(m, fp.State) else m for m in self.inner.receive(timeout)]

    def last_frames(self):
        return self.inner.last_frames()


def test_a_device_without_the_applied_bit_is_measured():
    """The same lockstep records from a device that never sets FORCE_APPLIED: force_seq
    names each FORCE (seq - d), so the run measures the felt matrices to 1e-6 as with the
    bit (before: a record without the bit was read as 'no FORCE arrived in time', the whole
    force sent taken as a disturbance, delay -1)."""
    sc = _scene("pantograph_wall.yaml")
    res = measure_felt_port(_WithoutAppliedBit(InProcessTransport(
        MockDeviceND(sc, lockstep=True))), sc, samples=150)
    assert res["late"] == 0 and res["delay"] == [1] * 5
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]

"""The Haply 2DIY (issue 23 item 6): its bytes against the published layout (hAPI's
Device.java set-up and write, the board firmware V1.5's parser and reply), the emulated
board's encoders and motors (directions, whole counts, the set-up's offset), hostile
streams (seeded byte loss and corruption both ways, a desync: the loop goes on, the
samples are counted), and the felt matrices measured through the bytes in lockstep within
the stated uncertainty."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from hapsim.daemon.haply2_board import Haply2DIYBoard, drive_haply2, measure_felt_haply2
from hapsim.drivers.haply2 import GENERATIONS, Haply2DIY
from hapsim.driver_mock import ByteFaults
from hapsim.scene_nd import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _scene(name="pantograph_wall.yaml"):
    return load_scene_nd(CONFIGS / name)


def _f(x):
    return struct.pack("<f", x)


@pytest.mark.parametrize("gen, mdir, edir, res", [("gen2", (1, 0), (1, 0), 10752.0),
                                                  ("gen3", (0, 0), (1, 1), 4880.0)])
def test_setup_and_write_bytes_follow_the_published_layout(gen, mdir, edir, res):
    """Set-up ``[1][id][mask 3][dir port1][dir port2][mask 3][dir port1][dir port2][0][0]
    [offset, resolution of port 1][of port 2]``: joint 1 is on port 2, joint 2 on port 1
    (hAPI's add_actuator(1, .., 2)); a write ``[2][id][tau port 1][tau port 2]``; the
    board's reply ``[id][angle port 1][angle port 2]``."""
    drv = Haply2DIY(gen, device_id=7)
    s = drv.setup_bytes((130.0, 50.0))
    want = (bytes([1, 7, 3, mdir[1], mdir[0], 3, edir[1], edir[0], 0, 0])
            + _f(50.0) + _f(res) + _f(130.0) + _f(res))
    assert s == want and len(s) == 26
    w = drv.write_bytes((0.01, -0.02))
    assert w == bytes([2, 7]) + _f(-0.02) + _f(0.01)
    assert drv.write_bytes((1.0, float("nan"))) == bytes([2, 7]) + _f(0.0) + _f(0.123)
    # the reply of port 1 is joint 2
    dec = drv.decoder()
    rep = bytes([7]) + _f(360.0 * 700 / res) + _f(360.0 * 1800 / res)
    (got,) = dec.feed(rep)
    assert drv.joints_of(got) == pytest.approx((math.radians(360.0 * 1800 / res),
                                                math.radians(360.0 * 700 / res)), rel=1e-7)


@pytest.mark.parametrize("gen", sorted(GENERATIONS))
def test_emulated_board_reads_the_joints_and_applies_the_torques(gen):
    """After the set-up (offsets = the operating point's joints) the board reads back the
    joints in whole counts of the set-up's resolution; a torque on joint 1 turns joint 1
    up (the generation's wiring) and its reading goes up; the opposite encoder direction
    bytes mirror the reading, not the motion."""
    sc = _scene()
    q0 = np.degrees(sc.device.joints)
    drv = Haply2DIY(gen)
    res = GENERATIONS[gen].resolution
    for flip in (False, True):
        board = Haply2DIYBoard(sc, gen)
        setup = bytearray(drv.setup_bytes(q0))
        if flip:
            setup[6:8] = bytes(1 - b for b in setup[6:8])
        board.feed(bytes(setup))
        assert board.parser.encoder_res[:2] == [res, res]
        start = None
        for k in range(40):
            rep = board.feed(drv.write_bytes((0.02, 0.0)))
            assert len(rep) == 9 and rep[0] == 1
            a2, a1 = struct.unpack_from("<ff", rep, 1)
            for a, off in ((a1, q0[0]), (a2, q0[1])):
                n = a * res / 360.0
                assert n == pytest.approx(round(n), abs=1e-3)
            if start is None:
                start = (a1, a2)
                # the first reply: one period from the offset, within a count
                assert a1 == pytest.approx(q0[0], abs=360.0 / res)
                assert a2 == pytest.approx(q0[1], abs=360.0 / res)
        moved = a1 - q0[0]
        assert abs(moved) > 5 * 360.0 / res
        assert (moved > 0) != flip
        assert board.plant.joints()[0] > math.radians(q0[0])       # the joint turned up


def test_flipped_motor_turns_the_joint_the_other_way():
    """The motor direction byte alone: flipped, the same write turns joint 1 down."""
    sc = _scene()
    q0 = np.degrees(sc.device.joints)
    drv = Haply2DIY("gen3")
    turned = []
    for flip in (False, True):
        board = Haply2DIYBoard(sc, "gen3")
        setup = bytearray(drv.setup_bytes(q0))
        if flip:
            setup[4] = 1 - setup[4]                     # port 2's motor = joint 1's
        board.feed(bytes(setup))
        for _ in range(30):
            board.feed(drv.write_bytes((0.02, 0.0)))
        turned.append(board.plant.joints()[0] - sc.device.joints[0])
    assert turned[0] > 0 > turned[1]
    assert turned[0] == pytest.approx(-turned[1], rel=1e-2)


@pytest.mark.parametrize("seed", [0, 1])
def test_hostile_streams_the_loop_goes_on_and_counts(seed):
    """Seeded byte loss and corruption both ways (0.3 % of the bytes each): every sample
    of the loop is run, the missing replies, the re-armings and the decoder's skipped
    bytes are counted, most samples are taken, no accepted reading is more than 1 deg
    from the joints (the handle stays within 0.5 deg), and the board ends set up and in
    step (a clean write is answered)."""
    sc = _scene()
    drv = Haply2DIY("gen2")
    board = Haply2DIYBoard(sc, "gen2", amplitude=1e-4)
    faults = ByteFaults({"drop_rx": 3e-3, "corrupt_rx": 3e-3, "drop_tx": 3e-3,
                         "corrupt_tx": 3e-3, "seed": seed})
    r = drive_haply2(board.feed, drv, sc, 400, faults=faults)
    taken = int(np.count_nonzero(~np.isnan(r["joints"][:, 0])))
    assert taken + r["missing"] >= 400 and r["missing"] > 0 and r["resyncs"] > 0
    assert taken > 0.6 * 400
    assert r["decoder"]["skipped"] > 0
    assert min(faults.counts.values()) > 0
    dq = np.abs(r["joints"][~np.isnan(r["joints"][:, 0])] - sc.device.joints)
    assert dq.max() < math.radians(1.0)
    assert np.abs(board.plant.joints() - sc.device.joints).max() < math.radians(0.5)
    assert len(board.feed(drv.write_bytes((0.0, 0.0)))) == 9


def test_a_corrupted_setup_offset_is_caught_and_armed_again():
    """A bit flipped in the set-up's first offset (50 deg read as 54 deg, a whole number
    of counts, so the decoder takes its replies): the board's angles would all be shifted;
    the first reply does not read the offsets sent, so the host arms again (bad_setups 1)
    and every reading is the joints'."""
    sc = _scene()
    drv = Haply2DIY("gen3")
    board = Haply2DIYBoard(sc, "gen3")
    zero = len(drv.write_bytes((0.0, 0.0)))

    class FlipOffset:
        def __init__(self):
            self.n = 0

        def rx(self, b):
            self.n += 1
            if self.n == 1:             # the first arm's bytes before its last write
                b = bytearray(b)
                b[len(b) - 16 + 2] ^= 0x10      # port 1's offset: 50 -> 54 deg
            return bytes(b)

        def tx(self, b):
            return b
    r = drive_haply2(board.feed, drv, sc, 50, faults=FlipOffset())
    assert r["bad_setups"] == 1 and r["resyncs"] == 1      # armed again once
    dq = np.abs(r["joints"][~np.isnan(r["joints"][:, 0])] - sc.device.joints)
    assert dq.max() < math.radians(0.1) and zero == 10


def test_a_lost_host_byte_desyncs_the_board_and_the_host_resyncs_it():
    """One host byte lost inside a write shifts the board's parser (its later bytes read
    as other commands): replies stop or turn to garbage; the host re-arms the board and
    the samples come back."""
    sc = _scene()
    drv = Haply2DIY("gen3")
    board = Haply2DIYBoard(sc, "gen3")

    class OneLoss:
        def __init__(self):
            self.n = 0

        def rx(self, b):
            self.n += 1
            return b[:3] + b[4:] if self.n == 20 else b

        def tx(self, b):
            return b
    r = drive_haply2(board.feed, drv, sc, 120, faults=OneLoss())
    assert r["resyncs"] >= 1 and r["missing"] >= 1
    assert not np.isnan(r["joints"][-50:, 0]).any()


def test_felt_matrices_through_the_bytes_within_the_stated_uncertainty():
    """In lockstep through the 2DIY's bytes (fine encoders, so the binary32 angles are the
    wire's resolution, 9e-4 of a = 1e-4 m): the measured felt matrices within the
    linearisation bound at a of the prediction, and not at round-off (the wire and the
    kinematics are really in the loop)."""
    from hapsim.analysis.linearisation_nd import linearisation_bound
    sc = _scene("pantograph_wall.yaml")
    res = measure_felt_haply2(sc, "gen2", amplitude=1e-4, cpr=2.0 ** 22, samples=150)
    b = linearisation_bound(sc, 1e-4, res["predicted"].render.rendered_poles).to_dict()
    dev = res["deviation"]
    assert res["quantum"] < 1e-3
    assert dev["felt_stiffness"] <= b["felt_stiffness"], (dev, b)
    assert dev["felt_damping"] <= b["felt_damping"], (dev, b)
    assert dev["felt_stiffness"] > 1e-6


def test_cli_driver_haply_on_a_2d_scene(capsys):
    """``run --driver haply`` needs --lockstep (exit 2 naming it); another driver on a
    2-D scene is refused naming --driver."""
    from hapsim.cli import main
    scene = str(CONFIGS / "pantograph_wall.yaml")
    for argv, key in ((["run", scene, "--driver", "haply"], "--lockstep"),
                      (["run", scene, "--driver", "firefader", "--lockstep"], "--driver")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert key in err and "Traceback" not in err


def test_cli_run_driver_haply_json(capsys):
    """``hapsim run configs/pantograph_circle.yaml --driver haply --lockstep --json``: the
    gen3 bytes, the measured felt matrices within the linearisation bound it reports, the
    wire's resolution and one count of each generation's encoders over a."""
    import json

    from hapsim.cli import main
    assert main(["run", str(CONFIGS / "pantograph_circle.yaml"), "--driver", "haply",
                 "--lockstep", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["driver"] == "haply" and out["generation"] == "gen3" and out["dof"] == 2
    b, dev = out["linearisation_bound"], out["deviation"]
    assert dev["felt_stiffness"] <= b["felt_stiffness"]
    assert dev["felt_damping"] <= b["felt_damping"]
    assert out["quantum"] < 1e-3 < out["quantum_real_encoders"]["gen2"] < \
        out["quantum_real_encoders"]["gen3"]

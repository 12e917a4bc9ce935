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
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hapsim.emulated.haply2_board import Haply2DIYBoard
from hapsim.emulated.haply2_lockstep import drive_haply2, measure_felt_haply2
from hapsim.drivers.haply2 import GENERATIONS, Haply2DIY
from hapsim.emulated.driver_mock import ByteFaults
from hapsim.scene import load_scene_nd
from tolerance import rel_tol

#: Unit round-off of IEEE binary32, the wire's floats [-] (IEEE 754: round to nearest).
U32 = 2.0 ** -24

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
    # binary32 on the wire: one rounding to single (U32), then the same few double
    # roundings either side (derived bound; measured 3.6e-8 relative, generic the same)
    assert drv.joints_of(got) == pytest.approx((math.radians(360.0 * 1800 / res),
                                                math.radians(360.0 * 700 / res)),
                                               rel=U32 + rel_tol(4))


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
        board = Haply2DIYBoard(sc, gen, clock="lockstep")
        setup = bytearray(drv.setup_bytes(q0))
        if flip:
            setup[6:8] = bytes(1 - b for b in setup[6:8])
        board.feed(bytes(setup))
        assert board.parser.encoder_res[:2] == [res, res]
        start = None
        for k in range(40):
            rep = board.feed(drv.write_bytes((0.02, 0.0)))
            assert len(rep) == 9 and rep[0] == drv.id
            a2, a1 = struct.unpack_from("<ff", rep, 1)
            for a, off in ((a1, q0[0]), (a2, q0[1])):
                n = a * res / 360.0
                # the board's 360 c / res (two double roundings) went as binary32 (U32 of
                # it), and two more here: whole counts to that (derived; measured 5.8e-8
                # relative, generic the same)
                assert n == pytest.approx(round(n), rel=U32 + rel_tol(4))
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
        board = Haply2DIYBoard(sc, "gen3", clock="lockstep")
        setup = bytearray(drv.setup_bytes(q0))
        if flip:
            setup[4] = 1 - setup[4]                     # port 2's motor = joint 1's
        board.feed(bytes(setup))
        for _ in range(30):
            board.feed(drv.write_bytes((0.02, 0.0)))
        turned.append(board.plant.joints()[0] - sc.device.joints[0])
    assert turned[0] > 0 > turned[1]
    # the linkage is not symmetric about the operating point: measured 1.3e-3 relative
    # (generic 1.3e-3; lockstep, so deterministic up to round-off), margin 7.7
    assert turned[0] == pytest.approx(-turned[1], rel=1e-2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_lockstep_drive_does_not_depend_on_the_hosts_speed(seed, monkeypatch):
    """A board stepped one period per write has the writes' time: the reach a reply is
    checked against grows with it, not with the wall time between two reads. The same
    hostile stream driven by a host whose clock runs 50 ms a read (a loaded machine) is
    read exactly as by a fast one (before, the reach grew with the wall clock, and a
    loaded full suite took a reading 2.6 rad off the joints)."""
    import itertools

    from hapsim.drivers.haply2 import Reply2Decoder

    def run(slow: bool) -> dict:
        sc = _scene()
        drv = Haply2DIY("gen2")
        if slow:
            ticks = itertools.count()
            make = drv.decoder

            def decoder():
                d = make()
                d._clock = lambda: 0.05 * next(ticks)    # 50 ms of wall time a read
                return d
            monkeypatch.setattr(drv, "decoder", decoder)
        board = Haply2DIYBoard(sc, "gen2", amplitude=1e-4, clock="lockstep")
        faults = ByteFaults({"drop_rx": 3e-3, "corrupt_rx": 3e-3, "drop_tx": 3e-3,
                             "corrupt_tx": 3e-3, "seed": seed})
        return drive_haply2(board.feed, drv, sc, 300, faults=faults)

    assert isinstance(Haply2DIY("gen2").decoder(), Reply2Decoder)
    fast, slow = run(False), run(True)
    assert slow["decoder"] == fast["decoder"] and slow["resyncs"] == fast["resyncs"]
    np.testing.assert_array_equal(slow["joints"], fast["joints"])   # bit for bit


@pytest.mark.parametrize("seed", [0, 1])
def test_hostile_streams_the_loop_goes_on_and_counts(seed):
    """Seeded byte loss and corruption both ways (0.3 % of the bytes each): every sample
    of the loop is run, the missing replies, the re-armings and the decoder's skipped
    bytes are counted, most samples are taken, no accepted reading is more than 1 deg
    from the joints (the handle stays within 0.5 deg), and the board ends set up and in
    step (a clean write is answered)."""
    sc = _scene()
    # the address 1 (the default before issue 29's): a lost host byte makes the board read
    # a set-up out of the next write, so the re-arming path is exercised too
    drv = Haply2DIY("gen2", device_id=1)
    board = Haply2DIYBoard(sc, "gen2", amplitude=1e-4, clock="lockstep")
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
    board = Haply2DIYBoard(sc, "gen3", clock="lockstep")
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


@pytest.mark.parametrize("address", [1, 3])
def test_a_lost_host_byte_desyncs_the_board_and_the_host_resyncs_it(address):
    """One host byte lost inside a write shifts the board's parser (its later bytes read
    as other commands). At the address 1 (the default before) the next write's address
    byte is read as a set-up: replies stop or turn to garbage; the host re-arms the board
    and the samples come back. At the default address 3, no command byte, the board is
    back in step at the write after: a missing sample, no re-arming."""
    sc = _scene()
    drv = Haply2DIY("gen3", device_id=address)
    board = Haply2DIYBoard(sc, "gen3", clock="lockstep")

    class OneLoss:
        def __init__(self):
            self.n = 0

        def rx(self, b):
            self.n += 1
            return b[:3] + b[4:] if self.n == 20 else b

        def tx(self, b):
            return b
    r = drive_haply2(board.feed, drv, sc, 120, faults=OneLoss())
    assert (r["resyncs"] >= 1 if address == 1 else r["resyncs"] == 0) and r["missing"] >= 1
    assert not np.isnan(r["joints"][-50:, 0]).any()


_PLANS = {}


def _plan(name, samples=150):
    """The prediction of a scene, computed once per test session (it does not depend on
    the amplitude)."""
    from hapsim.lockstep import identification_plan
    if name not in _PLANS:
        _PLANS[name] = (_scene(name), identification_plan(_scene(name), samples))
    return _PLANS[name]


def _wire_res(gen, bits, a, name="pantograph_wall.yaml", **kw):
    sc, plan = _plan(name)
    return sc, measure_felt_haply2(sc, gen, amplitude=a, cpr=2.0 ** bits, samples=150,
                                   plan=plan, **kw)


def test_the_wire_term_decides_the_verdict_at_small_amplitudes():
    """The first shift's wrong verdict, at its cause (2^22 counts/rev): on the circle at
    a = 5e-5 m the felt stiffness departs beyond the linearisation bound alone (the
    readings' rounding, not the kinematics) and inside the bound plus the wire's term:
    "within"; on the wall at a = 1.5e-5 m the damping departs far beyond the bound alone
    and its wire term exceeds the measurable limit: the felt damping (as a matrix and
    along each principal direction) is "not measurable" (not "differs", not "within" with
    a vacuous interval), while the felt stiffness, whose wire term is small, is stated
    "within" (as a matrix and along y; along x its term over the error box, 0.30, is
    beyond the limit: not stated, never a wrong verdict): the run's verdict is "partly
    within", the damping named as not measurable (never a bare "within" that a reader
    could take for a checked damping)."""
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.analysis.linearisation import linearisation_bound
    sc, r = _wire_res("gen3", 22, 5e-5, "pantograph_circle.yaml")
    # the old verdict: the bound alone, stated at the hand's a (now it is stated at the
    # records' excursion, 2.2 a here, which covers this departure by itself)
    lin = linearisation_bound(sc, 5e-5, r["predicted"].render.rendered_poles).to_dict()
    assert r["deviation"]["felt_stiffness"] > lin["felt_stiffness"]
    assert r["verdict"] in ("within", "partly within") and r["within"] is True
    assert (r["verdict"] == "partly within") == bool(r["not_stated"])
    assert r["deviation"]["felt_stiffness"] <= r["uncertainty"]["felt_stiffness"]
    _, r = _wire_res("gen3", 22, 1.5e-5)
    assert r["deviation"]["felt_damping"] > 3 * r["bound"].to_dict()["felt_damping"]
    assert r["wire"]["felt_damping"] > MEASURABLE_WIRE
    by = {s["name"]: s for s in r["statements"]}
    damping = [s for s in r["statements"] if s["quantity"] == "felt_damping"]
    stiffness = [s for s in r["statements"] if s["quantity"] == "felt_stiffness"]
    assert len(damping) == len(stiffness) == 3                 # the matrix, 2 directions
    assert by["felt damping"]["verdict"] == "not measurable"
    assert "felt damping" in r["not_stated"] and r["uncertainty"]["felt_damping"] is None
    for s in damping:
        assert s["verdict"] != "within" or s["wire"] <= MEASURABLE_WIRE
    assert by["felt stiffness"]["verdict"] == "within"
    for s in stiffness:
        assert s["verdict"] in ("within", "not measurable"), s
        assert (s["verdict"] == "within") == (s["wire"] <= MEASURABLE_WIRE), s
        if s["verdict"] == "within":
            assert s["deviation"] <= s["uncertainty"], s
    assert r["verdict"] == "partly within" and r["within"] is True
    assert "not measurable" in r["reason"] and "felt damping" in r["reason"]


@settings(max_examples=5, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(bits=st.integers(19, 23), quanta=st.floats(20.0, 3000.0),
       gen=st.sampled_from(sorted(GENERATIONS)),
       name=st.sampled_from(["pantograph_wall.yaml", "pantograph_circle.yaml"]))
def test_verdict_over_amplitudes_and_encoders(bits, quanta, gen, name):
    """Over excitations of 20 to 3000 reading steps (capped below the wall's depth) and
    encoders of 2^19..2^23 counts/rev, on a correct loop no statement is "differs": each
    quantity (a felt matrix, or the felt stiffness or damping along a principal
    direction) is stated exactly when its wire term is within the measurable limit, then
    "within" with its deviation inside its stated uncertainty (linearisation bound plus
    the wire's first-order worst case), and otherwise "not measurable"; the run's verdict
    is "within" when anything was stated, else "not measurable" with its cause."""
    from hapsim.kinematics import device
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    sc, _ = _plan(name)
    J = device("pantograph", sc.device.geometry).jacobian(sc.device.joints)
    a = min(quanta * np.linalg.norm(J, 2) * 2 * math.pi / 2.0 ** bits, 4e-4)
    _, r = _wire_res(gen, bits, a, name)
    dev, w, lin = r["deviation"], r["wire"], r["bound"].to_dict()
    assert r["verdict"] in ("within", "partly within", "not measurable"), \
        (a, bits, r["reason"], dev)
    if r["measured"]["felt_stiffness"] is None:
        # a rendered mode the records do not carry above their errors (a pair within
        # hapsim.analysis.pencil.MODE_FLOOR of the bound: 20 reading steps at 2^19):
        # no felt matrices, nothing stated, and the excitation named
        assert r["verdict"] == "not measurable" and "too small" in r["reason"], r["reason"]
        assert r["statements"] == [] and r["uncertainty"] is None
        return
    assert len(r["statements"]) == 6
    for s in r["statements"]:
        measurable = s["wire"] is not None and s["wire"] <= MEASURABLE_WIRE
        assert (s["verdict"] == "within") == measurable, (a, bits, s)
        if measurable:
            # the statement's three terms, two sums of positive numbers: derived rel_tol(2)
            # (the round-off term is 1.2e-7 of the sum here: without it the check held by
            # the approx default's 1e-6 only)
            assert s["uncertainty"] == pytest.approx(
                s["linearisation"] + s["wire"] + (s["roundoff"] or 0.0), rel=rel_tol(2))
            assert s["deviation"] <= s["uncertainty"], (a, bits, s)
    mat = {s["quantity"]: s for s in r["statements"] if s["direction"] is None}
    for key in ("felt_stiffness", "felt_damping"):
        if w[key] <= MEASURABLE_WIRE:
            # linearisation + wire + the matrix statement's round-off term: derived rel_tol(2)
            assert r["uncertainty"][key] == pytest.approx(
                lin[key] + w[key] + (mat[key]["roundoff"] or 0.0), rel=rel_tol(2))
            assert dev[key] <= r["uncertainty"][key], (a, bits, key, dev, r["uncertainty"])
    if r["verdict"] == "not measurable":
        assert r["uncertainty"] is None and "too small" in r["reason"]
        assert all(s["verdict"] == "not measurable" for s in r["statements"])


def test_a_device_unlike_the_scenes_differs():
    """The board's joint inertia 10 % above the scene's (a mis-declared device): the
    measured felt stiffness departs by ~6.7 %, beyond the stated uncertainty (3.7 %):
    "differs" (the bound with the wire's term is not so wide that it cannot fail). At 3 %
    (2.2 % off) the stated uncertainty, since the wire's term is taken over the error box
    (3.2 %: hapsim.analysis.wire_box), no longer resolves it: "partly within"."""
    import dataclasses
    sc, plan = _plan("pantograph_wall.yaml")
    plant = dataclasses.replace(sc, device=dataclasses.replace(
        sc.device, joint_inertia=sc.device.joint_inertia * 1.1))
    _, r = _wire_res("gen3", 22, 1e-4, plant=plant)
    assert r["verdict"] == "differs" and r["within"] is False
    assert r["deviation"]["felt_stiffness"] > r["uncertainty"]["felt_stiffness"]


def test_cli_driver_haply_on_a_2d_scene(capsys):
    """``run --driver haply --port`` is refused (a real board has no hand to start the
    records: exit 2 naming --port); another driver on a 2-D scene is refused naming
    --driver."""
    from hapsim.cli import main
    scene = str(CONFIGS / "pantograph_wall.yaml")
    for argv, key in ((["run", scene, "--driver", "haply", "--port", "/dev/null"],
                       "--port"),
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
    b, dev, u, w = (out["linearisation_bound"], out["deviation"], out["uncertainty"],
                    out["wire"])
    # the wire's term over the error box (hapsim.analysis.wire_box) leaves the damping
    # as a matrix and along one principal direction unstated (measured 0.45 and 0.72,
    # beyond 0.25):
    # what is stated is within, only a damping is not
    assert out["verdict"] in ("within", "partly within") and out["within"] is True
    assert all(s["quantity"] == "felt_damping" for s in out["statements"]
               if s["verdict"] == "not measurable")
    mat = {s["quantity"]: s for s in out["statements"] if s["direction"] is None}
    assert mat["felt_stiffness"]["verdict"] == "within"
    for key in ("felt_stiffness", "felt_damping"):
        if mat[key]["verdict"] == "not measurable":
            continue
        # linearisation + wire + the matrix statement's round-off term: derived rel_tol(2)
        assert dev[key] <= u[key] == pytest.approx(
            b[key] + w[key] + (mat[key]["roundoff"] or 0.0), rel=rel_tol(2))
    assert out["quantum"] < 1e-3 < out["quantum_real_encoders"]["gen2"] < \
        out["quantum_real_encoders"]["gen3"]
    # a lockstep board holds each torque exactly a period: no write-timing term
    assert w["hold_s"] is None and out["link_uncertainty"] is None


@settings(max_examples=60, deadline=None, derandomize=True)
@given(mmask=st.integers(1, 15), emask=st.integers(1, 15),
       dirs=st.lists(st.integers(0, 1), min_size=8, max_size=8))
def test_board_parser_keeps_motor_and_encoder_directions_apart(mmask, emask, dirs):
    """Any set-up (motor and encoder masks, a direction byte per port set up): the
    parser's k-th motor direction is the k-th motor byte and its k-th encoder direction
    the k-th encoder byte, as the firmware stores them (actuators[k], encoders[k]); one
    shared list (the 1-DoF parser's) gave a 2DIY gen3's motors its encoders' CCW."""
    from hapsim.emulated.haply_firmware import CommandDecoder
    nm, ne = bin(mmask).count("1"), bin(emask).count("1")
    md, ed = dirs[:nm], dirs[4:4 + ne]
    setup = (bytes([1, 9, mmask]) + bytes(md) + bytes([emask]) + bytes(ed) + bytes((0, 0))
             + (_f(10.0) + _f(4880.0)) * ne)
    dec = CommandDecoder()
    assert dec.feed(setup) == [("setup", 9)]
    assert dec.motor_direction[:nm] == md and dec.encoder_direction[:ne] == ed
    gen3 = Haply2DIY("gen3").setup_bytes((130.0, 50.0))
    dec.feed(gen3)
    assert dec.motor_direction[:2] == [0, 0] and dec.encoder_direction[:2] == [1, 1]


@pytest.mark.parametrize("later_s, absent", [(20e-6, False), (60e-6, True)])
def test_the_wall_clock_board_reads_an_absent_byte_as_255_at_its_pass(later_s, absent):
    """Firmware V1.5's single ``SerialUSB.read()`` of an empty buffer is 255; the board on
    its own clock reads a byte as absent only at the pass that comes before it arrives.
    A write taken at 0.1 s (the arming long done) puts the next pass ``PASS_S`` (50 us)
    on; the next write's command byte comes alone 10 us after it: the board waits for its
    pass. Its address arriving 20 us later (before the pass) is read: the whole write,
    one 9-byte reply. Arriving 60 us later (after the pass, which read 255 for it), the
    write went to address 255 (no port: its reply is the one byte 255), and the late
    bytes are read as the commands they spell."""
    from hapsim.emulated.haply2_board import PASS_S
    sc = _scene()
    drv = Haply2DIY("gen2")
    board = Haply2DIYBoard(sc, "gen2", clock="wall")
    zero = drv.write_bytes((0.0, 0.0))
    q0 = [math.degrees(v) for v in sc.device.joints]
    board.feed(drv.arm_bytes(q0), 0.0)
    assert len(board.feed(zero, 0.1)) == 9 and PASS_S == 50e-6
    t = 0.1 + 10e-6
    assert board.feed(zero[:1], t) == b"" and board.parser.waiting == 1
    got = board.feed(zero[1:], t + later_s)
    assert board.parser.stats["absent"] == int(absent)
    if absent:
        assert got[:1] == b"\xff"
    else:
        assert len(got) == 9 and got[0] == zero[1]


@pytest.mark.parametrize("seed", range(4))
def test_an_idle_board_takes_a_write_at_its_next_pass(seed):
    """Firmware V1.5's ``loop()`` passes every 50 us whether a command waits or not
    (``lastPublished`` set at each pass): writes that come at random times to an idle
    board (the 2DIY's, and the M3's) are each taken at the first pass after they came,
    less than a pass later, the passes on one grid from the set-up's end (before, an idle
    board took a write the moment it came: the holds varied only as the host's writes
    did, which the host sees; the pass's phase it does not)."""
    from hapsim.drivers import haply as hp
    from hapsim.emulated.driver_mock import HaplyDevice
    from hapsim.emulated.haply2_board import PASS_S
    from hapsim.scene import Device, Excitation
    rng = np.random.default_rng(seed)
    sc = _scene()
    drv = Haply2DIY("gen2")
    board = Haply2DIYBoard(sc, "gen2", clock="wall")
    board.feed(drv.arm_bytes([math.degrees(v) for v in sc.device.joints]), 0.0)
    m3 = HaplyDevice(Device(mass=1e-3, friction=1e-3, delay=1, force_limit=0.12), 1000.0,
                     Excitation())
    m3.feed(hp.setup_packet(1), 0.0)
    zero = drv.write_bytes((0.0, 0.0))
    arrivals = 0.05 + np.cumsum(rng.uniform(0.2e-3, 2e-3, 30))
    phases = []
    for dev, packet in ((board, zero), (m3, hp.write_packet(1, 0.0))):
        grid = None
        for t in arrivals:
            assert dev.feed(packet, float(t))
            took = dev.ready_at
            # (the board's times are sums of 50 us steps from the arming: 1e-9 of a
            # pass covers their round-off, derived from ~2,000 additions of 2^-52)
            assert t - 1e-9 * PASS_S <= took < t + PASS_S, (t, took)
            grid = took if grid is None else grid
            k = (took - grid) / PASS_S
            # on the grid: derived as above (a bound on the round-off of the sums, 1e-9
            # of a pass), pass_at's own tolerance of 1e-6 of a pass beside it
            assert abs(k - round(k)) < 1e-6, (took, grid)
            phases.append((took - t) / PASS_S)
    # (the test's test: the waits spread over the pass, not all at 0)
    assert max(phases) > 0.5, phases


def test_a_silent_host_lets_the_wall_clock_board_read_its_absent_bytes():
    """A command byte alone, then silence: the board's pass reads the absent address as
    255 without waiting for bytes that never come (:meth:`Haply2DIYBoard.idle`), and its
    reply goes out then."""
    sc = _scene()
    drv = Haply2DIY("gen2")
    board = Haply2DIYBoard(sc, "gen2", clock="wall")
    zero = drv.write_bytes((0.0, 0.0))
    q0 = [math.degrees(v) for v in sc.device.joints]
    board.feed(drv.arm_bytes(q0), 0.0)
    board.feed(zero, 0.1)
    assert board.feed(zero[:1], 0.1 + 10e-6) == b""
    assert board.idle(20e-6) == b""            # 30 us: the pass (50 us) has not come
    assert board.idle(0.02) == b"\xff" and board.parser.waiting == 0

"""The Haply joint's motor direction, found by identify before it excites (issue 20):
a torque pulse of each sign against the emulated board (firmware V1.5's two independent
direction bytes, and a wiring that may reverse the motor against the encoder)."""

import pytest

from hapsim.emulated.driver_mock import HaplyDevice
from hapsim.drivers import get_driver
from hapsim.drivers.haply import MAX_TORQUE, HaplyM3, setup_packet, write_packet
from hapsim.drivers.haply2 import GENERATIONS
from hapsim.drivers.haply_probe import LEVELS, find_direction
from hapsim.errors import IdentificationError
from hapsim.scene import Device


class _Link:
    """The emulated board called in process: each write's replies read back."""

    def __init__(self, dev):
        self.dev = dev
        self.buf = b""

    def write(self, data):
        self.buf += self.dev.feed(data)

    def read(self, timeout):
        out, self.buf = self.buf, b""
        return out


def _probe(dev, drv, force_limit=MAX_TORQUE):
    return find_direction(drv, _Link(dev), force_limit=force_limit, envelope=0.1,
                          pace=False, timeout=0.0)


# every wiring hAPI's two generations set up (the direction bytes per joint that count
# up), each driven with either encoder byte, with and without static friction
WIRINGS = sorted({(g.motor_direction[j], g.encoder_direction[j])
                  for g in GENERATIONS.values() for j in range(2)})


@pytest.mark.parametrize("wiring", WIRINGS)
@pytest.mark.parametrize("enc", [0, 1])
@pytest.mark.parametrize("md0", [0, 1])
@pytest.mark.parametrize("coulomb", [0.0, 0.03])
def test_probe_finds_the_motor_byte_of_every_wiring(wiring, enc, md0, coulomb):
    """The byte found drives the joint the way its angle counts up: a positive torque
    written after a set-up with it moves the encoder up; the pulses stay within the force
    limit, the joint within a few counts, and the board is left at zero torque."""
    m, e = wiring
    dev = HaplyDevice(Device(mass=1e-4, friction=1e-3, delay=1, coulomb=coulomb), 1000.0,
                      motor_sign=(-1) ** (m + e), clock="lockstep")
    drv = HaplyM3(direction=enc, motor_direction=md0)
    p = _probe(dev, drv, force_limit=0.1)
    assert p.motor_direction == (m + e + enc) % 2
    assert p.relative == (1 if p.motor_direction == md0 else -1)
    assert p.torque[0] > 0 > p.torque[1] and max(map(abs, p.torque)) <= 0.1
    # static friction is overcome only by a pulse above it (raised by doubling)
    assert all(abs(t) > coulomb for t in p.torque)
    assert all(3 <= abs(c) <= 8 for c in p.counts)
    assert dev.held == 0.0 and dev.settles_on() == 0.0
    # the byte found, independently: a set-up with it, then a positive torque
    link = _Link(dev)
    link.write(setup_packet(1, direction=enc, motor_direction=p.motor_direction)
               + write_packet(1, 0.0))
    a0 = dev.angle_deg()
    for _ in range(40):
        link.write(write_packet(1, 0.06))
    assert dev.angle_deg() > a0 + 360.0 * 3 / 4880.0
    link.write(write_packet(1, 0.0))


@pytest.mark.parametrize("coulomb,limit", [(0.2, MAX_TORQUE), (0.05, 0.04)])
def test_probe_refuses_a_joint_that_does_not_move(coulomb, limit):
    """Static friction above the largest torque allowed (the board's 0.123 N m, or a lower
    force limit): no motion, a clear refusal naming the torque, and zero torque left."""
    dev = HaplyDevice(Device(mass=1e-4, friction=1e-3, delay=1, coulomb=coulomb), 1000.0, clock="lockstep")
    with pytest.raises(IdentificationError, match=rf"did not move 3 encoder counts under "
                                                  rf"\+{min(limit, MAX_TORQUE):.4g} N m"):
        _probe(dev, HaplyM3(), force_limit=limit)
    assert dev.held == 0.0 and dev.settles_on() == 0.0
    # the torque went as binary32, and the board applies the firmware's level of it (its
    # 12-bit duty at the Due's 8 bits: hapsim.drivers.output_stage.m3_output, exact)
    from hapsim.drivers.output_stage import m3_output
    assert max(map(abs, dev.applied)) == abs(float(m3_output([min(limit, MAX_TORQUE)])[0][0]))
    assert len(set(abs(f) for f in dev.applied if f)) == LEVELS


def test_probe_refuses_a_joint_something_else_moves():
    """A joint already moving (here let go at 1 rad/s, as a hand or a spring would move
    it) does not come to rest at zero torque before the first pulse: refused after
    SETTLE_S, zero torque left."""
    from hapsim.scene import Excitation
    dev = HaplyDevice(Device(mass=1e-3, friction=1e-4, delay=1), 1000.0, Excitation(v0=1.0), clock="lockstep")
    with pytest.raises(IdentificationError, match="did not come to rest at zero torque "
                                                  "within 3 s.*something else moves it"):
        _probe(dev, HaplyM3(), force_limit=0.1)
    assert dev.held == 0.0 and dev.settles_on() == 0.0


def test_motor_direction_is_a_protocol_option_run_sends():
    """The byte found goes to protocol_options and the set-up run sends (motor byte 3,
    encoder byte 5); omitted, it is the encoder's (the set-up of earlier device files);
    the id is the host's: the board answers any."""
    drv = get_driver("haply", direction=0, motor_direction=1)
    setup = drv.arm()[-(8 + 8 + 6):-6]
    assert setup[0] == 1 and setup[3] == 1 and setup[5] == 0
    assert get_driver("haply", direction=1).options()["motor_direction"] == 1
    assert drv.mock_hardware()["motor_sign"] == -1
    for dev_id in (7, 200):
        dev = HaplyDevice(Device(mass=1e-4, friction=1e-3, delay=1), 1000.0, clock="lockstep")
        reply = dev.feed(HaplyM3(device_id=dev_id).arm())
        assert reply[-5] == dev_id


def test_a_motor_direction_given_is_not_probed_and_a_wrong_one_runs_away():
    """The case the probe is for: the same identification on the reversed board with the
    motor byte given as the encoder's (``--protocol-option motor_direction=0``: given, so
    not probed) is positive feedback and ends on a safety stop (the next test runs it
    with the probe: its whole length)."""
    from hapsim.pipeline.identify_run import record
    r = record(Device(mass=1e-3, friction=1e-3, delay=1), driver="haply", force_limit=0.1,
               envelope=0.2, duration=0.5, max_delay=4, progress=False,
               handle_signals=False, driver_options={"motor_direction": 0},
               mock_options={"cpr": 4880.0, "motor_sign": -1})
    assert r["loop"]["direction_probe"] is None and r["loop"]["safety_stop"]
    assert r["loop"]["samples"] < 500


def test_identify_writes_the_direction_found_to_the_device_file(tmp_path, capsys):
    """``hapsim identify --driver haply --out FILE`` on a board whose motor is wired
    reversed: the probe finds it, the excitation runs its whole length, the device file's protocol_options hold motor_direction 1 (the driver they
    build describes the reversed board, and its set-up sends that byte: what ``run``
    uses), the JSON shows the probe, and the text output says the id is the host's.

    In lockstep (the embedded mock ticks when the host has answered): what is tested is
    the probe, the record and the file, the same code as in real time. In real time a
    loaded machine stalls the mock's link: the record has gaps (0-5 at load 14-22 here),
    each cutting the stretches the fit may use, and twice in the loaded suite the fit
    refused what was left ("the device hardly moved": fewer than 100 samples of clear
    motion, exit 1), a verdict on the machine, not on the probe."""
    import json

    from hapsim.cli import main
    from hapsim.device_file import load_device
    out = tmp_path / "dev.yaml"
    argv = ["identify", "--driver", "haply", "--mock-scene", "configs/haply.yaml",
            "--force-limit", "0.1", "--envelope", "1", "--duration", "0.8", "--max-delay",
            "4", "--mock-option", "motor_sign=-1", "--out", str(out), "--lockstep"]
    assert main(argv + ["--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    probe = rep["loop"]["direction_probe"]
    assert probe["motor_direction"] == 1 and probe["relative"] == -1
    assert not rep["loop"]["safety_stop"] and rep["loop"]["samples"] == 800
    d = load_device(out)
    assert d.protocol == "haply" and d.protocol_options["motor_direction"] == 1
    drv = get_driver("haply", **d.protocol_options)
    assert drv.mock_hardware()["motor_sign"] == -1
    assert drv.arm()[-(8 + 8 + 6) + 3] == 1
    assert "found before the excitation" in out.read_text()


class _LossyLink(_Link):
    """:class:`_Link` losing each host byte with probability ``p`` (seeded)."""

    def __init__(self, dev, rng, p):
        super().__init__(dev)
        self.rng, self.p = rng, p

    def write(self, data):
        super().write(bytes(b for b in data if self.rng.random() >= self.p))


@pytest.mark.parametrize("seed", range(8))
def test_probe_on_a_lossy_link(seed):
    """One host byte in 200 lost (about a dozen in a probe's ~400 writes, some of them in
    its re-synchronisations' 62 bytes): the probe puts the board back in step (zero
    torque, the set-up at the last angle read; again after five writes unanswered) and
    finds the byte with which a positive torque moves the encoder up, leaving zero
    torque. Before, the probe's exchange had no re-synchronisation: after the first lost
    byte the decoder took no reply and the probe ended "does not answer its writes" (20
    seeds of 20; against the independent model of tools/independent_boards, 3 of 3)."""
    import numpy as np
    rng = np.random.default_rng(5100 + seed)
    m = int(rng.integers(0, 2))
    dev = HaplyDevice(Device(mass=1e-3, friction=1e-3, delay=1), 1000.0,
                      motor_sign=(-1) ** m, clock="lockstep")
    drv = HaplyM3()
    p = find_direction(drv, _LossyLink(dev, rng, 0.005), force_limit=0.1, envelope=1.0,
                       pace=False, timeout=0.0)
    assert p.motor_direction == m
    assert dev.held == 0.0 and dev.settles_on() == 0.0

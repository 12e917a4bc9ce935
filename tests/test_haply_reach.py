"""A Haply reading is believed only where the joint can be (issue 29 item 2).

The board has no framing and no checksum: a window of bytes with the device's id and a
whole number of encoder counts looks like a reply, and a set-up the stream corrupted
answers whole counts in another frame. The host's decoder takes a reply only within the
reach of the last one it took (:meth:`hapsim.drivers.haply.ReplyDecoder.reach_deg`: the
board's torque clamp over the joint's inertia, over the time since the write the last
reply answered, plus the encoder's whole counts), after a desync and after an arming too
(before: the next reply after either was taken unchecked, and a garbage one, 4.79 and
7.4 rad on a joint that stayed within 0.2 rad, stopped the run). Deterministic: the
decoder is told its time (no wall clock)."""

from __future__ import annotations

import math
import struct
import types

import numpy as np
import pytest

from hapsim.drivers import get_driver
from hapsim.drivers import haply as hp
from hapsim.emulated.haply_firmware import CommandDecoder
from tolerance import rel_tol

J = 1e-3                         # joint inertia [kg m^2] (configs/haply.yaml)
RES = 4880.0                     # counts per revolution
ALPHA = hp.MAX_TORQUE / J        # largest angular acceleration [rad/s^2]


def _count_deg(theta):
    """The firmware's reading of ``theta`` [rad]: a whole count, in degrees, as binary32
    (the wire's)."""
    return struct.unpack("<f", struct.pack("<f", 360.0 * round(theta / (2 * math.pi) * RES)
                                           / RES))[0]


def _trajectory(rng, n, T):
    """A joint driven by torques within the clamp (random, held 1-20 periods), integrated
    exactly per period (constant acceleration): angles [rad] at t = k T."""
    th = np.empty(n)
    x, v = rng.uniform(-0.3, 0.3), rng.uniform(-1.0, 1.0)
    k = 0
    while k < n:
        a = rng.uniform(-ALPHA, ALPHA)
        for _ in range(int(rng.integers(1, 21))):
            if k >= n:
                break
            th[k] = x
            x += v * T + 0.5 * a * T * T
            v += a * T
            k += 1
    return th


def _far_angle(rng, near_deg):
    """A whole-count angle [deg] at least 30 deg from ``near_deg`` (no joint gets there
    in the test's gaps) within the decoder's range."""
    while True:
        a = _count_deg(math.radians(rng.uniform(-1000.0, 1000.0)))
        if abs(a - near_deg) > 30.0:
            return a


@pytest.mark.parametrize("seed", range(12))
def test_only_reachable_replies_are_believed(seed):
    """Replies of a joint moving under torques within the clamp, read by a host that is
    late at random (gaps of 1 to 40 periods: the decoder is told the time since the write
    of the last reply it took), with garbage put in at random: runs of 1-byte ``[id]``
    answers long enough to count a desync, each followed by a well-formed reply of
    whole counts far away (a board set up by garbage answers so). Every genuine reply is
    taken, none of the garbage (each counted unreachable). Before: the first reply after
    a desync was taken unchecked."""
    rng = np.random.default_rng(seed)
    T = 1e-3
    n = 600
    th = _trajectory(rng, n, T)
    dec = hp.ReplyDecoder(1, resolution=RES, accel=ALPHA, clock=lambda: 0.0)
    taken = []
    genuine = []
    garbage = 0
    k = 0
    last_taken_t = None
    while k < n:
        data = b""
        if k > 5 and rng.random() < 0.05:
            data += bytes([1]) * int(rng.integers(hp.DESYNC_BYTES, 40))
            data += hp.reply_packet(1, _far_angle(rng, _count_deg(th[k])))
            garbage += 1
        a = _count_deg(th[k])
        data += hp.reply_packet(1, a)
        genuine.append(a)
        # the host reads now, k T + a late read's gap; the board sampled at k T
        dec.elapsed(None if last_taken_t is None else k * T - last_taken_t)
        got = dec.feed(data)
        taken += got
        if got:
            last_taken_t = k * T
        k += int(rng.choice([1, 1, 1, 2, 5, 40], p=[0.6, 0.1, 0.1, 0.1, 0.05, 0.05]))
    assert taken == genuine
    assert dec.stats["unreachable"] >= garbage > 0
    assert dec.stats["desync"] >= garbage


@pytest.mark.parametrize("seed", range(6))
def test_an_arming_is_anchored_at_its_offset(seed):
    """After an arming the decoder's prediction is the set-up's offset: a reply of a
    set-up the stream corrupted (whole counts in another frame) or an old-frame answer
    from before the set-up is not taken; the set-up's own reply is, and the ones after
    it go on from there. Before: the next two replies were taken unchecked."""
    rng = np.random.default_rng(100 + seed)
    off = float(rng.uniform(-30, 30))
    drv = get_driver("haply", device_id=1, offset_deg=off)
    dec = drv.decoder(inertia=J)
    fr = dec.frames
    fr.elapsed(0.002)
    dec.reset_prediction(jumps=2)
    bad = _far_angle(rng, off)
    assert dec.feed(hp.reply_packet(1, bad)) == []
    assert fr.stats["unreachable"] == 1
    a0 = _count_deg(math.radians(off))
    got = dec.feed(hp.reply_packet(1, a0))
    assert got == [pytest.approx(math.radians(a0), abs=0.0)]
    fr.elapsed(0.001)
    a1 = _count_deg(math.radians(off) + 1e-3)
    assert dec.feed(hp.reply_packet(1, a1)) == [pytest.approx(math.radians(a1), abs=0.0)]


def test_the_reach_is_the_physics():
    """The reach is the motion the clamp allows, not less: over a gap tau from rest it is
    at least 1/2 alpha tau^2 (the exact excursion from rest at the clamp) plus a count,
    and it grows as tau^2 (a joint never outruns it, however late the host); no less than
    the one-period floor."""
    dec = hp.ReplyDecoder(1, resolution=RES, accel=ALPHA)
    dec.reset_prediction(anchor=0.0)
    for tau in (1e-3, 5e-3, 0.02, 0.1, 0.5):
        exact = math.degrees(0.5 * ALPHA * tau * tau) + 360.0 / RES
        assert dec.reach_deg(0, tau) >= max(exact, dec.max_step)
    # twice the time, four times the acceleration's share
    r1 = dec.reach_deg(0, 0.2) - dec.reach_deg(0, 0.0)
    assert dec.reach_deg(0, 0.4) > 3.5 * r1
    with pytest.raises(ValueError, match="accel"):
        dec.set_accel(-1.0)


class _Port:
    """A serial port in memory: what the host writes is kept, what the test puts in
    ``inbuf`` is read."""

    is_open = True

    def __init__(self):
        self.inbuf = bytearray()
        self.written = []

    @property
    def in_waiting(self):
        return len(self.inbuf)

    def read(self, n):
        b = bytes(self.inbuf[:n])
        del self.inbuf[:n]
        return b

    def write(self, data):
        self.written.append(bytes(data))
        return len(data)

    def flush(self):
        pass

    def close(self):
        self.is_open = False


def _armed_transport(off_deg):
    import firmware_protocol as fp
    from hapsim.drivers.transport import DriverTransport
    drv = get_driver("haply", device_id=1, offset_deg=off_deg)
    tr = DriverTransport(drv, "loop://", inertia=J)
    port = _Port()
    tr._ser.close()
    tr._ser = port
    tr.send(fp.Config(1000.0, 5000, 10.0))
    return tr, port, fp


def test_the_first_record_is_no_velocity():
    """One record: an estimated sample has nothing to extrapolate from (NaN: the loop
    holds), and a re-synchronisation sets the encoder to that record, not to a position
    extrapolated from the host's initial 0 (before: the first record's angle per tick was
    taken for a velocity, 0.2 rad a tick on configs/haply.yaml: estimated samples at 0.4,
    0.6 rad and a set-up's offset as far off)."""
    off = 11.5
    tr, port, fp = _armed_transport(off)
    a0 = _count_deg(math.radians(off))
    port.inbuf += hp.reply_packet(1, a0)
    out = tr.receive()
    assert [m.position[0] for m in out if isinstance(m, fp.State)] == [math.radians(a0)]
    tr.send(fp.Force(0, (0.0,)))
    st = types.SimpleNamespace(seq=0, time_us=0, status=0, force_seq=0)
    assert math.isnan(tr.estimate(st, 1, 1))
    tr.close()


def test_a_reply_no_motion_reaches_resynchronises_at_once():
    """A well-formed reply out of the joint's reach (whole counts of another frame, as a
    set-up the stream corrupted answers) is evidence the board lost its place: the host
    re-synchronises at once (zero torque first, the set-up at the last record's angle),
    not after the reach has grown enough to believe it (before: dropped silently, and
    replies in that frame were taken once the host had been blind long enough)."""
    off = 11.5
    tr, port, fp = _armed_transport(off)
    a0 = _count_deg(math.radians(off))
    port.inbuf += hp.reply_packet(1, a0)
    tr.receive()
    tr.send(fp.Force(0, (0.01,)))
    n_written = len(port.written)
    port.inbuf += hp.reply_packet(1, a0 + 45.0)
    assert not [m for m in tr.receive() if isinstance(m, fp.State)]
    assert tr.stats["resyncs"] == 1
    resync = port.written[n_written]
    zero = tr.driver.encode_force(0.0)
    assert resync.startswith(zero) and resync.endswith(zero)
    # the set-up's encoder offset: the last record's angle (one record: no velocity)
    i = resync.index(hp.setup_packet(1, offset_deg=math.degrees(math.radians(a0)))[:8])
    # binary32's rounding of the angle (2^-24) after radians -> degrees (two roundings)
    assert struct.unpack_from("<f", resync, i + 8)[0] == pytest.approx(
        a0, rel=2.0 ** -24 + rel_tol(2))
    tr.close()


def _board():
    from hapsim.emulated.driver_mock import HaplyDevice
    from hapsim.scene import Device, Excitation
    return HaplyDevice(Device(mass=J, friction=1e-3, delay=1), 1000.0, Excitation(x0=0.2))


def test_a_single_read_of_an_empty_buffer_is_255():
    """The firmware's single ``SerialUSB.read()`` of a byte not arrived gives 255 (its -1
    stored in a byte); only ``readBytes`` waits. A write whose command byte was lost
    starts a set-up out of its torque bytes: with the masks read from what came and 255
    for the rest (4 encoders, 255 analog and PWM pins, all invalid), it waits only for
    the 32 bytes of 4 encoders' parameters, and the host's later writes are commands
    again (before: the model waited for every byte the garbage asked for, up to 556, and
    the host's re-synchronisation needed 556 zeros; on the board those 278 resets take
    14 ms of 50 us passes with the torque held)."""
    drv = get_driver("haply", device_id=1, offset_deg=11.46)
    cd = CommandDecoder(absent=255)
    w = drv.encode_force(0.1)                        # [2][1] cd cc cc 3d
    cmds = cd.feed(drv.arm()[:-6] + w[1:])           # set-up: addr 0xcd, motors 3 and 4,
    # (the arming on a fresh board: its zero write to an id with no motor is [2][1], its
    # torque bytes and the 32 zeros 18 resets, 2 no-commands, its set-up; the garbage
    # set-up is not taken yet: it waits in its readBytes)
    assert [c[0] for c in cmds] == ["write"] + ["reset"] * 18 + ["setup"]
    # its encoder mask, 4 directions, the pin counts and pins not there: 255 each
    assert cd.stats["absent"] == 1 + 4 + 1 + 255 + 1 + 255
    assert cd.feed(b"") == []
    got = []
    for _ in range(6):
        got += cd.feed(drv.encode_force(0.05))       # 6 bytes a write: 32 swallowed
    assert [c[0] for c in got] == ["setup"]          # the readBytes filled after 6 writes
    assert cd.motor_addr == [0, 0, 0xCD, 0xCD] and cd.encoder_addr == [0xCD] * 4
    assert [c[0] for c in cd.feed(drv.encode_force(0.05))] == ["write"]
    with pytest.raises(ValueError, match="absent"):
        CommandDecoder(absent=0)


@pytest.mark.parametrize("seed", range(25))
def test_the_resync_puts_any_board_back_in_step_at_zero_torque(seed):
    """Whatever the board's parser is inside (random writes with bytes lost at random,
    random garbage between), the re-synchronisation's 62 bytes leave it set up for the
    joint (motor 1 and encoder 1 at the id, the offset sent) at zero torque, its reply the
    set-up's offset; the board's passes for it end within 22 passes and two set-ups'
    2 ms (1 zero write, 16 resets, 2 no-commands, at most 1 garbage set-up finishing, the
    set-up, the zero write)."""
    rng = np.random.default_rng(1000 + seed)
    drv = get_driver("haply", device_id=1, offset_deg=11.46)
    b = _board()
    t = 0.0
    b.feed(drv.arm(), t)
    for k in range(int(rng.integers(1, 40))):
        t += 1e-3
        w = bytearray(drv.encode_force(float(rng.uniform(-0.123, 0.123))))
        if rng.random() < 0.3:
            del w[int(rng.integers(0, len(w)))]
        if rng.random() < 0.1:
            w += bytes(rng.integers(0, 256, int(rng.integers(1, 12)), dtype=np.uint8))
        b.feed(bytes(w), t)
    t = max(t + 1e-3, b._busy_until)                 # the board caught up with its passes
    x = float(rng.uniform(-0.5, 0.5))
    rep = b.feed(drv.resync(x), t)
    cd = b.decoder
    assert cd.motor_addr[0] == 1 and cd.encoder_addr[0] == 1
    assert b.settles_on() == 0.0
    assert rep[-5:][0] == 1
    got = struct.unpack("<f", rep[-4:])[0]
    # two whole counts (the board's count and the set-up's offset each round to one),
    # plus binary32's rounding of the angle sent and of the angle read (2^-24 each)
    assert abs(got - math.degrees(x)) <= (2 * 360.0 / RES + 2 * 2.0 ** -24 * abs(got)
                                          + rel_tol(3) * abs(math.degrees(x)))
    assert b.ready_at - t <= 22 * b.PASS_S + 2 * b.SETUP_S + 1e-12


@pytest.mark.parametrize("seed", range(8))
def test_a_board_that_lost_its_set_up_is_found_in_five_writes(seed):
    """A board with no encoder at the id (a reset or a garbage set-up forgot it) answers
    each write with the id alone: the decoder counts a desync once its buffer holds three
    of them in a row with no reply (the fifth write, a reply's length), not after
    :data:`~hapsim.drivers.haply.DESYNC_BYTES` of them (before: 11 writes, 11 ms at 1 kHz
    with the board holding whatever torque it had). Replies with one byte lost on the way
    back (the id and 3 bytes, or 4 bytes of the angle) are never taken for it."""
    rng = np.random.default_rng(200 + seed)
    dec = hp.ReplyDecoder(1, resolution=RES, accel=ALPHA)
    dec.elapsed(1e-3)
    a = 0.0
    n_faults = 0
    for k in range(400):
        a += float(rng.uniform(-0.05, 0.05))
        r = bytearray(hp.reply_packet(1, _count_deg(math.radians(a))))
        if k % 3 == 0:                                # one byte lost, one reply in three
            del r[int(rng.integers(0, 5))]
            n_faults += 1
        dec.feed(bytes(r))
    assert dec.stats["desync"] == 0 and dec.stats["lone"] == 0 and n_faults > 100
    for w in range(1, 12):
        dec.feed(bytes([1]))
        if dec.stats["desync"]:
            break
    assert w == 5 and dec.stats["lone"] == 1


class _BoardPort(_Port):
    """The emulated M3 board behind the port, stepped one period per write (lockstep, by
    name: what is tested is which readings the host believes, not timing): host byte
    ``drop`` of the first write (the arming) lost; each reply's angle is recorded with the
    board's true joint angle when it was sampled."""

    def __init__(self, board, drop):
        super().__init__()
        self.board, self.drop, self.n = board, drop, 0
        self.sent = {}

    def write(self, data):
        data = bytes(data)
        self.n += 1
        if self.n == 1:
            data = data[:self.drop] + data[self.drop + 1:]
        rep = self.board.feed(data)
        th = self.board.physics.sample()
        for i in range(0, len(rep) - 4):
            if rep[i] == 1 and (len(rep) - i) % 5 == 0:
                self.sent.setdefault(struct.unpack_from("<f", rep, i + 1)[0], th)
        self.inbuf += rep
        return len(data)


def test_a_byte_lost_in_the_arming_lockstep():
    """One host byte lost anywhere in the arming's set-up or its closing zero write (each
    position in turn), the board stepped per write: every reading the host believes is a
    reply the board sent, within 0.1 rad of where the joint truly was (one count, 1.3
    mrad, plus the frame error of a re-synchronisation: at most the reach over the
    25 ms a detection may take, 123 rad/s^2 x (0.025 s)^2 = 0.077 rad). Before: readings
    in a corrupted set-up's frame were believed, 11 rad from the joint here (on the
    wall-clock board in process: 0.2 to 2.6 rad off, and for 3 of the 24 positions bytes
    the board never sent as a reply)."""
    import firmware_protocol as fp
    from hapsim.emulated.driver_mock import HaplyDevice
    from hapsim.drivers.transport import DriverTransport
    from hapsim.scene import Device, Excitation
    drv = get_driver("haply", device_id=1, offset_deg=math.degrees(0.2))
    n = len(drv.arm())
    worst = 0.0
    for drop in range(n - 24, n):               # the set-up (16 bytes), the zero write
        board = HaplyDevice(Device(mass=J, friction=1e-3, delay=1), 1000.0,
                            Excitation(x0=0.2), clock="lockstep")
        tr = DriverTransport(drv, "loop://", inertia=J)
        tr._ser.close()
        port = _BoardPort(board, drop)
        tr._ser = port
        tr.send(fp.Config(1000.0, 5000, 10.0))
        x = 0.2
        for k in range(120):
            for m in tr.receive(0.0):
                if isinstance(m, fp.State):
                    x = m.position[0]
                    a = struct.unpack("<f", struct.pack("<f", math.degrees(x)))[0]
                    assert a in port.sent, (drop, k, x)
                    worst = max(worst, abs(x - port.sent[a]))
            tr.send(fp.Force(k, (-0.5 * x,)))
        tr.close()
        assert board.settles_on() == 0.0
    assert worst <= 0.1, worst

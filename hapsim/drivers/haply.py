"""Haply M3 board (Arduino Due, native USB): one joint driven as a 1-DoF rotary axis.

Layout, as the published board firmware reads and writes it (Haply "Arduino firmware"
V1.5, S. Ding and C. Gallacher, 2017, functions ``setup_device``, ``write_states``,
``read_states``; the hAPI hosts build the same bytes). Floats are IEEE-754 binary32,
little-endian; the baud rate is irrelevant (USB CDC).

host -> device ::

    reset  [0][id]
    setup  [1][id][motor mask][direction per motor][encoder mask][direction per encoder]
           [n analog][pin ...][n pwm][pin ...][per encoder: float32 offset deg,
           float32 counts per revolution]
    write  [2][id][one byte per PWM pin of id][float32 torque N m per motor of id]

device -> host, after each write only ::

    [id][float32 per analog pin of id][float32 angle in degrees per encoder of id]

The board clamps the torque to 0.123 N m. This driver sets up motor port 1 and encoder
port 1 (no analog pin, no PWM pin), so a write is 6 bytes and a reply 5: ``[id][angle]``.

What the board does not do (read from the firmware):

- **no watchdog**: the motor's PWM duty is only set by a write; reset (``reset_haply``)
  and set-up (``setup_device`` -> ``reset_device``) clear the ports' addresses and the PWM
  *pins*, not the motor's duty, so the board holds the last torque when the host stops
  talking, through a reset and through a set-up. The host therefore commands zero torque
  first (in :meth:`HaplyM3.arm` and :meth:`HaplyM3.resync`) and on every end (the
  transport's STOP and close).
- **no framing**: the board reads one command byte per pass and then the bytes the
  command's layout says, so one lost or extra host byte shifts its parser: later bytes
  are read as other commands (a reset forgets the set-up: writes are then answered by
  the 1-byte ``[id]``; a set-up out of garbage sets up other ports and ids). Replies are
  checked for their length and format (:class:`ReplyDecoder`: the id, and an angle that
  is a whole number of encoder counts within range, within the reach the torque clamp
  and the joint's inertia allow since the last reply taken: :meth:`ReplyDecoder.
  reach_deg`; no reply is taken unchecked); more bytes that make no reply than
  two faulty replies explain mean the board lost its place (``desync``), and the host re-synchronises it
  (:meth:`HaplyM3.resync`: :data:`LONGEST_WAIT` zero bytes, which any command the board
  is inside takes as zero torque, encoder parameters or a harmless reset, then the set-up
  and a zero-torque write). A single ``SerialUSB.read()`` of an empty buffer returns -1
  (the byte 255) and does not wait; only ``readBytes`` does (the board's parser, on the
  device side of the wire: :class:`hapsim.emulated.haply_firmware.CommandDecoder`).
"""

from __future__ import annotations

import math
import struct
import time

from hapsim.drivers.base import AlignedDecoder, Driver, MappedDecoder

__all__ = ["HaplyM3", "DEFAULT_ID", "MAX_TORQUE", "setup_packet", "write_packet", "reply_packet",
           "ReplyDecoder", "LONGEST_COMMAND", "LONGEST_WAIT", "DESYNC_BYTES",
           "resync_bytes", "ResyncRule"]

#: The board's torque clamp [N m] (firmware ``MAX_TORQUE``).
MAX_TORQUE = 0.123
CMD_RESET, CMD_SETUP, CMD_WRITE = 0, 1, 2
_F = struct.Struct("<f")
#: Longest command the board can be inside [bytes]: a set-up with 4 motors, 4 encoders,
#: 255 analog pins and 255 PWM pins (1 + 1 + 1 + 4 + 1 + 4 + 1 + 255 + 1 + 255 + 4 * 8).
LONGEST_COMMAND = 556
#: Longest wait the firmware can be inside a command for [bytes]: a ``readBytes`` of 4
#: encoders' parameters (8 bytes each, ``setup_device``, ``Haply_M3_Firmware_V1_5.h`` line
#: 188; a write's torques are at most 4 x 4, line 218). Its single reads do not wait (an
#: empty buffer reads 255: :class:`hapsim.emulated.haply_firmware.CommandDecoder`), so a
#: re-synchronisation's zeros need only outlast this, not :data:`LONGEST_COMMAND`.
LONGEST_WAIT = 32
#: The address the host gives the joint by default: a byte that is no command (0 reset,
#: 1 set-up, 2 write). A host byte lost makes the board read the write after it shifted
#: by one: its second byte, the address, as a command. Address 1 (the default before) is
#: the set-up's code: the board read a garbage set-up out of the next bytes, forgot its
#: own (the motor holding its torque, the writes swallowed or answered by the address
#: alone) until the host found it out, ~12 ms later (median), and re-synchronised it, at an
#: encoder offset that was the host's estimate: at 1 byte in 200 lost each way, ~25
#: re-synchronisations a run of 1.5 s, the joint's frame walking off by their errors, and
#: 5 of 16 runs ended on the force at the limit (simulated time, 3 % of ticks stalled).
#: An address that is no command is skipped: the lost byte costs the torque of one write
#: (its float completed by the next write's first byte, ~0) and one answer, and the board
#: is back in step at the next write (0.5 re-synchronisations a run, median; no safety
#: stop in those 16, the joint never past its start).
DEFAULT_ID = 3
#: Bytes skipped since the last good reply that mean the board lost its place: more than
#: two replies' worth of single faults on the way back (a lost byte skips at most 4 bytes,
#: a corrupted one 5); a board that lost its set-up answers 1 byte per write, so this is
#: about 11 writes.
DESYNC_BYTES = 11

LIMITS = """\
Haply M3 protocol limits (hapsim --driver haply):
  host-clocked only: the board answers each write and has no sequence numbers, so the
    loop runs on the host's clock and the delay d cannot be measured (the scene's
    device.delay is taken as given)
  no start byte, no checksum: a lost or corrupted byte shifts or alters a reply; the
    decoder realigns on the device id and a plausible angle, but a corrupted value byte
    is a wrong angle or torque
  units: one joint, rotary: the scene's mass is an inertia [kg m^2], stiffness
    [N m/rad], damping [N m s/rad]; angle resolution 360/counts-per-revolution degrees
    (float32 on the wire), torque float32 clamped to 0.123 N m by the board"""


def setup_packet(device_id: int, *, motor_port: int = 1, encoder_port: int = 1,
                 direction: int = 0, offset_deg: float = 0.0, resolution: float = 4880.0,
                 motor_direction: int | None = None) -> bytes:
    """Set-up command for one motor and one encoder (module notes).

    Parameters
    ----------
    device_id : int, 0..255
    motor_port, encoder_port : int, 1..4
        Board ports.
    direction : {0, 1}
        Rotational direction byte of the encoder (and of the motor when
        ``motor_direction`` is None).
    motor_direction : {0, 1}, optional
        Rotational direction byte of the motor.
    offset_deg : float
        Encoder offset [deg].
    resolution : float
        Encoder counts per revolution.

    Returns
    -------
    bytes
    """
    md = direction if motor_direction is None else motor_direction
    return (bytes([CMD_SETUP, device_id & 0xFF, 1 << (motor_port - 1), md,
                   1 << (encoder_port - 1), direction, 0, 0])
            + _F.pack(offset_deg) + _F.pack(resolution))


def write_packet(device_id: int, torque: float) -> bytes:
    """Write command ``[2][id][float32 torque]`` (no PWM pin set up)."""
    return bytes([CMD_WRITE, device_id & 0xFF]) + _F.pack(torque)


def reply_packet(device_id: int, angle_deg: float) -> bytes:
    """Reply ``[id][float32 angle deg]`` (one encoder, no analog pin)."""
    return bytes([device_id & 0xFF]) + _F.pack(angle_deg)


def resync_bytes(zero: bytes, setup: bytes, zeros: int = LONGEST_COMMAND) -> bytes:
    """Bytes that put a board back in step whatever its parser is inside, zero torque
    first (module notes; the 1-DoF joint's and the 2DIY's): the zero-torque write
    ``zero`` (taken if the board is in step), :data:`LONGEST_COMMAND` zero bytes (inside
    a write they are zero torque, elsewhere resets, which hold the torque), two bytes 3
    (no command: the address of a reset the zeros ended inside, or nothing), the set-up
    ``setup``, and ``zero`` again, whose reply is the next sample.

    Parameters
    ----------
    zero : bytes
        The zero-torque write of the device's id.
    setup : bytes
        Its set-up.
    zeros : int
        Zero bytes: :data:`LONGEST_COMMAND` for a board model whose single reads wait
        (the 2DIY's), :data:`LONGEST_WAIT` for the firmware's (whose single reads of an
        empty buffer give 255: only a ``readBytes`` waits).

    Returns
    -------
    bytes
    """
    return zero + bytes(int(zeros)) + bytes((3, 3)) + setup + zero


class ResyncRule:
    """When the host re-synchronises an unframed board (:func:`resync_bytes`): the reply
    decoder counted a ``desync`` (bytes that make no reply: module notes), or more than
    ``silent`` writes went unanswered (the board may be inside a garbage command that
    swallows them).

    Parameters
    ----------
    stats : dict
        The reply decoder's counters (its ``desync``, read live).
    silent : int
        Unanswered writes allowed (the real-time loop, whose replies lag a tick or more,
        allows more than a lockstep one).

    Attributes
    ----------
    count : int
        Re-synchronisations it called for.
    """

    def __init__(self, stats: dict, silent: int) -> None:
        self._stats = stats
        self._seen = stats.get("desync", 0)
        self.silent = int(silent)
        self.count = 0

    def due(self, unanswered: int) -> bool:
        """Whether to re-synchronise now (counted when it is).

        Parameters
        ----------
        unanswered : int
            Writes sent since the last reply (or since the arming).

        Returns
        -------
        bool
        """
        d = self._stats.get("desync", 0)
        if d != self._seen or unanswered > self.silent:
            self._seen = d
            self.count += 1
            return True
        return False


class ReplyDecoder(AlignedDecoder):
    """Host side: 5-byte replies ``[id][float32 deg]`` out of a byte stream (or, with
    ``angles`` encoders of one id, ``1 + 4 angles``-byte replies, each angle checked).

    A reply is taken where the id matches and the angle is finite, within
    ``max_angle_deg``, within ``max_step_deg`` of where the last two replies say the joint
    is going, and a whole number of encoder counts (the firmware sends
    ``360 * count / resolution``: the window ``01 01 01 3f c5``, -3056.06 deg, is 41426.4
    counts at 4880 per revolution, no reply); otherwise one byte is dropped and the next
    position tried. :data:`DESYNC_BYTES` or more bytes dropped since the last reply mean the
    stream lost its format: the board answers something else than the replies it was set
    up for (counted in ``desync``, once per run of bad bytes, again every 100 bytes).

    Parameters
    ----------
    device_id : int
    max_angle_deg : float
        Largest plausible angle [deg].
    resolution : float or None
        Encoder counts per revolution (None: the whole-count check is off).
    max_step_deg : float
        Largest distance of a reply from the linear prediction of the last two taken
        [deg] when it comes within ``period_s`` of the last (2 deg: an acceleration of
        35000 rad/s^2 at 1 kHz, or a missed reply at 30 rad/s); a reply farther off is
        misaligned or corrupted. Later replies get the reach of :meth:`reach_deg` over
        the time that passed: a board on its own clock moved on while the host was late
        or stalled, and that is no evidence of a lost place.
    period_s : float
        The period the step bound is stated for [s] (1 ms).
    clock : callable
        Monotonic time [s] of a read (``time.monotonic``): the time between two reads is
        the elapsed time of :meth:`reach_deg` unless the host states it
        (:meth:`elapsed`).
    angles : int, optional
        Encoders in a reply (1: the angle is returned as a float; more: a tuple, in port
        order, and ``resolution`` may give one per encoder).
    accel : float, optional
        Largest angular acceleration of the joint(s) [rad/s^2]: the board's torque clamp
        over the smallest joint inertia (:meth:`set_accel`). None: ``max_step_deg`` per
        period squared (no physics known: 35000 rad/s^2 at 1 kHz).
    arm_deg : float or tuple, optional
        The angle(s) the arming's set-up sets the encoder(s) to [deg]: the replies after
        an arming (:meth:`reset_prediction`) are checked against it, not taken blind.

    Attributes
    ----------
    stats : dict
        ``frames`` (replies), ``skipped`` (bytes dropped realigning), ``desync``,
        ``damaged`` (replies the dropped bytes held, short of a desync), ``unreachable``
        (well-formed replies out of the reach of :meth:`reach_deg`: a frame another
        set-up made, or a misaligned window that looked like a reply), ``lone`` (desyncs
        counted at once on three writes answered by the id alone: a board that lost its
        set-up; before, after :data:`DESYNC_BYTES` of them).
    """

    length = 5

    def __init__(self, device_id: int, max_angle_deg: float = 3600.0,
                 resolution=None, max_step_deg: float = 2.0, angles: int = 1,
                 period_s: float = 1e-3, clock=time.monotonic, accel=None,
                 arm_deg=None) -> None:
        super().__init__()
        self.period_s = float(period_s)
        self._clock = clock
        self._t_read = self._t_prev = None
        self._tau = None
        self._speed = None                # a bound on the speed [deg/s] (elapsed)
        self._accel_deg = None
        self.set_accel(accel)
        self.arm_deg = arm_deg
        self.angles = int(angles)
        self.length = 1 + 4 * self.angles
        self._fmt = struct.Struct("<" + "f" * self.angles)
        self.max_step = float(max_step_deg)
        self._prev = self._prev2 = None
        self.id = device_id & 0xFF
        self.max = float(max_angle_deg)
        if resolution is None:
            self.res = None
        elif isinstance(resolution, (int, float)):
            self.res = (float(resolution),) * self.angles
        else:
            self.res = tuple(float(r) for r in resolution)
        # one encoder count [deg] per angle (0: no whole-count check, no count term)
        self._count = tuple(360.0 / r if r > 0 and math.isfinite(r) else 0.0
                            for r in self.res) if self.res else (0.0,) * self.angles
        self.stats["desync"] = 0
        self.stats["damaged"] = 0
        self.stats["unreachable"] = 0
        self.stats["lone"] = 0
        self._lone = False
        self._bad = 0
        self._free = 0

    def feed(self, data: bytes) -> list:
        """Replies out of the bytes of one read (the read's time scales the step bound:
        ``max_step_deg``).

        Parameters
        ----------
        data : bytes

        Returns
        -------
        list
            The angles [deg] decoded (tuples with several encoders).
        """
        self._t_read = self._clock()
        return super().feed(data)

    def clear(self) -> None:
        """Drop the bytes held and the run of dropped bytes counted so far: a re-arming
        drains the link, and the bytes skipped before it are no reply's that follows (left
        counted, the first good reply after the set-up was taken as answering a damaged
        reply before it: the set-up's reply read as the next write's, a bad set-up)."""
        super().clear()
        self._bad = 0

    def set_accel(self, accel) -> None:
        """State the joint's largest angular acceleration [rad/s^2] (None: the default of
        the class notes): the board's torque clamp over the smallest joint inertia (a hand
        on the handle only adds inertia).

        Raises
        ------
        ValueError
            ``accel`` not finite and > 0.
        """
        if accel is None:
            self._accel_deg = None
            return
        if not (math.isfinite(accel) and accel > 0):
            raise ValueError(f"accel must be a finite acceleration > 0 [rad/s^2], got "
                             f"{accel!r}")
        self._accel_deg = math.degrees(float(accel))

    def elapsed(self, tau, speed_deg=None) -> None:
        """The host states the time [s] from the write the last reply taken answered to
        now (an upper bound of the time between the two samples: the board samples when
        a write arrives), for the replies of the next reads; None: the time between the
        reads (the class notes). A host that knows its writes' times states it: a reply
        read late was still sampled when its write arrived.

        ``speed_deg``: a bound on the joint's speed at the last reply taken [deg/s], from
        the host's times of two replies far enough apart
        (:meth:`hapsim.drivers.transport.DriverTransport._speed_bound`), or None. The
        last two replies' step stands for the speed over one period; two replies sampled
        close together (a late board's backlog, 50 us apart) make it ~0, and a joint
        moving at speed was then "out of reach" a few ms later. With a bound, the speed
        the reach assumes is never below it (:meth:`reach_deg`)."""
        self._tau = None if tau is None else float(tau)
        self._speed = None if speed_deg is None else float(speed_deg)

    def reach_deg(self, k: int, tau) -> float:
        """How far [deg] a reply ``tau`` seconds after the last one taken may be from the
        linear prediction of the last two (one period ahead), encoder ``k``: the motion
        the largest acceleration allows, with the prediction's lag and the encoder's whole
        counts.

        With r = max(1, tau / T) (T = ``period_s``), v = |q1 - q2| the last step and
        alpha the acceleration [deg/s^2] (``accel``): the joint is then within
        ``(r - 1) v + alpha tau^2`` of the prediction (Taylor's theorem: 1/2 alpha tau^2,
        a factor 2 of margin for the velocity's own error), never less than
        ``max_step_deg``, plus ``2 r + 2`` counts (each reading is a whole count: the
        prediction off by 3, its slope by 2 a period; the reply by 1). The same rule the
        2DIY's host states its elapsed time to (:mod:`hapsim.pipeline.haply2_record`).

        Parameters
        ----------
        k : int
            Encoder index in the reply.
        tau : float or None
            Time since the last reply taken [s] (None: one period).

        Returns
        -------
        float
        """
        T = self.period_s
        r = 1.0 if tau is None else max(1.0, tau / T)
        tau = r * T
        acc = self._accel_deg if self._accel_deg is not None else self.max_step / (T * T)
        v = self._step_v(k)
        step = max(self.max_step, (r - 1.0) * v + acc * tau * tau)
        return step + (2.0 * r + 2.0) * self._count[k]

    def _step_v(self, k: int) -> float:
        """The joint's motion per period the reach assumes, encoder ``k`` [deg]: the last
        two replies' step, never below the host's stated speed bound times the period
        (:meth:`elapsed`)."""
        v = 0.0
        if self._prev is not None and self._prev2 is not None:
            v = abs(self._prev[k] - self._prev2[k])
            v = v if v == v else 0.0
        if self._speed is not None:
            v = max(v, self._speed * self.period_s)
        return v

    def reset_prediction(self, jumps: int = 1, anchor=None) -> None:
        """Forget the last replies (an arming: the angles start afresh at the set-up's
        offset). With an anchor (``anchor``, else the decoder's ``arm_deg``) the
        prediction restarts there, with no velocity: the next replies are checked against
        it (the reach of :meth:`reach_deg` from the arming on), so a reply of a set-up the
        stream corrupted (another offset: a frame no motion reaches) is not taken; an
        answer from before the set-up, at the old angle, is dropped too. Without one, the
        next ``jumps`` replies are taken without the step check, each restarting the
        prediction (the 2DIY's arming checks its first reply against its offsets
        itself).

        Parameters
        ----------
        jumps : int
            Replies taken unchecked when there is no anchor.
        anchor : float or tuple, optional
            The set-up's angle(s) [deg].
        """
        anchor = self.arm_deg if anchor is None else anchor
        self._prev2 = None
        if anchor is None:
            self._prev = None
            self._free = int(jumps)
            return
        a = (anchor,) if isinstance(anchor, (int, float)) else tuple(anchor)
        self._prev = tuple(float(x) for x in a)
        self._free = 0
        self._t_prev = self._clock()

    def parse(self, buf):
        """The angle [deg] (a tuple of ``angles``, port order, when more than one) of a
        reply at the start of ``buf``, or None."""
        # (index loops, floats only: the real-time loops decode without allocating)
        self._lone = False
        if buf[0] != self.id:
            return None
        a = self._fmt.unpack_from(buf, 1)
        res = self.res
        na = self.angles
        # three id bytes in a row that make no reply: writes answered by the id alone,
        # as a board answers when it has no encoder at that address (a reset or a set-up
        # out of garbage forgot its set-up: Haply_M3_Firmware_V1_5.h read_states); a byte
        # lost or corrupted on the way back leaves the id and 3 or 4 bytes of an angle
        lone = buf[1] == self.id and buf[2] == self.id
        k = 0
        while k < na:
            v = a[k]
            if not (math.isfinite(v) and abs(v) <= self.max):
                self._lone = lone
                return None
            if res is not None:
                # the firmware's 360 * count / resolution, rounded once to binary32: a
                # count of 0 is exactly 0.0 (a tiny garbage float is no reply); the
                # nearest whole count as a float (remainder rounds half to even, as
                # round does)
                n = v * res[k] / 360.0
                n -= math.remainder(n, 1.0)
                want = 360.0 * n / res[k]
                if abs(v - want) > 1e-6 * abs(want):
                    self._lone = lone
                    return None
            k += 1
        if self._free:
            # a jump allowed (reset_prediction): predict from this reply on
            self._free -= 1
            self._t_prev = self._t_read
            self._prev2, self._prev = None, a
            return a[0] if self.angles == 1 else a
        if self._prev is not None:
            # a flipped exponent bit is still a whole count (x 2^k, half the time), and a
            # set-up the stream corrupted answers whole counts of another offset: no
            # joint moves that far from where its last two replies say it is going, in the
            # time that passed (reach_deg: the host's stated time, else the reads')
            tau = self._tau
            if tau is None and self._t_read is not None and self._t_prev is not None:
                tau = self._t_read - self._t_prev
            k = 0
            while k < na:
                step = self.reach_deg(k, tau)
                p1 = self._prev[k]
                guess = p1 if self._prev2 is None else 2.0 * p1 - self._prev2[k]
                # off the linear prediction, a reply is still a joint's motion when it
                # moved no more than last time plus the step: the board samples when a
                # write arrives, so two replies a late host's writes brought close
                # together are close in time too, though the last two were far apart
                if abs(a[k] - guess) > step and (
                        self._prev2 is None
                        or abs(a[k] - p1) > self._step_v(k) + step):
                    # a well-formed reply no motion reaches: counted (the host takes it
                    # for evidence that the board answers in another frame)
                    self.stats["unreachable"] += 1
                    return None
                k += 1
        self._t_prev = self._t_read
        self._prev2, self._prev = self._prev, a
        return a[0] if self.angles == 1 else a

    def accept(self, value) -> bool:
        """A reply taken: the run of dropped bytes before it ends; the replies it held
        are counted in ``damaged`` (a run of ``s`` bytes held ``ceil(s / length)``: a
        byte lost leaves ``length - 1``, a corrupted reply ``length``; a run long enough
        to be a desync is the re-synchronisation's, not counted)."""
        if self._bad:
            if self._bad < DESYNC_BYTES:
                self.stats["damaged"] += -(-self._bad // self.length)
            self._bad = 0
        return True

    def on_skip(self) -> None:
        """A byte dropped: after :data:`DESYNC_BYTES` in a row (and every 100 more while
        it lasts) a ``desync`` is counted. The prediction is kept: the re-synchronisation
        sets the encoder to the host's estimate of where the joint is, so the replies after
        it are still within reach of the last one taken (before, the next reply was taken
        unchecked: a garbage one, whole counts of 7.4 rad, was believed and stopped the
        run)."""
        self._bad += 1
        if self._lone and self._bad < DESYNC_BYTES:
            # the board answers the id alone (parse): it lost its set-up; a desync now,
            # not after DESYNC_BYTES of them (the run counts as that long)
            self._lone = False
            self._bad = DESYNC_BYTES
            self.stats["desync"] += 1
            self.stats["lone"] += 1
            return
        if self._bad % 100 == DESYNC_BYTES:
            self.stats["desync"] += 1


class HaplyM3(Driver):
    """A Haply M3 board joint as a 1-DoF rotary axis (module notes).

    Parameters
    ----------
    device_id : int, 1..255
        The address the host gives the joint's ports in the set-up and names in each
        write (0 is refused: after a reset every PWM pin's address is 0, so a write to id
        0 would be read as 14 PWM bytes first). The board has no id of its own: firmware
        V1.5 stores the set-up's address and answers a write with the write's address, so
        any id works and there is nothing to identify. The default, :data:`DEFAULT_ID`,
        is no command byte: see there (1, the default before, is the set-up's).
    resolution : float > 0
        Encoder counts per revolution (sent in the set-up).
    direction : {0, 1}
        Rotational direction byte of the encoder (firmware CW = 0, CCW = 1: CCW swaps
        the encoder's two pins, ``initialize_encoder``): the sense in which the angle
        counts up, a choice of the host's.
    motor_direction : {0, 1}, optional
        Rotational direction byte of the motor (firmware ``create_torque``: it flips the
        direction pin). Which byte makes a positive torque turn the joint the way its
        angle counts up depends on the motor's and the encoder's wiring: ``hapsim
        identify --driver haply`` finds it with a torque pulse of each sign
        (:func:`hapsim.drivers.haply_probe.find_direction`); None: the same byte as
        ``direction``. A wrong one is positive feedback: every spring pushes away.
    offset_deg : float
        The joint's angle when it is armed [deg]: the set-up sets the encoder's count to
        it (firmware ``initialize_encoder``), so angles are read from the pose the joint
        is held at when hapsim arms it.

    Raises
    ------
    ConfigError
        A bad id, resolution or direction (the key and the valid range named).
    """

    position_rel = 2.0 ** -24        # binary32 fields on the wire (round to nearest)
    force_rel = 2.0 ** -24

    name = "haply"
    baud = 115200                     # USB CDC: ignored
    rtscts = False
    native_rate_hz = 1000.0
    force_limit = MAX_TORQUE
    force_scale = 0.0
    limits = LIMITS
    unframed = True
    scale_option = "resolution"
    scale_kind = "position"
    #: ``hapsim identify`` finds the motor direction first (:mod:`hapsim.drivers.
    #: haply_probe`): a wrong one makes the excitation run away.
    probes_direction = True
    answering_firmware = "Haply M3 firmware V1.5 layout (one reply per write)"
    #: Its decoder takes the joint's inertia (:meth:`decoder`): the transport states it
    #: and the time since the last record's command before each read.
    checks_reach = True
    #: Firmware V1.5 sets the torque in the pass that takes a write and holds it until the
    #: next (``loop``: ``write_states`` then ``read_states``; no watchdog, no tick): a
    #: hold is the time between two writes' arrivals (:attr:`Driver.holds_from_write`).
    holds_from_write = True

    def unknown_force_rows(self, columns: dict):
        """Rows whose torque the board may have parsed from the wrong bytes (a host byte
        lost or corrupted on its way), left out of the measurement.

        Firmware V1.5 reads a write's bytes by count (no start byte, no checksum:
        ``Haply_M3_Firmware_V1_5.ino``, ``loop``): with one byte of write ``w`` lost it
        completes that command with the first byte of write ``w + 1``, a torque float
        shifted by a byte, and answers only then, so the reply the host reads at tick
        ``w + 1`` is missing (that row is estimated, ``FLAG_ESTIMATED``); the bytes after
        it are parsed out of step (garbage torques, replies missing or damaged) until the
        board is back in step. Row ``r``'s reading is the reply to write ``r - 1``, and the
        torque of write ``w`` acts at row ``w + d`` (``d`` the loop's delay,
        :attr:`loop_delay`): a run of estimated rows ``[r0, r1]`` follows a write
        ``w >= r0 - 1`` parsed out of step, and the writes up to ``r1 - 1`` may be, so
        rows ``r0 - 1 + d .. r1 - 1 + d`` may hold an unknown torque. It leaves out rows
        ``r0 - 1 .. r1 + d``: those, ``d`` rows before them and one after; the fit
        drops each stretch's first ``d + 2`` rows after a cut as well (the torques in
        flight). A reply lost on its way back costs the same
        rows (the host cannot tell the two apart). Measured before (issue 29,
        ``tools/driver_timing.py``, 1 host byte in 200 lost, beside two CPU-bound
        processes at ``SCHED_FIFO``): the measured k 0.4 to 3.6 % off the prediction
        against a stated 0.3 to 0.5 %, "differs" in 3 of 4 seeds; with the replies' bytes
        lost instead, within in 4 of 4. With the cut: 1 host byte in 100 lost, 10 seeds,
        no "differs" (4 within, 4 not measurable for re-synchronisations, 2 too few
        cycles left to measure).

        The windows are in host ticks (``seq``): a command whose reply never came is an
        estimated row, or no row at all where the loop logged none for it (a gap in
        ``seq``: a lockstep mock's command asked again, as ``hapsim identify`` records
        it, or a re-synchronisation's skipped number). The same window is left out
        around such a gap: before, ``identify`` over a lockstep M3 with host bytes lost
        saw only gaps, and fitted the torques parsed from the wrong bytes after each
        as the ones sent.

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``flags``, and ``seq`` if given: each shape
            (n,); without ``seq``, or with one not increasing, row ``r`` is tick ``r``).

        Returns
        -------
        ndarray of bool, shape (n,), or None
            None when no tick's reply is missing.
        """
        import numpy as np     # here: building the CLI's parser loads no numpy
        from hapsim.drivers.base import FLAG_ESTIMATED
        flags = columns.get("flags")
        if flags is None:
            return None
        est = (np.asarray(flags).astype(np.int64) & FLAG_ESTIMATED) != 0
        n = est.size
        # the windows are counted in host ticks (the commands, ``seq``): a command no
        # record answered is an estimated row or, where the loop logged none for it (a
        # lockstep mock asked again, a re-synchronisation's skipped number), a gap in seq
        # -- the same missing reply
        seq = columns.get("seq")
        tick = None
        if seq is not None and np.shape(seq) == (n,) and n:
            s = np.asarray(seq, np.int64)
            if np.all(np.diff(s) >= 1):
                tick = s - s[0]
        if tick is None:
            tick = np.arange(n, dtype=np.int64)
        span = int(tick[-1]) + 1 if n else 0
        miss = np.ones(span, bool)
        miss[tick] = est                      # a logged row: missing when estimated
        if not miss.any():
            return None
        d = max(int(getattr(self, "loop_delay", 1) or 0), 0)
        # a difference array over the runs of missing ticks: +1 at t0 - 1, -1 after
        # t1 + d
        edge = np.diff(np.concatenate(([0], miss.astype(np.int8), [0])))
        r0, r1 = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1) - 1
        mark = np.zeros(span + 1, np.int64)
        np.add.at(mark, np.clip(r0 - 1, 0, span), 1)
        np.add.at(mark, np.clip(r1 + d + 1, 0, span), -1)
        return (np.cumsum(mark[:span]) > 0)[tick]

    def __init__(self, device_id: int | None = None, resolution: float = 4880.0,
                 direction: int = 0, offset_deg: float = 0.0,
                 motor_direction: int | None = None) -> None:
        from hapsim.errors import ConfigError
        if device_id is None:
            device_id = DEFAULT_ID
        if not 1 <= int(device_id) <= 255:
            raise ConfigError(f"device id must be 1..255 (0 is every PWM pin's address after "
                              f"a reset), got {device_id!r}", key="device_id")
        if not (math.isfinite(resolution) and resolution > 0):
            raise ConfigError(f"counts per revolution must be > 0, got {resolution!r}",
                              key="resolution")
        if direction not in (0, 1):
            raise ConfigError(f"direction must be 0 (CW) or 1 (CCW), got {direction!r}",
                              key="direction")
        if motor_direction is None:
            motor_direction = direction
        if motor_direction not in (0, 1):
            raise ConfigError(f"motor direction must be 0 (CW) or 1 (CCW), got "
                              f"{motor_direction!r}", key="motor_direction")
        self.motor_direction = int(motor_direction)
        self.id = int(device_id)
        self.device_id = self.id
        # the board holds it as binary32
        self.resolution = _F.unpack(_F.pack(float(resolution)))[0]
        self.direction = int(direction)
        if not math.isfinite(offset_deg):
            raise ConfigError(f"must be a finite angle [deg], got {offset_deg!r}",
                              key="offset_deg")
        self.offset_deg = float(offset_deg)
        self.position_scale = 2 * math.pi / self.resolution

    def stop_bytes(self, position: float = 0.0) -> bytes:
        """Zero torque whatever the board's parser is doing (:meth:`resync`): the board has
        no watchdog, so a zero write it misreads would leave the last torque on."""
        return self.resync(position)

    @classmethod
    def embedded_options(cls, options: dict, x0: float) -> dict:
        """``options`` with ``offset_deg`` at the start angle ``x0`` [rad] unless given:
        the board's set-up sets the encoder's count to the offset
        (``initialize_encoder``), so the embedded board is armed with the joint at the
        excitation's start (:meth:`hapsim.drivers.base.Driver.embedded_options`)."""
        out = dict(options)
        out.setdefault("offset_deg", math.degrees(x0))
        return out

    def mock_hardware(self) -> dict:
        """The mock's encoder: this many counts per revolution; its wiring: the one these
        direction bytes drive the right way (``motor_sign``, :class:`hapsim.emulated.driver_mock.
        HaplyDevice`)."""
        return {"cpr": self.resolution,
                "motor_sign": 1 if self.motor_direction == self.direction else -1}

    def resync(self, position: float = 0.0) -> bytes:
        """Put the board back in step, zero torque first (module notes): a zero-torque
        write (taken if the board is in step), :data:`LONGEST_WAIT` zero bytes (inside a
        write's ``readBytes`` they are zero torque, inside a set-up's its encoder
        parameters, elsewhere resets, which hold the torque), two bytes 3 (no command: the
        address of a reset the zeros ended inside, or nothing), the set-up, and a
        zero-torque write, whose reply is the next sample. 62 bytes, 19 passes of the
        board's loop and its set-up's 2 ms: the zero torque is at most ~3 ms away
        (before: 556 zeros, 278 passes of at least 50 us, 14 ms with the torque held).

        Parameters
        ----------
        position : float
            The joint's last angle read [rad]: the set-up's encoder offset, because the
            firmware sets the encoder's count to the offset (``initialize_encoder``), so
            the angle goes on from there instead of jumping to 0.

        Returns
        -------
        bytes
        """
        setup = setup_packet(self.id, resolution=self.resolution, direction=self.direction,
                             motor_direction=self.motor_direction,
                             offset_deg=math.degrees(position) if math.isfinite(position)
                             else 0.0)
        return resync_bytes(self.encode_force(0.0), setup, LONGEST_WAIT)

    def arm(self) -> bytes:
        """The re-synchronisation (:meth:`resync`, at the arming pose ``offset_deg``): the
        board may hold a torque from an earlier session and be anywhere in its parser."""
        return self.resync(math.radians(self.offset_deg))

    def rearm_anchor(self, position: float) -> float:
        """A re-arming keeps the board's frame: set up at ``position`` [rad], in [deg]."""
        return math.degrees(position)

    def encode_force(self, force: float) -> bytes:
        """Write of ``force`` [N m], clamped to the board's 0.123 N m (NaN/inf: 0)."""
        t = float(force) if math.isfinite(force) else 0.0
        return write_packet(self.id, max(-MAX_TORQUE, min(MAX_TORQUE, t)))

    def applied_force(self, force: float) -> float:
        """The torque the board receives [N m]: clamped, rounded to binary32."""
        return _F.unpack(self.encode_force(force)[2:])[0]

    def decoder(self, inertia: float | None = None):
        """A fresh host decoder returning the joint angle [rad] (whole encoder counts),
        anchored at each arming to the set-up's offset (``offset_deg``).

        Parameters
        ----------
        inertia : float, optional
            The joint's smallest inertia [kg m^2]: its replies are then believed only
            within the reach the board's torque clamp (0.123 N m) allows it
            (:meth:`ReplyDecoder.reach_deg`); None: the decoder's default.

        Returns
        -------
        MappedDecoder
        """
        accel = (MAX_TORQUE / float(inertia) if inertia is not None
                 and math.isfinite(inertia) and inertia > 0 else None)
        return MappedDecoder(ReplyDecoder(self.id, resolution=self.resolution, accel=accel,
                                          arm_deg=self.offset_deg), math.radians)

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

from hapsim.drivers.base import Driver, binary32_commands
from hapsim.drivers.decoders import MappedDecoder
from hapsim.drivers.haply_reply import DESYNC_BYTES, ReplyDecoder
from hapsim.option_values import option_value

__all__ = ["HaplyM3", "DEFAULT_ID", "MAX_TORQUE", "setup_packet", "write_packet", "reply_packet",
           "ReplyDecoder", "LONGEST_COMMAND", "LONGEST_WAIT", "DESYNC_BYTES",
           "resync_bytes", "ResyncRule"]

#: The board's torque clamp [N m] (firmware ``MAX_TORQUE``).
MAX_TORQUE = 0.123
CMD_RESET, CMD_SETUP, CMD_WRITE = 0, 1, 2
_F = struct.Struct("<f")
#: The largest finite binary32 (the board's floats): 3.4028235e38.
F32_MAX = float.fromhex("0x1.fffffep+127")
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
    """Write command ``[2][id][float32 torque]`` (no PWM pin set up).

    Parameters
    ----------
    device_id : int
        The board's id (its low byte).
    torque : float
        Motor 1's torque [N m] (binary32 on the wire).

    Returns
    -------
    bytes
        6 bytes.
    """
    return bytes([CMD_WRITE, device_id & 0xFF]) + _F.pack(torque)


def reply_packet(device_id: int, angle_deg: float) -> bytes:
    """Reply ``[id][float32 angle deg]`` (one encoder, no analog pin).

    Parameters
    ----------
    device_id : int
        The board's id (its low byte).
    angle_deg : float
        Encoder 1's angle [deg] (binary32 on the wire).

    Returns
    -------
    bytes
        5 bytes.
    """
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

    def answered(self) -> None:
        """A re-synchronisation made for another reason (the host watchdog's robust
        write, :mod:`hapsim.pipeline.haply2_record`): the desyncs counted so far are
        answered by it, and call for none more (not counted here)."""
        self._seen = self._stats.get("desync", 0)


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
    rotary = True
    #: ``hapsim identify --driver haply`` without a scene: a joint in the range of the
    #: shipped scene's (configs/haply.yaml: 0.001 kg m^2, 0.001 N m s/rad), and the
    #: scene's 0.2 rad of reach. hapsim's default mock device read in these units (0.1
    #: kg m^2, 0.5 N m s/rad) did not turn 3 counts under the board's 0.123 N m, and
    #: 0.01 rad spans 8 of its encoder's counts: "hardly moved".
    identify_device = {"mass": 0.001, "friction": 0.001}
    identify_envelope = 0.2
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
    #: Replies that came late but in order (``seq -> position``), filled by the transport
    #: (:class:`hapsim.drivers.late_replies.LateReplies`); None without one (an offline
    #: record: every estimated row is cut).
    late_answers = None

    def _late_rows(self, columns: dict):
        """Rows whose reply came late but in order (:attr:`late_answers`), shape (n,)
        bool, or None (none, or no ``seq`` to name them by)."""
        import numpy as np
        seq, late = columns.get("seq"), self.late_answers
        if not late or seq is None:
            return None
        rows = np.isin(np.asarray(seq, np.int64), np.fromiter(late, np.int64, len(late)))
        return rows if rows.any() else None

    def account(self, columns: dict, force):
        """:meth:`hapsim.drivers.base.Driver.account`, with the estimated rows whose
        replies came late but in order (:attr:`late_answers`) taken as answered: their
        commands reached the board and were parsed in step (firmware V1.5 answers each
        write it parses, in order), so the force applied from them is the one sent, not
        ambiguous between it and the one before.

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``flags``, ``seq``: shape (n,)).
        force : ndarray, shape (n,)
            The force each row's command carried [N m].

        Returns
        -------
        hapsim.applied.AppliedAccount or None
        """
        late = self._late_rows(columns)
        flags = columns.get("flags")
        if late is not None and flags is not None and getattr(flags, 'shape', None) == late.shape:
            from hapsim.drivers.base import FLAG_ESTIMATED
            columns = dict(columns)
            columns["flags"] = flags & ~(late.astype(flags.dtype) * FLAG_ESTIMATED)
        return super().account(columns, force)

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
        rows (the host cannot tell the two apart). An estimated row whose reply came late
        but in order (:attr:`late_answers`: read with every reply after it, none
        damaged) is no missing reply: its write was parsed in step, its torque is the one
        sent, and the row is kept (the measurement states its position's error, the
        estimate the loop stepped with; :mod:`hapsim.drivers.late_replies`). Before, each
        such row was cut with its neighbours, and beside two CPU-bound processes records
        were left in stretches too short to fit ("not measurable: too few cycles" in 3 of
        10 runs with 1 byte in 200 lost, 1 of 10 without; issue 29). Measured before (issue 29,
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
        late = self._late_rows(columns)
        if late is not None and late.shape == est.shape:
            est &= ~late                      # answered late, in order: a reading
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
                 motor_direction: int | None = None, torque_levels: int = 256) -> None:
        from hapsim.errors import ConfigError
        if torque_levels not in (256, 0):
            raise ConfigError(f"the board's torque levels: 256 (the 12-bit duty written at "
                              f"the Due's 8 bits, Haply_M3_Firmware_V1_5.h:489, pwm01.h) "
                              f"or 0 (a board that applies the float as it is), got "
                              f"{torque_levels!r}", key="torque_levels")
        #: The board's torque levels (:meth:`output_stage`): 256, or 0 for a board that
        #: applies the write's float as it is (no output stage).
        self.torque_levels = int(torque_levels)
        if device_id is None:
            device_id = DEFAULT_ID
        # (a device id of 0 is every PWM pin's address after a reset)
        device_id = option_value("device_id", device_id, low=1, high=255, whole=True)
        # (both binary32 on the wire: within its largest finite value)
        resolution = option_value("resolution", resolution, "counts per revolution", low=0,
                                  low_ok=False, high=F32_MAX)
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
        self.offset_deg = option_value("offset_deg", offset_deg, "deg", low=-F32_MAX,
                                       high=F32_MAX)
        self.position_scale = 2 * math.pi / self.resolution

    def stop_bytes(self, position: float = 0.0) -> bytes:
        """Zero torque whatever the board's parser is doing (:meth:`resync`): the board has
        no watchdog, so a zero write it misreads would leave the last torque on.

        Parameters
        ----------
        position : float
            The joint's last angle read [rad] (the set-up's offset, :meth:`resync`).

        Returns
        -------
        bytes
            :meth:`resync`'s 62 bytes.
        """
        return self.resync(position)

    @classmethod
    def embedded_options(cls, options: dict, x0: float) -> dict:
        """``options`` with ``offset_deg`` at the start angle ``x0`` [rad] unless given:
        the board's set-up sets the encoder's count to the offset
        (``initialize_encoder``), so the embedded board is armed with the joint at the
        excitation's start (:meth:`hapsim.drivers.base.Driver.embedded_options`).

        Parameters
        ----------
        options : dict
            The driver's keywords given.
        x0 : float
            The excitation's start angle [rad].

        Returns
        -------
        dict
            A new dict; ``options`` is not changed.
        """
        out = dict(options)
        out.setdefault("offset_deg", math.degrees(x0))
        return out

    def mock_hardware(self) -> dict:
        """The mock's encoder: this many counts per revolution; its wiring: the one these
        direction bytes drive the right way (``motor_sign``, :class:`hapsim.emulated.driver_mock.
        HaplyDevice`).

        Returns
        -------
        dict
            ``cpr`` (float, counts per revolution) and ``motor_sign`` (+1 or -1).
        """
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
        board may hold a torque from an earlier session and be anywhere in its parser.

        Returns
        -------
        bytes
        """
        return self.resync(math.radians(self.offset_deg))

    def rearm_anchor(self, position: float) -> float:
        """A re-arming keeps the board's frame: set up at ``position`` [rad], in [deg].

        Parameters
        ----------
        position : float
            The last angle read [rad].

        Returns
        -------
        float
            The same angle [deg] (the decoder's anchor).
        """
        return math.degrees(position)

    def encode_force(self, force: float) -> bytes:
        """Write of ``force`` [N m], clamped to the board's 0.123 N m (NaN/inf: 0).

        Parameters
        ----------
        force : float
            The torque to send [N m].

        Returns
        -------
        bytes
            The 6-byte write (:func:`write_packet`).
        """
        t = float(force) if math.isfinite(force) else 0.0
        return write_packet(self.id, max(-MAX_TORQUE, min(MAX_TORQUE, t)))

    def applied_force(self, force: float) -> float:
        """The torque the board receives [N m]: clamped, rounded to binary32.

        Parameters
        ----------
        force : float
            The torque sent [N m].

        Returns
        -------
        float
            [N m]: clamped to +-:data:`MAX_TORQUE`, then rounded to binary32.
        """
        return _F.unpack(self.encode_force(force)[2:])[0]

    def applied_forces(self, force):
        """:meth:`applied_force` of every force of an array, at numpy's speed
        (:func:`hapsim.drivers.base.binary32_commands` at the board's limit; arguments, shapes and
        units as :meth:`hapsim.drivers.base.Driver.applied_forces`).

        Parameters
        ----------
        force : array_like of float, shape (n,)
            Torques sent [N m].

        Returns
        -------
        ndarray of float64, shape (n,)
            The torques the writes carry [N m].
        """
        return binary32_commands(force, MAX_TORQUE)

    def output_stage(self, force):
        """The torque the board's motor gets for the torques sent
        (:meth:`hapsim.drivers.base.Driver.output_stage`): the write's binary32, clamped,
        through ``create_torque``'s 12-bit duty written at the Due's 8 bits, truncated
        (:func:`hapsim.drivers.output_stage.m3_output`; ``Haply_M3_Firmware_V1_5.h``
        lines 483-491, ``pwm01.h`` ``pwm_write_duty``, ``variant.h`` ``PWM_RESOLUTION``).

        Parameters
        ----------
        force : ndarray, shape (n,)
            Torques sent [N m].

        Returns
        -------
        tuple of ndarray
            ``(out, half_width)`` [N m], shape (n,); the half-width is 0 (exact).
        """
        if not self.torque_levels:
            return None
        import numpy as np

        from hapsim.drivers.output_stage import m3_output
        f = np.asarray(force, float)
        f = np.where(np.isfinite(f), np.clip(f, -MAX_TORQUE, MAX_TORQUE), 0.0)
        return m3_output(f)

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

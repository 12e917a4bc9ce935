"""Hapkit over serial, in the host-protocol variant of the WHC2017 Hapkit sketch.

Layout, as that sketch (S. Ding and C. Gallacher's rework of the Stanford Hapkit code for
the World Haptics 2017 student challenge, ``Hapkit_arduino.ino``) and its Processing host
(``Board.java``) exchange it at 57600 baud, binary32 little-endian:

host -> device, 10 bytes ::

    [header][function][float32 a][float32 b]
    header = type << 4 | motor mask (this driver: type 1, motor 1 -> 0x11)

device -> host, 9 bytes, one per command (after the render that follows its read) ::

    [function][float32 x: handle position, m][float32 the sketch's Tp, N m, or force, N]

The reply's second float is the motor pulley's torque ``Tp`` the sketch computed
(``Hapkit_arduino.ino:129`` at the repository's head, haphub/WHC2017 ef6028f) or, in its
copy of 2017-04-07 (e09075d, ``Virtual-Environment/Hapkit_arduino/Hapkit_arduino.ino:129``),
the rendered ``force``; neither is the force the motor applies, which the sketch quantises
on a square-root curve to 256 levels (:mod:`hapsim.drivers.output_stage`). The driver
tells the two apart from the replies (``reply``), and its account computes the motor's
force from them.

The published sketch renders its own virtual environments (``function`` picks one, the
floats are its parameters). To close the THS on the host, the firmware must apply the
second float as the handle force for one function code: this driver sends its force there
with ``function`` = :data:`HOST_FORCE_FUNCTION` (255 by default, an unused code; add that
case to the sketch's ``renderingAlgorithm``). Neither direction has a start byte, sequence
number or checksum; both decoders take a frame only when its fixed bytes match and its
floats are finite and plausible, and otherwise drop one byte and look again (counted).
"""

from __future__ import annotations

import math
import struct

from hapsim.drivers.base import FLAG_ESTIMATED, Driver, binary32_commands
from hapsim.drivers.decoders import AlignedDecoder, MappedDecoder
from hapsim.drivers.sketch_timing import (FIRMWARE_TICK_S, PERIOD_TICKS_TOL,  # noqa: F401
                                          RENDER_LATENCY_S, RENDER_S, SketchTiming,
                                          whole_ticks)
from hapsim.option_values import option_value

__all__ = ["HapkitSerial", "HOST_FORCE_FUNCTION", "HEADER", "command_packet", "reply_packet",
           "ReplyDecoder", "ReplyLog", "CommandDecoder", "SKETCH_READ_TIMEOUT_S",
           "SHIFT_SIGNATURE", "SKETCH_COUNT_M", "FIRMWARE_TICK_S", "PERIOD_TICKS_TOL",
           "whole_ticks"]

HOST_FORCE_FUNCTION = 255
#: How long the sketch's ``Serial.readBytes`` waits for each byte of a command [s]: the
#: Stream's 1000 ms of ``millis()``, which runs 64 times fast on the sketch's board:
#: ``standard_hapkit_setup`` sets Timer0's prescaler to 1 for the motor's PWM on pin 5
#: (``Hapkit_arduino.h``, ``initialize_actuator`` -> ``setPwmFrequency(pwm, 1)``), and
#: Arduino's ``millis()`` counts Timer0's overflows as if it ran at 1/64: 15.625 ms. A
#: command cut short by a lost byte is completed by the next command's bytes, and the
#: sketch reads every later command one byte out of step, until the host is silent longer
#: than this (haphub/WHC2017 ``hFirmware/Hapkit_Arduino_Control/Hapkit_arduino``:
#: ``loop`` reads a header byte and ``receive_data``'s ``readBytes`` of 9, no framing).
SKETCH_READ_TIMEOUT_S = 1.0 / 64
#: The bytes of the command's first float, which the sketch's host-force function does
#: not use (``freq``): distinct bytes that no function of the sketch renders (its
#: functions are 0-3 and the host's), so that a sketch reading the commands ``s`` bytes
#: out of step (1 <= s <= 4) takes ``0xA0 + s`` for the function byte: no force, and its
#: reply ``[0xA0 + s][x][0.0]`` tells the host by how much
#: (:meth:`HapkitSerial.realign_bytes`). A float of about -7e-17.
SHIFT_SIGNATURE = bytes([0xA1, 0xA2, 0xA3, 0xA4])
#: The sketch's position step at the handle [m]: ``xh = rh (m updatedPos + b)``
#: (``Hapkit_Kinematics_Simulation.h:130-138``), one count of the magnetoresistive
#: sensor's flip-counted angle moving it ``rh m``, with the sketch's calibration
#: ``m = 0.0002292`` rad a count (sim.h:23) and handle radius ``rh = 0.075`` m (sim.h:38-40):
#: 17.19 um. Each paddle is calibrated for itself (the driver's ``count_m``).
SKETCH_COUNT_M = 0.075 * 0.0002292


#: Header byte: type 1 (read encoder data / command) << 4 | motor 1 (Board.format_header).
HEADER = (1 << 4) | 0x01
_FF = struct.Struct("<ff")
_F32 = struct.Struct("<f")
#: Largest plausible handle position [m] (the paddle travels a few centimetres).
MAX_POSITION = 0.5
#: Largest plausible force in a reply [N].
MAX_FORCE = 100.0

LIMITS = """\
Hapkit-serial protocol limits (hapsim --driver hapkit-serial, WHC2017 sketch framing):
  host-clocked only: the sketch answers each 10-byte command with one 9-byte reply on
    its next 0.992 ms tick and has no sequence numbers: the loop runs on the host's clock
    and the delay d cannot be measured (the scene's device.delay is taken as given)
  no start byte, no checksum: the decoders realign on the fixed bytes and plausible
    floats; a corrupted float byte is a wrong force or position
  the stock sketch renders its own environments: the firmware must apply the second
    float as the handle force for function code 255 (see docs/devices.md)
  57600 baud: 19 bytes per sample take 3.3 ms on the wire, the sketch's render and
    tick up to 1 ms more: at most 201.613 Hz (5 ticks)
  the sketch's position is whole counts of its sensor, 17.19 um at the handle with its
    published calibration (protocol option count_m: a paddle calibrated for itself)
  the sketch takes each command on its own Timer1 tick of 0.992 ms (1.008 kHz): the
    host's period must be a whole number of ticks (201.613, 168.011, 144.009, ... Hz;
    250 Hz is refused, its samples would be 4 and 5 ticks apart), and the host times its
    writes in the middle of a tick, measured at the first arming (a board whose crystal
    drifts from the host's clock walks that phase by its drift times the run's length)"""


def command_packet(force: float, function: int = HOST_FORCE_FUNCTION,
                   header: int = HEADER, a: float = 0.0) -> bytes:
    """The 10-byte command ``[header][function][float32 a][float32 force]``.

    Parameters
    ----------
    force : float
        The force to render [N] (binary32 on the wire).
    function : int
        The function code (its low byte).
    header : int
        The header byte (its low byte).
    a : float
        The first float (the driver sends :data:`SIGNATURE_A`).

    Returns
    -------
    bytes
        10 bytes, the floats little-endian.
    """
    return bytes([header & 0xFF, function & 0xFF]) + _FF.pack(a, force)


#: The first float of the driver's commands: :data:`SHIFT_SIGNATURE` as a binary32.
SIGNATURE_A = struct.unpack("<f", SHIFT_SIGNATURE)[0]


def reply_packet(function: int, x: float, force: float) -> bytes:
    """The 9-byte reply ``[function][float32 x][float32 force]``.

    Parameters
    ----------
    function : int
        The function code echoed (its low byte).
    x : float
        The handle's position [m].
    force : float
        The reply's second float (``Tp`` [N m] or the force [N], by the sketch).

    Returns
    -------
    bytes
        9 bytes, the floats little-endian.
    """
    return bytes([function & 0xFF]) + _FF.pack(x, force)


def _plausible(x: float, lim: float) -> bool:
    return math.isfinite(x) and abs(x) <= lim


class ReplyLog:
    """The replies a host decoder took, in order: ``x`` [m] and the reply's second float
    (``Tp`` [N m] or the rendered force [N], module notes: not the motor's force); a
    callable mapping a reply to its position (the decoder's output).

    Arrays grown by doubling, preallocated: taking a reply stores two floats (no array
    per sample).

    Attributes
    ----------
    x, force : ndarray, shape (capacity,)
        The first :attr:`n` entries are the replies'.
    n : int
    """

    def __init__(self, capacity: int = 4096) -> None:
        import numpy as np
        self.x = np.zeros(int(capacity))
        self.force = np.zeros(int(capacity))
        self.n = 0

    def __call__(self, reply) -> float:
        n = self.n
        if n == self.x.size:
            import numpy as np
            self.x = np.concatenate([self.x, np.zeros(n)])
            self.force = np.concatenate([self.force, np.zeros(n)])
        self.x[n] = reply[0]
        self.force[n] = reply[1]
        self.n = n + 1
        return reply[0]


class ReplyDecoder(AlignedDecoder):
    """Host side: 9-byte replies out of a byte stream, as ``(x [m], Tp [N m] or force [N])``.

    Attributes
    ----------
    stats : dict
        ``frames`` (replies), ``skipped`` (bytes dropped realigning), ``unconfirmed``
        (windows that parsed but were followed by no function byte: dropped).

    Notes
    -----
    A reply is taken only where the byte after it, when one has come, is the function
    byte a reply starts with, and one found by realigning waits for that byte
    (:attr:`AlignedDecoder.confirm_next`): no start byte and no checksum let the tail of a
    damaged reply and the head of the next make a plausible reply (about one lost byte in
    200 did; taken as a reading, it made a measurement "differ").
    """

    length = 9
    confirm_next = True

    def starts_frame(self, byte: int) -> bool:
        """A reply starts with its function byte.

        Parameters
        ----------
        byte : int, 0..255

        Returns
        -------
        bool
        """
        return byte == self.function

    def __init__(self, function: int = HOST_FORCE_FUNCTION) -> None:
        super().__init__()
        self.function = function & 0xFF
        self.stats["shifted"] = 0
        #: The last out-of-step reply's shift ``s`` (bytes the sketch reads late, 1-4),
        #: and how many such replies came (:attr:`shifts`).
        self.shift = 0
        self.shifts = 0

    def parse(self, buf):
        """``(x, force)`` of a plausible reply at the start of ``buf``, or None. A reply of
        a sketch reading the commands out of step (``[0xA0 + s][x][0.0]``, x plausible:
        :data:`SHIFT_SIGNATURE`) is no reply; it is counted (``stats["shifted"]``) and its
        ``s`` kept (:attr:`shift`).

        Parameters
        ----------
        buf : bytearray
            At least :attr:`length` (9) bytes.

        Returns
        -------
        tuple of float or None
            ``(x [m], the second float: Tp [N m] or force [N])``, binary32 values.
        """
        if buf[0] != self.function:
            s = buf[0] - SHIFT_SIGNATURE[0] + 1
            if 1 <= s <= 4 and buf[5:9] == b"\0\0\0\0" and \
                    _plausible(_FF.unpack_from(buf, 1)[0], MAX_POSITION):
                self.stats["shifted"] += 1
                self.shift, self.shifts = s, self.shifts + 1
            return None
        x, f = _FF.unpack_from(buf, 1)
        return (x, f) if _plausible(x, MAX_POSITION) and _plausible(f, MAX_FORCE) else None


class CommandDecoder(AlignedDecoder):
    """Device side (the mock): 10-byte commands whose header and function match, as the
    commanded force [N] (a NaN or infinite one as 0.0, counted in ``non_finite``).

    Attributes
    ----------
    stats : dict
        ``frames`` (commands), ``skipped`` (bytes dropped realigning), ``non_finite``.
    """

    length = 10

    def __init__(self, function: int = HOST_FORCE_FUNCTION, header: int = HEADER) -> None:
        super().__init__()
        self.function = function & 0xFF
        self.header = header & 0xFF
        self.stats["non_finite"] = 0

    def parse(self, buf):
        """The force of a command at the start of ``buf``, or None.

        Parameters
        ----------
        buf : bytearray
            At least :attr:`length` (10) bytes.

        Returns
        -------
        float or None
            The force [N] (binary32; NaN/inf: 0.0, counted); None: header or function differ.
        """
        if buf[0] != self.header or buf[1] != self.function:
            return None
        f = _FF.unpack_from(buf, 2)[1]
        if not math.isfinite(f):
            self.stats["non_finite"] += 1
            return 0.0
        return f


class HapkitSerial(SketchTiming, Driver):
    """A Hapkit running the WHC2017 sketch with a host-force function (module notes).

    Parameters
    ----------
    function : int, 0..255
        The function code the firmware applies the host's force for.
    force_limit : float > 0
        Largest force sent [N] (the Hapkit 3 paddle: about 2 N at the handle).
    reply, levels, render_latency_s
        What the reply's second float is, the sketch's output levels and its render
        latency's bounds [s] (below).
    count_m : float >= 0
        The sketch's position step at the handle [m] (default :data:`SKETCH_COUNT_M`, its
        published calibration; 0: a sketch that reads the handle exactly): the sensor step
        the measurement states its uncertainty with (:attr:`position_scale`). Unstated
        (0 before), a host stall's record against an independent model of the sketch said
        "differs" of a matching paddle once in 20 runs (k 1.39 half-widths off); stated,
        10 of 10 within with the truth inside (docs/testing.md).
    """

    name = "hapkit-serial"
    baud = 57600
    rtscts = False
    #: The highest rate the driver takes (:meth:`check_rate`): a whole number of the
    #: sketch's ticks (5 x 0.992 ms) whose period holds a command and its answer at 57600
    #: baud at any write phase (:meth:`HapkitSerial.latest_answer_s`, 4.27 ms)
    native_rate_hz = 1.0 / (5 * FIRMWARE_TICK_S)
    device_id = 0x48415053           # "HAPS"
    position_rel = 2.0 ** -24        # binary32 fields on the wire (round to nearest)
    force_rel = 2.0 ** -24
    position_scale = SKETCH_COUNT_M  # the sketch's count (``count_m``), sent as a float32
    force_scale = 0.0
    limits = LIMITS
    #: The sketch reads the handle at a command's end for the write phases the transport
    #: aims at (``Hapkit_arduino.ino:96-135``; :func:`hapsim.drivers.tick_align.
    #: fit_tick_jump`): as late as the host's write (:attr:`Driver.samples_at_write`).
    samples_at_write = True
    #: The sketch's control tick [s] (:data:`FIRMWARE_TICK_S`, 0.992 ms): a command is
    #: taken at the tick after it has come, the handle read and the force applied there
    #: (:class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`). The transport
    #: measures where its writes fall in that tick at arming and writes in its middle
    #: (:meth:`hapsim.drivers.tick_align.TickAligned.tick_phase`).
    tick_s = FIRMWARE_TICK_S
    answering_firmware = "WHC2017 Hapkit sketch layout (one reply per command)"
    #: The sketch reads a command as a header byte and nine more, no framing
    #: (:data:`SKETCH_READ_TIMEOUT_S`): a host byte lost puts every later command out of
    #: step, and only a silence longer than its ``readBytes`` timeout puts it back. The
    #: transport realigns it so (:meth:`hapsim.drivers.resync.Resynchronising._resync`):
    #: no write for :attr:`realign_quiet_s` from its last, on the evidence of
    #: :attr:`garbled_commands` commands unanswered for :attr:`garbled_s` while replies'
    #: bytes came that made none (out of step, the sketch answers every command with its
    #: function byte read from the host's first float: 0).
    unframed = True
    #: The sketch's read timeout and 2.4 ms for the link's latency and a tick [s]; less
    #: than the hold bound, so the host's watchdog writes after the sketch realigned.
    realign_quiet_s = SKETCH_READ_TIMEOUT_S + 0.0024
    #: More than this many commands unanswered (with :attr:`garbled_s`): the sketch
    #: answers a command within ~4.5 ms (its 10 bytes, a tick, its reply's 9 bytes at
    #: 57600 baud), and a reply found after bytes dropped is taken when the next one's
    #: function byte comes (:attr:`ReplyDecoder.confirm_next`): two unanswered may be
    #: in step.
    garbled_commands = 2
    #: The oldest unanswered command's wait that, with the above, is evidence [s].
    garbled_s = 0.006

    #: The sketch's render after its read (:data:`RENDER_LATENCY_S`): the loop's delay is
    #: the scene's whole periods and this much more, within these bounds [s]
    #: (:func:`hapsim.pipeline.render_latency.timed_prediction`).
    render_latency_s = RENDER_LATENCY_S
    #: The sketch's reply comes up to 4.27 ms after the write (:meth:`latest_answer_s`),
    #: 0.69 ms before the next deadline at 5 ticks: a host that wakes later than that
    #: (an idle core's wake-up, a loaded machine) takes it a period late, and until the
    #: echo pairs it the loop steps with a reading a period old
    #: (:class:`hapsim.drivers.late_replies.LateReplies`). A 50 N/m spring at 5 ticks,
    #: stable up to a delay of 1.52 periods, ran the paddle to the 0.2 m envelope beside
    #: the suite's load so (docs/drivers.md): the loop must hold a period more
    #: (:attr:`Driver.late_reading_periods`).
    late_reading_periods = 1

    def __init__(self, function: int = HOST_FORCE_FUNCTION, force_limit: float = 2.0,
                 reply: str = "auto", levels: int = 256,
                 render_latency_s: tuple | list | None = None,
                 count_m: float = SKETCH_COUNT_M) -> None:
        from hapsim.errors import ConfigError
        count_m = option_value("count_m", count_m, "m", low=0)  # (the step at the handle)
        #: The sketch's position step [m] (the HELLO's position scale the host states).
        self.count_m = float(count_m)
        self.position_scale = self.count_m
        from hapsim.drivers.output_stage import sketch_gearing
        self._gearing = sketch_gearing()        # binary32 (answer_names)
        function = option_value("function", function, low=0, high=255, whole=True)
        force_limit = option_value("force_limit", force_limit, "N", low=0, low_ok=False)
        if reply not in ("auto", "Tp", "force"):
            raise ConfigError(f"the reply's second float: 'Tp' (the repository's head), "
                              f"'force' (its copy of 2017-04-07) or 'auto', got {reply!r}",
                              key="reply")
        if levels not in (256, 0):
            raise ConfigError(f"the sketch's output levels: 256 (forceOutput's "
                              f"(int)(255 * duty), Hapkit_Kinematics_Simulation.h:227) or 0 "
                              f"(a sketch that applies the float as it is), got {levels!r}",
                              key="levels")
        if render_latency_s is not None:
            try:
                lo, hi = (float(v) for v in render_latency_s)
            except (TypeError, ValueError):
                lo, hi = math.nan, math.nan
            if not (math.isfinite(hi) and 0.0 <= lo <= hi):
                raise ConfigError(f"must be [low, high] seconds, 0 <= low <= high, got "
                                  f"{render_latency_s!r}", key="render_latency_s")
        else:
            lo, hi = RENDER_LATENCY_S
        #: The bounds in force [s] (a list: a device file's ``protocol_options``).
        self.render_latency_s = [float(lo), float(hi)]
        self.function = int(function)
        self.force_limit = float(force_limit)
        #: The sketch's output levels (``forceOutput``): 256, or 0 for a sketch that
        #: applies the rendered float as it is (no output stage: :meth:`output_stage`).
        self.levels = int(levels)
        #: What the reply's second float is (module notes): ``"Tp"``, ``"force"`` or
        #: ``"auto"`` (told from the replies by :meth:`account`; the last run's answer in
        #: :attr:`reply_found`).
        self.reply = reply
        self.reply_found = None

    def mock_hardware(self) -> dict:
        """The emulated sketch this driver describes: its position step (``count_m``).

        Returns
        -------
        dict
            ``{"count_m": float}`` [m], the mock's keywords.
        """
        return {"count_m": self.count_m}

    def output_stage(self, force):
        """The force the sketch's motor makes for the forces sent
        (:meth:`hapsim.drivers.base.Driver.output_stage`): the command's binary32, clamped
        at the limit, through ``forceOutput``'s 256 square-root levels
        (:func:`hapsim.drivers.output_stage.sketch_output`; sim.h:191, 206-229).

        Parameters
        ----------
        force : ndarray, shape (n,)
            Forces sent [N].

        Returns
        -------
        tuple of ndarray
            ``(out, half_width)`` [N], shape (n,).
        """
        if not self.levels:
            return None
        import numpy as np

        from hapsim.drivers.output_stage import sketch_output
        f = np.asarray(force, float)
        f = np.where(np.isfinite(f), np.clip(f, -self.force_limit, self.force_limit), 0.0)
        return sketch_output(f)

    def encode_force(self, force: float) -> bytes:
        """The command for ``force`` [N], clamped to the limit (NaN/inf: 0).

        Parameters
        ----------
        force : float
            The force to send [N].

        Returns
        -------
        bytes
            The 10-byte command (:func:`command_packet`, first float :data:`SIGNATURE_A`).
        """
        f = float(force) if math.isfinite(force) else 0.0
        return command_packet(max(-self.force_limit, min(self.force_limit, f)), self.function,
                              a=SIGNATURE_A)

    def applied_force(self, force: float) -> float:
        """The force the command carries [N]: clamped, rounded to binary32.

        Parameters
        ----------
        force : float
            The force sent [N].

        Returns
        -------
        float
        """
        return _FF.unpack(self.encode_force(force)[2:])[1]

    def applied_forces(self, force):
        """:meth:`applied_force` of every force of an array, at numpy's speed
        (:func:`hapsim.drivers.base.binary32_commands` at the force limit; arguments, shapes and
        units as :meth:`hapsim.drivers.base.Driver.applied_forces`).

        Parameters
        ----------
        force : array_like of float, shape (n,)
            Forces sent [N].

        Returns
        -------
        ndarray of float64, shape (n,)
        """
        return binary32_commands(force, self.force_limit)

    def realign_bytes(self, frames) -> bytes:
        """The bytes that put the sketch back in step, from the replies it sent out of step
        (:class:`ReplyDecoder`'s :attr:`~ReplyDecoder.shift`): a sketch reading ``s``
        bytes late completes the command it waits for with ``s`` more bytes, and reads the
        next command in step (the one it completes takes function byte ``0xA0 + s``: no
        force). ``b""`` when the decoder has no shift.

        Parameters
        ----------
        frames : ReplyDecoder
            The transport's frame decoder.

        Returns
        -------
        bytes
            ``s`` zero bytes, or ``b""``.
        """
        s = int(getattr(frames, "shift", 0) or 0)
        frames.shift = 0
        return bytes(s) if 1 <= s <= 4 else b""

    def unknown_force_rows(self, columns: dict):
        """Rows whose force the sketch took from commands read out of step, left out of
        the measurement (:meth:`hapsim.drivers.base.Driver.unknown_force_rows`).

        A host byte lost puts the sketch's reads out of step (:data:`SKETCH_READ_TIMEOUT_S`):
        its commands then carry the function byte 0 (no force) or a byte of the host's
        force (one of the sketch's own environments), neither the force sent nor the one
        before, and their replies do not parse (``FLAG_ESTIMATED`` rows), until the
        transport realigns it with a silence, a gap in ``seq``. A run of estimated rows
        ``[r0, r1]`` that a gap ends is such a run: the commands of those rows act at
        rows ``r0 + d - 1 .. r1 + d - 1``; rows ``r0 - 1 .. r1 + d`` are left out (the
        fit drops ``d + 2`` rows after a cut as well). A run no gap ends is a reply lost
        on its way back, whose commands were taken: :meth:`account` states it.

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``seq``, ``flags``, each shape (n,)).

        Returns
        -------
        ndarray of bool, shape (n,), or None
            None when the columns or the delay are missing.
        """
        import numpy as np
        d = getattr(self, "loop_delay", None)
        seq, flags = columns.get("seq"), columns.get("flags")
        if d is None or seq is None or flags is None:
            return None
        seq = np.asarray(seq, np.int64)
        est = (np.asarray(flags) & FLAG_ESTIMATED) != 0
        n = est.size
        out = np.zeros(n, bool)
        r = 0
        while r < n:
            if not est[r]:
                r += 1
                continue
            r1 = r
            while r1 + 1 < n and est[r1 + 1] and seq[r1 + 1] == seq[r1] + 1:
                r1 += 1
            if r1 + 1 < n and seq[r1 + 1] > seq[r1] + 1:
                out[max(r - 1, 0):min(r1 + int(d) + 1, n)] = True
            r = r1 + 1
        return out

    def probe_decoder(self):
        """A fresh frame decoder for the transport's tick probe at arming: replies as
        ``(x, force)``, not logged in :attr:`replies` (they answer no row).

        Returns
        -------
        ReplyDecoder
        """
        return ReplyDecoder(self.function)

    def answer_names(self, command: bytes, echo) -> bool | None:
        """Whether a reply whose second float is ``echo`` can answer ``command``: the
        sketch's reply carries the force it rendered from the command read, as the
        binary32 ``force`` or its ``Tp`` (``Hapkit_arduino.ino:129``, ``sim.h:191``:
        :func:`hapsim.drivers.output_stage.sketch_tp`), exactly: equal to the command's
        force or to its ``Tp``. None for bytes that are no command of this driver.

        Per reply in the host's loop, so no array: ``Tp`` is the binary32 product of the
        gearing and the force, both binary32, whose exact product (48 bits) the double
        holds, so one rounding to binary32 gives ``sketch_tp``'s value.

        Parameters
        ----------
        command : bytes
            The bytes written (a 10-byte command of :meth:`encode_force`).
        echo : float
            The reply's second float (:meth:`answer_echo`): ``Tp`` [N m] or force [N].

        Returns
        -------
        bool or None
        """
        if len(command) != 10 or command[1] != self.function:
            return None
        f = _FF.unpack_from(command, 2)[1]              # binary32 already
        if echo == f:
            return True
        tp = self._gearing * f
        return abs(tp) < 3.4e38 and echo == _F32.unpack(_F32.pack(tp))[0]

    def answer_echo(self):
        """The second float of the last reply decoded (:attr:`replies`), or None.

        Returns
        -------
        float or None
            ``Tp`` [N m] or the force [N] (module notes); None before any reply.
        """
        log = getattr(self, "replies", None)
        return None if log is None or log.n == 0 else float(log.force[log.n - 1])

    def least_answer_s(self) -> float:
        """:meth:`round_trip_s`: the sketch's UART takes the command's bytes at the baud
        rate, and so does the emulated board (:class:`hapsim.emulated.hapkit_serial_board.
        HapkitSerialDevice`).

        Returns
        -------
        float
            [s]: 3.45 ms at 57600 baud.
        """
        return self.round_trip_s()

    def decoder(self):
        """A fresh host decoder returning the handle position [m]; every reply's
        ``(x, Tp or the rendered force)`` is kept in :attr:`replies` (a ReplyLog) for
        :meth:`account`.

        Returns
        -------
        MappedDecoder
        """
        self.replies = ReplyLog()
        return MappedDecoder(ReplyDecoder(self.function), self.replies)

    def reply_kind(self, tp_on, force_on, got) -> str:
        """What the replies' second float is (module notes), from the replies themselves
        unless :attr:`reply` names it: ``"Tp"`` where more replies carry the ``Tp`` of the
        force sent than the force itself (a force of 0 says nothing: both are 0), else
        ``"force"``; ``"Tp"`` (the repository's head) when none tells.

        Parameters
        ----------
        tp_on, force_on : ndarray, shape (m,)
            The ``Tp`` and the binary32 force of the command each reply answers.
        got : ndarray, shape (m,)
            The replies' second floats.

        Returns
        -------
        str
        """
        import numpy as np
        if self.reply != "auto":
            return self.reply
        said = force_on != 0
        n_tp = int(np.count_nonzero(said & (got == tp_on)))
        n_f = int(np.count_nonzero(said & (got == force_on)))
        return "force" if n_f > n_tp else "Tp"

    def account(self, columns: dict, force):
        """The force the device applied per tick: what the sketch rendered, as its replies
        name it, through its output stage.

        Each reply carries the ``Tp`` (or, in the 2017-04-07 copy, the ``force``) the
        sketch computed at the render that follows its read of a command (module notes):
        which command it rendered, not the force its motor applied, which ``forceOutput``
        cuts to one of 256 levels (:meth:`output_stage`). A command the sketch took
        wrongly (a byte lost: its parser took the next command's header as the last byte
        of a float, a force of ~1e-28 N, or a corrupted float byte) is then no unknown
        disturbance: the row whose reply says it has that render's output, a known input
        the measurement takes out, as a late tick on the framed link. Every other row
        holds the force sent through the output stage: a known input too, at every row.
        The rows are matched to the replies in order by their position (the binary32 the
        reply carried, exactly; a reply no row took, from an arming, a record the host
        dropped or one its decoder held until the next came, is passed over). A reply
        whose value is the sent force's to within the binary32 rounding of ``Tp`` is in
        step. A row with no reply (``FLAG_ESTIMATED``) may have had its command lost: the
        force from it on is the one sent, or what the sketch held at the row before --
        that row's account, the output its reply named (a damaged command's ~0 N, not the
        force the host sent) or, itself unknown, its whole interval. The account takes
        the middle of the two and states half their span (before, "the one before" was
        the host's sent force, which a damaged command had not applied; two lost commands
        in a row left the force two back outside). Before the output stage, the reply's
        float was read as the force applied (the head's ``Tp``, 0.43 % of the force, would
        have been taken for it).

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``position``, ``flags``).
        force : ndarray, shape (n,)
            The force each row's command carried [N].

        Returns
        -------
        hapsim.applied.AppliedAccount or None
            None when the delay is not known or no reply was logged
            (:meth:`Driver.account`'s answer then).
        """
        import numpy as np

        from hapsim.applied import AppliedAccount, account_from_timing
        from hapsim.drivers.output_stage import SKETCH_EDGE_ULPS, sketch_output_from_tp, \
            sketch_tp
        d = getattr(self, "loop_delay", None)
        log = getattr(self, "replies", None)
        flags = columns.get("flags")
        pos = columns.get("position")
        if d is None or log is None or log.n == 0 or flags is None or pos is None:
            return super().account(columns, force)
        # the forces sent as the sketch receives them (binary32, clamped), on time
        base = account_from_timing(force, d, quantise=self.applied_forces)
        f_on = base.applied.astype(np.float32)
        tp_on = sketch_tp(f_on)
        est = (np.asarray(flags) & FLAG_ESTIMATED) != 0
        n = est.size
        xs, fs = log.x[:log.n], log.force[:log.n]
        rows, got = [], []
        j = 0
        for r in np.flatnonzero(~est):
            # the next reply at this row's position (a few replies at most are passed
            # over: the arming's, a record the host did not take)
            k = j
            while k < xs.size and k < j + 8 and xs[k] != pos[r]:
                k += 1
            if k >= xs.size or xs[k] != pos[r]:
                continue
            j = k + 1
            rows.append(r)
            got.append(fs[k])
        rows = np.asarray(rows, np.int64)
        got = np.asarray(got, np.float64).astype(np.float32)
        kind = self.reply_kind(tp_on[rows], f_on[rows], got)
        self.reply_found = kind
        tp_got = got if kind == "Tp" else sketch_tp(got)
        # in step: the reply is the sent force's Tp to within Tp's rounding
        tol = SKETCH_EDGE_ULPS * np.spacing(np.abs(tp_on[rows]))
        step = np.abs(tp_got.astype(np.float64) - tp_on[rows].astype(np.float64)) <= tol
        if self.levels:
            out_on, hw_on, _ = sketch_output_from_tp(tp_on, sign_of=f_on)
            out_got, hw_got, _ = sketch_output_from_tp(tp_got, sign_of=tp_got)
        else:
            # a sketch that applies the rendered float as it is (levels 0, by name)
            from hapsim.drivers.output_stage import sketch_gearing
            out_on, hw_on = f_on.astype(np.float64), np.zeros(n)
            out_got = (got.astype(np.float64) if kind == "force"
                       else got.astype(np.float64) / sketch_gearing())
            hw_got = np.zeros(out_got.size)
        applied = np.where(base.source >= 0, out_on, 0.0)
        hw = np.where(base.source >= 0, hw_on, 0.0)
        late = base.late.copy()
        known = base.known.copy()
        replied = np.zeros(n, bool)
        replied[rows] = True
        known[rows] = True
        moved = rows[~step]
        late[moved] = True
        applied[moved] = out_got[~step]
        hw[moved] = hw_got[~step]
        # row r applies the force of the command answered (or not) at row r - d + 1
        amb = np.zeros(n, bool)
        k = np.flatnonzero(est) + d - 1
        amb[k[(k >= 0) & (k < n)]] = True
        amb &= ~replied
        unknown = self.unknown_force_rows(columns)
        if unknown is not None:
            known &= ~unknown
        for r in np.flatnonzero(amb):
            on_lo, on_hi = applied[r] - hw[r], applied[r] + hw[r]
            held_lo = held_hi = 0.0
            if r > 0:
                held_lo, held_hi = applied[r - 1] - hw[r - 1], applied[r - 1] + hw[r - 1]
            lo, hi = min(on_lo, held_lo), max(on_hi, held_hi)
            applied[r] = 0.5 * (lo + hi)
            hw[r] = 0.5 * (hi - lo)
        return AppliedAccount(applied, base.source, base.tick_delay, base.delay, late, hw,
                              known, "replies")

"""FireFader (E. Berdahl and A. Kontogeorgakopoulos): two motorised faders, serial bytes.

Layout, as the published firmware (``haptics_firmware.ino`` and the older ``.pde`` in
Berdahl's "Open-Source Haptics for Artists" repository) and its Pd host patch
(``FireFader~.pd``) read and write it:

host -> device, one packet per update ::

    [127, fA, fB]        fA, fB: forces as signed bytes (two's complement), clamped to
                         -127..126 so that 127 (the packet start) never appears in them

device -> host, one record per packet ::

    [255, pA, pB, b3, b4, b5, b6]   pA, pB: fader positions 0..254 (255 is the record
                                    start and never a value); b3, b4 the motor currents,
                                    b5, b6 the capacitive touch sense (0 from the .pde)

57600 baud with RTS/CTS flow control. This module drives fader A as hapsim's one axis,
with the position measured from the middle of the travel (count 127) and fader B held at
zero force.

Units (device parameters, :class:`FireFader`; ``hapsim identify`` finds the full scale):

- force full scale, the force at 127 counts with the firmware's enable full: the
  repository's *calibrated* Pd patch (``FireFader~.calibrated.pd``) divides the force in
  newtons by 0.39 before multiplying by 127 (its uncalibrated patch divides by 4 and says
  "this should be more like / 0.39"): 0.39 N is the default (:data:`FULL_SCALE_N`);
- position: both patches map ``(count - 128) / 128 * 0.05`` to metres, 0.390625 mm per
  count (:data:`METRES_PER_COUNT`; an earlier reading here, 99 mm over 254 counts, had no
  source).

Neither direction has a sequence number or a checksum: the decoders resynchronise on the
start byte and count what they drop; a corrupted value byte is a wrong force or position.

The firmware answers each pass with one record and only runs a pass when a packet has come
(``Hardware/FireFader/Firmware/haptics_firmware/haptics_firmware.ino`` of
eberdahl/Open-Source-Haptics-For-Artists, commit 6bbe9cd, 2013: ``loop``, lines 283-315):
it hunts for a 127, takes the next two bytes as the forces *whatever they are*, and runs the
pass once no byte is waiting (packets that waited are merged: the last one counts). One
lost value byte therefore makes it take the next packet's 127 as a force and swallow that
packet's forces (:class:`hapsim.emulated.driver_mock.FireFaderDevice` parses so;
:meth:`FireFader.account` states the force such a pass may have applied). A pass reads the
capacitive sense, the currents and the pots (about 1.25 ms: 175 + 175 + 150 + 150 + 300 +
300 us, as its comments time them), and the record takes 7 bytes x 10 bits / 57600 baud =
1.215 ms on the wire after the 3-byte packet's 0.52 ms: about 3 ms from a packet to its
record, so the host's period must be longer (:meth:`FireFader.round_trip_s`). Its force is
**gated** by an enable filter (``setPWM``, lines 188-216: the PWM is twice the count, or 0
while the enable is below :data:`ENABLE_GATE`): the enable (lines 380-382) rises
``e <- (31 e >> 5) + 5`` per pass while the fader is touched, inside ``4 < pot < 251`` and
cool, so the force is off for the first 5 passes after power-on or 0.1 s without a byte
(``waitForSerialInput``, lines 264-277: 65000 idle polls zero the enable and the motor),
and goes off ~59 passes after the fader leaves the pot range, is let go or gets hot. An
older copy in the same repository (``haptics_firmware_old_lesssensitive_capsensing_level``,
line 204) *scales* the force by ``(e - 1) / 128`` instead (a ramp over ~66 passes):
``firmware="ino-scaled"`` in the mock, ``scaled=True`` in :func:`enable_passes`. The Nano
resets when the port opens (about 1 s in its bootloader), so the transport repeats its
arming packet until the first record comes. The older ``.pde`` (not in that repository's
snapshot: described from an earlier reading) has no enable filter and no silence rule (the
force stays) and streams records unprompted; the transport says which firmware answered.
"""

from __future__ import annotations

import collections
import math
import select
import time

from hapsim.drivers.base import FLAG_ESTIMATED, Driver
from hapsim.drivers.decoders import MappedDecoder
from hapsim.option_values import option_value

__all__ = ["FireFader", "Records", "enable_passes", "pass_pwm", "enable_step", "ENABLE_GATE", "HOST_START", "DEVICE_START", "POSITION_MAX",
           "FORCE_MIN", "FORCE_MAX", "METRES_PER_COUNT", "FULL_SCALE_N", "encode_packet", "encode_record",
           "force_counts", "RecordDecoder", "PacketDecoder", "HAND_PASSES"]

HOST_START = 127
DEVICE_START = 255
RECORD_BYTES = 6
POSITION_MAX = 254
FORCE_MIN = -127
FORCE_MAX = 126
#: Position resolution [m/count]: 0.05 m per 128 counts (the repository's Pd patches).
METRES_PER_COUNT = 0.05 / 128
#: Force at 127 counts [N] (the repository's calibrated Pd patch; a device parameter:
#: identify yours).
FULL_SCALE_N = 0.39
#: The firmware's pass, its reads alone [s] (its comments: 2 x 175 + 2 x 150 + 2 x 300 us).
PASS_READS_S = 1.25e-3
#: The count at the middle of the travel: position 0 of the driven axis.
CENTRE = 127
#: The embedded mock's travel between its end stops [counts of its own position scale]:
#: inside the pot's rails, as a sweep needs (:mod:`hapsim.drivers.firefader_travel`).
MOCK_TRAVEL_COUNTS = 250
#: The ``.ino``'s silence rule: after about 0.1 s without a byte (65000 idle polls) the
#: enable and the motor go to 0 [s].
SILENCE_S = 0.1
#: Host silences this close to :data:`SILENCE_S` may or may not have reset the enable (the
#: idle polls' time is the firmware's estimate; the host's clock stamps the send) [s].
SILENCE_DOUBT_S = (0.08, 0.14)
#: The enable filter's full value (its fixed point: ``(31 * 129 >> 5) + 5 = 129``).
ENABLE_FULL = 129
#: The ``.ino``'s gate: below this enable the PWM is 0, from it on twice the packet's count
#: (``haptics_firmware/haptics_firmware.ino`` line 204: ``if (forceEnable < 20) force=0``).
ENABLE_GATE = 20
#: Passes with zero force after the enable was zeroed (0, 5, 9, 13, 17: below the gate).
GATE_PASSES = 5
#: The two faders' real-time run (:mod:`hapsim.pipeline.faders_run`): after its pause
#: between records the host sends this many zero packets, the last one's record the
#: record's first row; the hand (a person's, or the emulated board's) holds the faders
#: still at the record's start until that pass and lets go (the enables' 5 passes below
#: their gate and 3 more).
HAND_PASSES = 8

LIMITS = """\
FireFader protocol limits (hapsim --driver firefader):
  host-clocked only: the device has no clock hapsim can read and no sequence numbers,
    so the loop runs on the host's clock and the delay d cannot be measured: the scene's
    device.delay is taken as given (identify it with 'hapsim identify')
  no checksum: a corrupted byte is a wrong force or position; only a lost start byte or
    a truncated record is noticed (resync, counted as bad frames)
  resolution: position 0.39 mm per count (0.05 m per 128 counts), force full_scale/127
    per count (-127..126; 3.07 mN at the default 0.39 N): the THS is closed through both
    quantisers, so measured (k, b) equal the prediction only to the bound these give
  57600 baud, RTS/CTS: a 3-byte packet (0.52 ms), the firmware's reads (1.25 ms) and
    the 7-byte record (1.215 ms) take ~3 ms: rates above ~330 Hz are refused
  the firmware's force is gated by an enable filter: off for 5 passes after power-on
    or 0.1 s of silence, and off ~59 passes after the fader is let go, reaches an end
    (pot <= 4 or >= 251) or gets hot: the force the device applied is then 0, not the
    one sent (the records' touch byte shows the touch)
  the firmware takes the two bytes after a 127 as forces whatever they are: one lost
    value byte makes it read the next packet's 127 as fader B's force (+127: full
    force on B if B is touched) and swallow that packet
  the Nano resets when the port opens (~1 s bootloader): hapsim repeats its first
    packet until a record comes
  the older .pde firmware streams records unprompted and has no silence rule: hapsim
    says which firmware answered; the host sends zero force at every end"""


def force_counts(force: float, full_scale: float = FULL_SCALE_N) -> int:
    """Force [N] as FireFader counts: ``round(127 f / full_scale)`` clamped to -127..126.

    Parameters
    ----------
    force : float
        Force [N]; NaN or infinite gives 0 (never a full-scale force from a bad number).
    full_scale : float > 0
        Force at 127 counts [N].

    Returns
    -------
    int
        Counts in ``FORCE_MIN .. FORCE_MAX``.
    """
    if not math.isfinite(force):
        return 0
    c = round(force / full_scale * 127.0)
    return int(min(max(c, FORCE_MIN), FORCE_MAX))


def encode_packet(count_a: int, count_b: int) -> bytes:
    """Host -> device packet ``[127, fA, fB]`` (counts clamped to -127..126).

    Parameters
    ----------
    count_a, count_b : int
        Force counts of faders A and B.

    Returns
    -------
    bytes, length 3
    """
    a = min(max(int(count_a), FORCE_MIN), FORCE_MAX)
    b = min(max(int(count_b), FORCE_MIN), FORCE_MAX)
    return bytes((HOST_START, a & 0xFF, b & 0xFF))


def encode_record(pos_a: int, pos_b: int, extra=(0, 0, 0, 0)) -> bytes:
    """Device -> host record ``[255, pA, pB, b3..b6]``.

    Parameters
    ----------
    pos_a, pos_b : int, 0..254
        Fader positions [counts].
    extra : sequence of 4 int, 0..254
        The record's other bytes.

    Returns
    -------
    bytes, length 7

    Raises
    ------
    ValueError
        A value outside 0..254 (it would read as a record start).
    """
    vals = (int(pos_a), int(pos_b)) + tuple(int(e) for e in extra)
    if len(vals) != RECORD_BYTES or any(not 0 <= v <= POSITION_MAX for v in vals):
        raise ValueError(f"record values must be 6 integers in 0..{POSITION_MAX}, got {vals}")
    return bytes((DEVICE_START,) + vals)


def pass_pwm(count: int, enable: int, scaled: bool = False) -> int:
    """The ``.ino``'s PWM for a packet's force count (``setPWM``), of 254 full scale.

    ``haptics_firmware/haptics_firmware.ino`` lines 188-216: ``2 n``, or 0 while the
    enable is below :data:`ENABLE_GATE`; the old copy
    (``haptics_firmware_old_lesssensitive_capsensing_level/haptics_firmware.ino`` lines
    201-205, ``scaled``): ``(2 n (e - 1)) >> 7`` (arithmetic shift, as avr-gcc's on an int).

    Parameters
    ----------
    count : int
        The packet's force byte as signed (-128..127).
    enable : int
        The enable filter before this pass (0..129).
    scaled : bool
        The old copy's scaling instead of the gate.

    Returns
    -------
    int
        Signed PWM (-256..254); its sign is the direction pin's.
    """
    if scaled:
        return (2 * int(count) * (int(enable) - 1)) >> 7
    return 0 if enable < ENABLE_GATE else 2 * int(count)


def enable_step(enable: int, heat: int, pwm: int, pot: int, touched: bool = True):
    """One pass's update of the ``.ino``'s heat estimate and force enable, after the record.

    ``haptics_firmware/haptics_firmware.ino`` lines 366-368 (``h <- (16383 h >> 14) +
    (pwm >> 5)``, the *signed* PWM: a negative force cools the estimate, so only pushing
    towards the pot's high end can trip the heat gate) and 380-382 (``e <- (31 e >> 5) +
    5 [4 < pot < 251 and h >> 10 < 40 and capsense > 30]``).

    Parameters
    ----------
    enable, heat : int
        The filters before the update.
    pwm : int
        The signed PWM this pass set (:func:`pass_pwm`).
    pot : int
        The fader count the pass read (0..254).
    touched : bool
        The capacitive sense's filter above 30.

    Returns
    -------
    tuple of int
        ``(enable, heat)`` after the pass.
    """
    heat = ((int(heat) * 16383) >> 14) + (int(pwm) >> 5)
    ok = 4 < int(pot) < 251 and (heat >> 10) < 40 and touched
    return ((int(enable) * 31) >> 5) + 5 * ok, heat


def enable_passes(counts, silence, pots, *, threshold: float = SILENCE_S,
                  delay: int = 1, enable0: int = ENABLE_FULL, heat0: int = 0,
                  scaled: bool = False):
    """The ``.ino`` firmware's PWM per pass, from the host's commands: its enable filter
    replayed (module notes; :class:`hapsim.emulated.driver_mock.FireFaderDevice` runs the same loop).

    Pass ``c`` (command ``c``) sets the motor to :func:`pass_pwm` of the packet's count and
    the enable, then updates the heat estimate and the enable (:func:`enable_step`; touch
    is taken as given: the host does not log the record's sense bytes); a silence of
    ``threshold`` or more before a command zeroes the enable and the motor
    (``waitForSerialInput``, ``haptics_firmware.ino`` lines 264-277; the force queued in the
    device's delay is dropped: the next ``delay`` passes hold 0).

    Parameters
    ----------
    counts : array_like of int, shape (n,)
        Force count of each command (-127..126).
    silence : array_like of float, shape (n,)
        Host silence before each command [s].
    pots : array_like of int, shape (n,)
        Fader count read at each pass (0..254).
    threshold : float
        Silence that resets the enable [s].
    delay : int >= 0
        Passes between a command and its force acting (the device's delay d).
    enable0, heat0 : int
        The filters before the first command (full enable after the arming).
    scaled : bool
        The old copy's scaled enable instead of the gate (:func:`pass_pwm`).

    Returns
    -------
    ndarray of int, shape (n,)
        PWM acting over pass ``c``'s period (of 254 full scale; 0 during the ``delay``
        passes after a reset and before the first command's force arrives).
    """
    import numpy as np
    n = len(counts)
    pwm = np.zeros(n, np.int64)
    due = np.zeros(n, np.int64)
    e, h = int(enable0), int(heat0)
    zero_until = -1
    for c in range(n):
        if silence[c] >= threshold:
            e = 0
            zero_until = c + delay - 1
        p = pass_pwm(int(counts[c]), e, scaled)
        pwm[c] = p
        e, h = enable_step(e, h, p, int(pots[c]))
        if c - delay >= 0 and c > zero_until:
            due[c] = pwm[c - delay]
    return due


class _StartByteDecoder:
    """Frames of ``length`` value bytes after a ``start`` byte, resynchronising on it.

    A start byte inside a frame drops the partial frame (``truncated``) and begins a new
    one; bytes before a start byte are ``skipped``; ``value(b)`` returns None for a byte
    out of range (the frame is dropped, ``out_of_range``) or the decoded value.
    """

    def __init__(self, start: int, length: int, value) -> None:
        self._start, self._len, self._value = start, length, value
        self._buf: list = []
        self._hunting = True
        self.stats = {"frames": 0, "skipped": 0, "truncated": 0, "out_of_range": 0}

    def feed(self, data: bytes) -> list:
        """Bytes in, complete frames (tuples of values) out."""
        out = []
        st = self.stats
        buf = self._buf
        for b in data:
            if b == self._start:
                if not self._hunting and buf:
                    st["truncated"] += 1
                buf.clear()
                self._hunting = False
                continue
            if self._hunting:
                st["skipped"] += 1
                continue
            v = self._value(b)
            if v is None:
                st["out_of_range"] += 1
                buf.clear()
                self._hunting = True
                continue
            buf.append(v)
            if len(buf) == self._len:
                out.append(tuple(buf))
                buf.clear()
                st["frames"] += 1
                self._hunting = True
        return out


class RecordDecoder(_StartByteDecoder):
    """Host side: device -> host bytes to records ``(pA, pB, b3..b6)``, values 0..254.

    Attributes
    ----------
    stats : dict
        ``frames`` (complete records), ``skipped`` (bytes dropped while hunting for a
        start byte), ``truncated`` (a start byte inside a record: the partial record
        dropped), ``out_of_range`` (always 0: every byte but the start is a value).
    """

    def __init__(self) -> None:
        super().__init__(DEVICE_START, RECORD_BYTES, int)


def _signed_force(b: int):
    """A force byte as -127..126 (two's complement); None for -128, which no host sends."""
    if b == 0x80:
        return None
    return b - 256 if b > 127 else b


class PacketDecoder(_StartByteDecoder):
    """Device side (the mock): host -> device bytes to force packets ``(count_a, count_b)``.

    Attributes
    ----------
    stats : dict
        ``frames`` (packets), ``skipped`` (bytes while hunting), ``truncated`` (a start
        byte inside a packet), ``out_of_range`` (a force byte of -128: the packet is
        dropped).
    """

    def __init__(self) -> None:
        super().__init__(HOST_START, 2, _signed_force)


class Records:
    """The board's records as they come, one per command, in order.

    A read may find several records waiting: the answer to a zero write the host's
    watchdog made in a stall and the answer to the host's own write after it, when the
    host was descheduled between that write and its read. Each is the answer to one
    command, so each is taken by the read for that command; a read that kept only the
    last of them left the next read waiting for a record that had come already (a
    fresh-clone suite's two-fader run stopped so: "no record within 0.5 s (the board
    lost)" after a 190 ms stall of its host: :mod:`hapsim.pipeline.faders_run`).

    Parameters
    ----------
    dec : hapsim.drivers.firefader.RecordDecoder
        The stream's decoder.
    """

    def __init__(self, dec) -> None:
        self.dec = dec
        self.pending: collections.deque = collections.deque()

    def next(self, ser, timeout: float):
        """The next record's two pot counts, or None when none came within ``timeout``.

        Parameters
        ----------
        ser : serial.Serial or serial-like
            The port (``in_waiting``, ``read``; ``fileno`` to wait on it).
        timeout : float
            Longest wait [s] (an in-process link without ``fileno``: none, its answer is
            there or not).

        Returns
        -------
        (int, int) or None
        """
        end = time.monotonic() + timeout
        while not self.pending:
            n = ser.in_waiting
            if n:
                self.pending.extend(self.dec.feed(ser.read(n)))
                if self.pending:
                    break
            left = end - time.monotonic()
            if left <= 0 or not hasattr(ser, "fileno"):
                return None
            select.select([ser.fileno()], [], [], min(left, 0.01))
        rec = self.pending.popleft()
        return rec[0], rec[1]

    def answers(self, ser, owed: int, timeout: float, within: float):
        """The record of a write, with those of the commands written beside it (the host
        watchdog's zero writes in a stall): one each, the write's the last, unless the
        ``.ino`` ran one pass for packets that waited for it, the last counting (``loop``,
        lines 283-315: :class:`hapsim.emulated.firefader_board.FireFaderDevice`); then
        fewer come, and the records say nothing of which command they answer.

        Parameters
        ----------
        ser : serial.Serial or serial-like
        owed : int
            The commands owed a record, >= 1.
        timeout : float
            Longest wait for the first record [s].
        within : float
            Longest wait for the others [s], from the first.

        Returns
        -------
        rec : (int, int) or None
            The last record taken (None: none came within ``timeout``).
        got : int
            How many came, ``<= owed``.
        """
        rec = self.next(ser, timeout)
        if rec is None:
            return None, 0
        got = 1
        if owed > 1:
            end = time.monotonic() + within
            while got < owed:
                nxt = self.next(ser, max(0.0, end - time.monotonic()))
                if nxt is None:
                    break
                rec, got = nxt, got + 1
        return rec, got

    def clear(self, ser) -> None:
        """Every record not read yet dropped, with the port's input (before a record's
        start: the pause's answers).

        Parameters
        ----------
        ser : serial.Serial or serial-like
        """
        ser.reset_input_buffer()
        self.pending.clear()


class FireFader(Driver):
    """The FireFader as a 1-DoF device (module notes).

    Parameters
    ----------
    axis : {0, 1}
        Fader driven as hapsim's axis (0: A, 1: B); the other gets zero force.
    full_scale : float > 0
        Force at 127 counts [N] (default :data:`FULL_SCALE_N`).
    metres_per_count : float > 0
        Position per count [m] (default :data:`METRES_PER_COUNT`).

    Raises
    ------
    ConfigError
        A bad axis, full scale or position scale.
    """

    #: The ``.ino``'s silence rule zeroes the forces after :data:`SILENCE_S`: longer
    #: than the host's hold bound, so the host's watchdog runs beside it too
    #: (:attr:`hapsim.drivers.base.Driver.holds_force_s`).
    holds_force_s = SILENCE_S
    name = "firefader"
    travel_sweep = True
    #: ``hapsim identify --driver firefader`` without a scene: the shipped scene's fader
    #: (configs/firefader.yaml: knob, belt and rotor 0.05 kg, 0.1 N s/m) and its 15 mm
    #: of reach (38 of the pot's 0.39 mm counts). With hapsim's default mock device
    #: (0.1 kg, 0.5 N s/m, 10 mm) the mass came out 0.080 in [0.0047, 0.161].
    identify_device = {"mass": 0.05, "friction": 0.1}
    identify_envelope = 0.015
    #: Both faders in every packet and record (:mod:`hapsim.pipeline.faders_run`).
    ports_per_board = 2
    baud = 57600
    rtscts = True
    position_scale = METRES_PER_COUNT
    native_rate_hz = 300.0
    device_id = 0x46464144            # "FFAD"
    limits = LIMITS
    scale_option = "full_scale"
    scale_kind = "force"
    #: 4 passes for the touch filter to pass 30, 66 for the enable to reach 129 (the
    #: current ``.ino``'s gate needs 5 of them; the older copy's scale all), 2 more
    arming_records = 72
    answering_firmware = "haptics_firmware.ino (one record per packet)"
    streaming_firmware = "haptics_firmware.pde (records streamed unprompted)"

    def __init__(self, axis: int = 0, full_scale: float = FULL_SCALE_N,
                 metres_per_count: float = METRES_PER_COUNT) -> None:
        from hapsim.errors import ConfigError
        if axis not in (0, 1):
            raise ConfigError(f"FireFader axis must be 0 (A) or 1 (B), got {axis!r}",
                              key="axis")
        self.axis = axis
        self.full_scale = option_value("full_scale", full_scale, "N", low=0, low_ok=False)
        self.position_scale = self.metres_per_count = option_value(
            "metres_per_count", metres_per_count, "m", low=0, low_ok=False)
        self.force_scale = self.full_scale / 127.0
        self.force_limit = FORCE_MAX * self.force_scale

    def encode_force(self, force: float) -> bytes:
        """Packet commanding ``force`` [N] on the driven fader, 0 on the other.

        The count is clamped to -126..126 (the protocol's -127 would exceed the symmetric
        force limit, 126 counts, by one count).

        Parameters
        ----------
        force : float
            Force [N]; NaN or infinite: 0 (:func:`force_counts`).

        Returns
        -------
        bytes
            The 3-byte packet ``[127, fA, fB]`` (:func:`encode_packet`).
        """
        c = max(force_counts(force, self.full_scale), -FORCE_MAX)
        return encode_packet(c, 0) if self.axis == 0 else encode_packet(0, c)

    def applied_force(self, force: float) -> float:
        """The force the packet of ``force`` commands [N]: its count times the scale.

        Parameters
        ----------
        force : float
            The force sent [N].

        Returns
        -------
        float
            [N], a whole number of counts (-126..126) of ``full_scale / 127``.
        """
        return max(force_counts(force, self.full_scale), -FORCE_MAX) * self.force_scale

    def mock_hardware(self) -> dict:
        """The mock's fader: this full scale and position scale, and end stops
        :data:`MOCK_TRAVEL_COUNTS` counts apart around the middle (its pot reads about 2
        and 252 at them).

        Returns
        -------
        dict
            ``full_scale`` [N], ``metres_per_count`` [m/count], ``travel`` [m].
        """
        return {"full_scale": self.full_scale, "metres_per_count": self.position_scale,
                "travel": MOCK_TRAVEL_COUNTS * self.position_scale}

    def round_trip_s(self) -> float:
        """From a packet's first byte to its record's last [s]: 3 + 7 bytes of 10 bits at
        57600 baud and the firmware's reads (module notes), about 2.99 ms.

        Returns
        -------
        float
            [s]: ``100 / baud + PASS_READS_S``.
        """
        return (3 + 7) * 10 / self.baud + PASS_READS_S

    def rate_reason(self) -> str:
        """Why the rate is bounded (said with a refused ``--rate``): the round trip
        :meth:`round_trip_s` sums.

        Returns
        -------
        str
            The round trip's parts and sum [ms].
        """
        return (f"a packet (0.52 ms at {self.baud} baud), the firmware's reads "
                f"({PASS_READS_S * 1e3:.2f} ms) and its 7-byte record (1.22 ms) take "
                f"{self.round_trip_s() * 1e3:.2f} ms, and a period must hold them (a "
                "record a period late is taken for the next packet's)")

    def account(self, columns: dict, force):
        """The force the fader applied per tick (:meth:`Driver.account`), with the
        firmware's enable filter replayed (:func:`enable_passes`).

        The ``.ino`` gates each packet's force by its enable (``setPWM``,
        ``haptics_firmware.ino`` lines 188-216), which the host cannot read but can
        replay: it is full after the arming (:attr:`arming_records` at zero force) and goes
        to 0 after a silence of :data:`SILENCE_S`, after which the force is off for
        :data:`GATE_PASSES` passes. The host's clock stamps each command (the ``time`` column: when
        the command a row answers was sent), so a host stall that long is in the record: the
        gated rows are late ticks with a known applied force, taken out as a known
        input by the measurement (:func:`hapsim.analysis.measurement.late_accounted`).
        A silence within :data:`SILENCE_DOUBT_S` may or may not have reset the enable: the
        account takes the mean of both and states their half-difference. The touch,
        pot-range and heat gating is replayed with the fader touched, also without a
        silence (a fader held past a pot count of 250 or under 5 for ~59 passes has its
        force cut by the range gate).

        Parameters
        ----------
        columns : dict of str to ndarray
            Telemetry columns (``seq``, ``time``, ``position``, ``flags``).
        force : ndarray, shape (n,)
            The force each row's command carried [N].

        Returns
        -------
        hapsim.applied.AppliedAccount or None
            None when every answer came and no silence reached the doubt band.
        """
        import numpy as np
        acc = self._parser_account(columns, force, super().account(columns, force))
        d = getattr(self, "loop_delay", None)
        t = columns.get("time")
        seq = columns.get("seq")
        if d is None or t is None or seq is None or len(seq) < 2:
            return acc
        seq = np.asarray(seq, np.int64)
        # the board's time: the wall clock of the host's rows, or, on a lockstep mock
        # (command_period), its commands' (a period each; its silence rule counts
        # those): a host descheduled for 0.1 s was no silence of that board, and
        # measuring one from the rows' wall times made the same record measure otherwise
        # on a loaded host (tests/test_subsample.py's lockstep run: b within, then not)
        T_cmd = getattr(self, "command_period", None)
        t = (seq - seq[0]) * T_cmd if T_cmd else np.asarray(t, float)
        gap = np.diff(t)
        # the enable also falls while the fader reads outside 4 < pot < 251 (the
        # firmware's range gate) or once the heat estimate reaches 40 << 10 (at most
        # 254 >> 5 = 7 per pass: not within 5851 passes): without a silence, a gate or
        # that many passes, the force is the one sent
        xs = np.asarray(columns["position"], float)
        pot = CENTRE + np.round(xs / self.position_scale)
        gated = bool(np.any((pot <= 4) | (pot >= 251)))
        if not (np.any(gap >= SILENCE_DOUBT_S[0]) or gated
                or xs.size * (POSITION_MAX >> 5) >= 40 << 10):
            return acc
        from hapsim.applied import account_from_timing
        if acc is None:
            acc = account_from_timing(force, d, force_scale=self.force_scale,
                                      quantise=self.applied_forces)
        f = np.asarray(force, float)
        n = f.size
        # commands seq[0] .. seq[-1] + 1: row j answers command seq[j]; the force computed
        # from row j goes out with command seq[j] + 1 (a command no row answered, a hold,
        # repeats the force before); pass seq[j] + 1 moves the fader over row j's period
        c0 = int(seq[0])
        m = int(seq[-1]) + 2 - c0
        row_of = np.full(m, -1, np.int64)
        ok = (seq - c0 >= 0) & (seq - c0 < m)
        row_of[seq[ok] - c0] = np.flatnonzero(ok)
        cnt = np.zeros(m, np.int64)
        sil = np.zeros(m)
        pots = np.full(m, CENTRE, np.int64)
        x = np.asarray(columns["position"], float)
        last = 0
        for c in range(1, m):
            r = row_of[c - 1]
            if r >= 0:
                last = max(force_counts(f[r], self.full_scale), -FORCE_MAX)
            cnt[c] = last
            r1 = row_of[c]
            # the pot the pass read: its record (row_of[c]), or the one before
            pots[c] = (min(max(CENTRE + round(float(x[r1]) / self.position_scale), 0),
                           POSITION_MAX) if r1 >= 0 else pots[c - 1])
            if r1 >= 1 and row_of[c - 1] >= 0:
                sil[c] = t[r1] - t[row_of[c - 1]]
        lo, hi = SILENCE_DOUBT_S
        sure = enable_passes(cnt, sil, pots, threshold=hi, delay=d)
        maybe = enable_passes(cnt, sil, pots, threshold=lo, delay=d)
        rows = np.arange(n)
        pas = seq - c0 + 1
        inside = pas < m
        fs = self.full_scale / 254.0
        a = np.where(inside, sure[np.minimum(pas, m - 1)], 0) * fs
        b = np.where(inside, maybe[np.minimum(pas, m - 1)], 0) * fs
        nominal = acc.applied
        new = 0.5 * (a + b)
        differs = (np.abs(new - nominal) > 1e-12) | (np.abs(a - b) > 1e-12)
        differs &= rows >= d
        if not differs.any():
            return acc
        acc.applied = np.where(differs, new, nominal)
        acc.half_width = np.where(differs, np.maximum(acc.half_width, 0.5 * np.abs(a - b)),
                                  acc.half_width)
        acc.late = acc.late | differs
        return acc

    def _parser_account(self, columns: dict, force, acc):
        """Widen ``acc`` (:meth:`Driver.account`) for the ``.ino``'s parser: the command
        *after* one whose answer never came may have been read as the rest of a damaged
        packet (module notes: a lost force byte makes the firmware take the next 127 as
        fader B's force and run the pass with the damaged packet's fader-A byte). Its
        force is then the one sent, the one before (fader B's byte lost) or fader B's 0
        (fader A's byte lost); driving fader B, the one sent or +127 counts (B's byte is
        the 127). The row it acts on gets the middle of those and half their range.

        Parameters
        ----------
        columns : dict of str to ndarray
            Telemetry columns (``flags`` marks the estimated rows).
        force : ndarray, shape (n,)
            The force each row's command carried [N].
        acc : hapsim.applied.AppliedAccount or None
            The base account (None: every answer came; returned as is).

        Returns
        -------
        hapsim.applied.AppliedAccount or None
        """
        import numpy as np
        d = getattr(self, "loop_delay", None)
        flags = columns.get("flags")
        if acc is None or d is None or flags is None:
            return acc
        est = np.flatnonzero((np.asarray(flags) & FLAG_ESTIMATED) != 0)
        n = acc.applied.size
        fq = self.applied_forces(force)
        for e in est:
            r = e + d                          # the force of command e + 1 (row e's) acts
            if r >= n:
                continue
            if self.axis == 0:
                cand = [fq[e], fq[e - 1] if e >= 1 else 0.0, 0.0]
            else:
                cand = [fq[e], 127 * self.force_scale]
            lo = min(min(cand), acc.applied[r] - acc.half_width[r])
            hi = max(max(cand), acc.applied[r] + acc.half_width[r])
            acc.applied[r] = 0.5 * (lo + hi)
            acc.half_width[r] = 0.5 * (hi - lo)
        return acc

    def decoder(self):
        """A fresh host-side decoder returning the driven fader's position [m].

        Returns
        -------
        MappedDecoder
            Over a :class:`RecordDecoder`: ``(count - 127) * position_scale`` [m].
        """
        ax = self.axis
        mpc = self.position_scale
        return MappedDecoder(RecordDecoder(), lambda r: (r[ax] - CENTRE) * mpc)

"""FireFader (E. Berdahl and A. Kontogeorgakopoulos): two motorised faders, serial bytes.

Layout, as the published host code reads and writes it (Berdahl's Pd patch and Arduino
firmware, as used e.g. by the SuperCollider host in abramhindle/firefadervocoder):

host -> device, one packet per update ::

    [127, fA, fB]        fA, fB: forces as signed bytes (two's complement), clamped to
                         -127..126 so that 127 (the packet start) never appears in them

device -> host, one record per packet ::

    [255, pA, pB, b3, b4, b5, b6]   pA, pB: fader positions 0..254 (255 is the record
                                    start and never a value); four more bytes 0..254

57600 baud with RTS/CTS flow control. The host code maps 127 counts to 1.56 (its force unit
at ``scale = 1``), and a position count to 0.39 mm (the fader travel is 99 mm over 254
counts). This module drives fader A as hapsim's one axis, with the position measured from
the middle of the travel (count 127) and fader B held at zero force.

Neither direction has a sequence number or a checksum: the decoders resynchronise on the
start byte and count what they drop; a corrupted value byte is a wrong force or position.
"""

from __future__ import annotations

import math

from hapsim.drivers.base import Driver, MappedDecoder

__all__ = ["FireFader", "HOST_START", "DEVICE_START", "POSITION_MAX", "FORCE_MIN", "FORCE_MAX",
           "METRES_PER_COUNT", "FULL_SCALE_N", "encode_packet", "encode_record",
           "force_counts", "RecordDecoder", "PacketDecoder"]

HOST_START = 127
DEVICE_START = 255
RECORD_BYTES = 6
POSITION_MAX = 254
FORCE_MIN = -127
FORCE_MAX = 126
#: Position resolution [m/count] (99 mm of travel over 254 counts, Berdahl's host code).
METRES_PER_COUNT = 0.00039
#: Force at 127 counts [N] (the host code's unit at scale 1; set ``full_scale`` to the
#: calibration of your amplifier).
FULL_SCALE_N = 1.56
#: The count at the middle of the travel: position 0 of the driven axis.
CENTRE = 127

LIMITS = """\
FireFader protocol limits (hapsim --driver firefader):
  host-clocked only: the device has no clock hapsim can read and no sequence numbers,
    so the loop runs on the host's clock and the delay d cannot be measured: the scene's
    device.delay is taken as given (identify it with 'hapsim identify')
  no checksum: a corrupted byte is a wrong force or position; only a lost start byte or
    a truncated record is noticed (resync, counted as bad frames)
  resolution: position 0.39 mm per count (0..254 over 99 mm), force full_scale/127 per
    count (-127..126; 12.3 mN at the default 1.56 N): the THS is closed through both
    quantisers, so measured (k, b) equal the prediction only to the bound these give
  57600 baud, RTS/CTS: a 3-byte packet and a 7-byte record take 1.7 ms on the wire,
    so rates above ~500 Hz are not reachable
  no watchdog in the protocol: the host sends zero force at the end, on a stop or a loss"""


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


class FireFader(Driver):
    """The FireFader as a 1-DoF device (module notes).

    Parameters
    ----------
    axis : {0, 1}
        Fader driven as hapsim's axis (0: A, 1: B); the other gets zero force.
    full_scale : float > 0
        Force at 127 counts [N] (default :data:`FULL_SCALE_N`).

    Raises
    ------
    ConfigError
        A bad axis or full scale.
    """

    name = "firefader"
    baud = 57600
    rtscts = True
    position_scale = METRES_PER_COUNT
    native_rate_hz = 500.0
    device_id = 0x46464144            # "FFAD"
    limits = LIMITS

    def __init__(self, axis: int = 0, full_scale: float = FULL_SCALE_N) -> None:
        from hapsim.errors import ConfigError
        if axis not in (0, 1):
            raise ConfigError(f"FireFader axis must be 0 (A) or 1 (B), got {axis!r}",
                              key="axis")
        if not (math.isfinite(full_scale) and full_scale > 0):
            raise ConfigError(f"must be a positive force [N], got {full_scale!r}",
                              key="full_scale")
        self.axis = axis
        self.full_scale = float(full_scale)
        self.force_scale = self.full_scale / 127.0
        self.force_limit = FORCE_MAX * self.force_scale

    def encode_force(self, force: float) -> bytes:
        """Packet commanding ``force`` [N] on the driven fader, 0 on the other.

        The count is clamped to -126..126 (the protocol's -127 would exceed the symmetric
        force limit, 126 counts, by one count)."""
        c = max(force_counts(force, self.full_scale), -FORCE_MAX)
        return encode_packet(c, 0) if self.axis == 0 else encode_packet(0, c)

    def applied_force(self, force: float) -> float:
        """The force the packet of ``force`` commands [N]: its count times the scale."""
        return max(force_counts(force, self.full_scale), -FORCE_MAX) * self.force_scale

    def decoder(self):
        """A fresh host-side decoder returning the driven fader's position [m]."""
        ax = self.axis
        return MappedDecoder(RecordDecoder(), lambda r: (r[ax] - CENTRE) * METRES_PER_COUNT)

"""I/O-free codec of the hapsim framed serial protocol (see ``PROTOCOL.md``).

A frame on the wire is ``COBS(packet) + b"\\x00"`` where
``packet = type:u8 | body | crc:u16`` (body little-endian, fixed layout; CRC-16/CCITT-FALSE
over ``type | body``, sent most significant byte first). This module turns message objects
into frames (:func:`encode`), single frames into messages (:func:`decode_frame`) and an
arbitrary byte stream into messages (:class:`StreamDecoder`). It performs no I/O and imports
nothing from ``hapsim``.

Sources: COBS, S. Cheshire and M. Baker, "Consistent Overhead Byte Stuffing", IEEE/ACM
Trans. Networking 7(2), 1999; CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection,
no final XOR; check value 0x29B1), as computed by :func:`binascii.crc_hqx`.
"""

from __future__ import annotations

import math
import struct
from binascii import crc_hqx
from collections import deque
from dataclasses import dataclass
from typing import ClassVar, Union

from cobs import cobs as _cobs

__all__ = [
    "PROTOCOL_VERSION", "MAX_FRAME", "MAX_PACKET", "MAX_AXES", "CRC_INIT",
    "MSG_HELLO", "MSG_HELLO_REQUEST", "MSG_CONFIG", "MSG_LINK", "MSG_SENSORS_REQUEST",
    "MSG_SENSORS", "MSG_STATE", "MSG_FORCE", "MSG_VELOCITY",
    "MSG_STATE_COMPACT", "MSG_FORCE_COMPACT",
    "MSG_PING", "MSG_PONG", "MSG_FAULT", "MSG_STOP", "MESSAGE_TYPES", "SENSOR_VELOCITY",
    "FEATURE_COMPACT", "COMPACT_LAG_MAX",
    "STATUS_ARMED", "STATUS_WATCHDOG_TRIPPED", "STATUS_FORCE_CLAMPED", "STATUS_FAULT",
    "STATUS_RX_ERROR", "STATUS_OVERRUN", "STATUS_CONFIGURED", "STATUS_FORCE_APPLIED",
    "FAULT_WATCHDOG", "FAULT_BAD_CONFIG", "FAULT_SENSOR", "FAULT_AMPLIFIER",
    "FAULT_NON_FINITE_FORCE", "FAULT_AXES_MISMATCH", "FAULT_RX_ERRORS", "FAULT_OVERRUN",
    "FAULT_VERSION_MISMATCH", "FAULT_NAMES",
    "Hello", "HelloRequest", "Config", "Link", "SensorsRequest", "Sensors", "State", "Force",
    "Velocity", "StateCompact", "ForceCompact", "Ping", "Pong", "Fault", "Stop",
    "Message", "CompactExpander", "compact_force", "F32_MAX", "FrameError", "DecoderStats", "StreamDecoder",
    "encode", "encode_packet", "decode_frame", "decode_packet", "crc16",
    "state_frame_bytes", "force_frame_bytes", "velocity_frame_bytes", "LINK_LOAD",
    "link_max_rate", "state_compact_frame_bytes", "force_compact_frame_bytes",
    "ROUND_TRIP_SHARE", "link_round_trip", "wants_compact",
]

# --------------------------------------------------------------------------- constants

#: Protocol version carried by HELLO and HELLO_REQUEST. Bump on any incompatible change.
PROTOCOL_VERSION = 1
#: Maximum length of a frame on the wire [bytes], COBS bytes plus the 0x00 delimiter.
MAX_FRAME = 128
#: Maximum length of a decoded packet (type + body + CRC) [bytes]: ``MAX_FRAME - 2``
#: (COBS adds exactly one byte to any packet shorter than 255 bytes).
MAX_PACKET = MAX_FRAME - 2
#: Number of axes a device may have: 1..MAX_AXES.
MAX_AXES = 8
#: Initial value of the CRC-16/CCITT-FALSE register.
CRC_INIT = 0xFFFF

MSG_HELLO = 0x01
MSG_HELLO_REQUEST = 0x02
MSG_CONFIG = 0x03
#: LINK, device -> host with HELLO: the device's serial line. Added within version 1
#: (PROTOCOL.md §9): a host written before it counts it as an unknown type.
MSG_LINK = 0x04
#: SENSORS_REQUEST, host -> device, and SENSORS, device -> host (its answer): the host asks
#: for extra sensor messages (VELOCITY). Added within version 1 (PROTOCOL.md §4, §9): a
#: device written before them drops the request (unknown type) and never answers.
MSG_SENSORS_REQUEST = 0x05
MSG_SENSORS = 0x06
MSG_STATE = 0x10
MSG_FORCE = 0x11
#: VELOCITY, device -> host, just before the STATE of the same ``seq``, only while the host
#: enabled it by SENSORS_REQUEST. Added within version 1 (PROTOCOL.md §9).
MSG_VELOCITY = 0x12
#: STATE_COMPACT, device -> host, and FORCE_COMPACT, host -> device: STATE and FORCE with
#: 16-bit sequence numbers and binary32 values, sent only in a session whose host asked for
#: them (SENSORS_REQUEST bit :data:`FEATURE_COMPACT`). Added within version 1 (PROTOCOL.md
#: §4 "Compact frames", §9).
MSG_STATE_COMPACT = 0x13
MSG_FORCE_COMPACT = 0x14
MSG_PING = 0x20
MSG_PONG = 0x21
MSG_FAULT = 0x30
MSG_STOP = 0x31

#: STATE.status bits.
STATUS_ARMED = 0x0001
STATUS_WATCHDOG_TRIPPED = 0x0002
STATUS_FORCE_CLAMPED = 0x0004
STATUS_FAULT = 0x0008
STATUS_RX_ERROR = 0x0010
STATUS_OVERRUN = 0x0020
STATUS_CONFIGURED = 0x0040
#: ``force_seq`` names a FORCE applied since the last CONFIG (clear: none yet, and
#: ``force_seq`` = 0 means nothing). Added within version 1 (PROTOCOL.md §9): a device
#: written before it never sets it.
STATUS_FORCE_APPLIED = 0x0080

#: Sensor bits of SENSORS_REQUEST.sensors and SENSORS.offered / SENSORS.enabled.
SENSOR_VELOCITY = 0x0001
#: SENSORS_REQUEST / SENSORS bit: STATE_COMPACT instead of STATE, FORCE_COMPACT accepted
#: (PROTOCOL.md §4 "Compact frames"). Added within version 1.
FEATURE_COMPACT = 0x0002
#: STATE_COMPACT.lag saturates here: 255 means "255 ticks or more".
COMPACT_LAG_MAX = 255
#: Largest finite binary32 [N]: FORCE_COMPACT saturates a larger finite force to it.
F32_MAX = 3.4028234663852886e38

#: FAULT.code values.
FAULT_WATCHDOG = 0x0001
FAULT_BAD_CONFIG = 0x0002
FAULT_SENSOR = 0x0003
FAULT_AMPLIFIER = 0x0004
FAULT_NON_FINITE_FORCE = 0x0005
FAULT_AXES_MISMATCH = 0x0006
FAULT_RX_ERRORS = 0x0007
FAULT_OVERRUN = 0x0008
FAULT_VERSION_MISMATCH = 0x0009

FAULT_NAMES = {
    FAULT_WATCHDOG: "WATCHDOG",
    FAULT_BAD_CONFIG: "BAD_CONFIG",
    FAULT_SENSOR: "SENSOR",
    FAULT_AMPLIFIER: "AMPLIFIER",
    FAULT_NON_FINITE_FORCE: "NON_FINITE_FORCE",
    FAULT_AXES_MISMATCH: "AXES_MISMATCH",
    FAULT_RX_ERRORS: "RX_ERRORS",
    FAULT_OVERRUN: "OVERRUN",
    FAULT_VERSION_MISMATCH: "VERSION_MISMATCH",
}


#: Largest share of the line the STATE frames may take (the rest: FAULT, PONG, tick jitter).
LINK_LOAD = 0.8


def state_frame_bytes(n_axes: int = 1) -> int:
    """Bytes on the wire of a STATE frame with ``n_axes`` axes (PROTOCOL.md §3).

    Parameters
    ----------
    n_axes : int, 1..8

    Returns
    -------
    int
        ``5 + 18 + 8 n``: type, CRC, one COBS byte and the delimiter around the body
        (COBS adds exactly one byte to a packet shorter than 255 bytes, §1).
    """
    return 5 + 18 + 8 * int(n_axes)


def force_frame_bytes(n_axes: int = 1) -> int:
    """Bytes on the wire of a FORCE frame with ``n_axes`` axes: ``5 + 4 + 8 n`` (§3)."""
    return 5 + 4 + 8 * int(n_axes)


def velocity_frame_bytes(n_axes: int = 1) -> int:
    """Bytes on the wire of a VELOCITY frame with ``n_axes`` axes: ``5 + 4 + 8 n`` (§3)."""
    return 5 + 4 + 8 * int(n_axes)


def state_compact_frame_bytes(n_axes: int = 1) -> int:
    """Bytes on the wire of a STATE_COMPACT frame: ``5 + 4 + 4 n`` (13 for one axis, §4)."""
    return 5 + 4 + 4 * int(n_axes)


def force_compact_frame_bytes(n_axes: int = 1) -> int:
    """Bytes on the wire of a FORCE_COMPACT frame: ``5 + 2 + 4 n`` (11 for one axis, §4)."""
    return 5 + 2 + 4 * int(n_axes)


#: Largest share of the tick period the round trip of one STATE and one FORCE on the wire
#: may take before a host asks for compact frames (PROTOCOL.md §4 "Compact frames": the
#: rest of the period is the device's sampling, encoding and decoding and the host's answer).
ROUND_TRIP_SHARE = 0.5


def link_round_trip(baud: int, bits_per_byte: int = 10, n_axes: int = 1,
                    compact: bool = False) -> float:
    """Time one STATE up and the FORCE answering it down spend on a serial line [s].

    Parameters
    ----------
    baud : int
        Line rate [bit/s]; 0 means "not a UART" (no time on the line).
    bits_per_byte : int
        Bits per byte on the line (10 for 8N1).
    n_axes : int
        Axes per STATE/FORCE.
    compact : bool
        STATE_COMPACT and FORCE_COMPACT instead of STATE and FORCE.

    Returns
    -------
    float
        ``(up + down) * bits_per_byte / baud`` with ``up``, ``down`` the frame bytes
        (PROTOCOL.md §4 "Compact frames", the byte budget); 0 for ``baud == 0``. One axis at
        2 Mbaud 8N1: 240 us full (31 + 17 bytes), 120 us compact (13 + 11 bytes).
    """
    if baud <= 0:
        return 0.0
    if compact:
        n = state_compact_frame_bytes(n_axes) + force_compact_frame_bytes(n_axes)
    else:
        n = state_frame_bytes(n_axes) + force_frame_bytes(n_axes)
    return n * bits_per_byte / baud


def wants_compact(baud: int, bits_per_byte: int, n_axes: int, rate_hz: float) -> bool:
    """Whether a host should ask for compact frames: the full frames' round trip on the
    line takes more than :data:`ROUND_TRIP_SHARE` of the tick period (PROTOCOL.md §4).

    Parameters
    ----------
    baud, bits_per_byte : int
        The device's LINK [bit/s], [bits].
    n_axes : int
        Axes per STATE/FORCE.
    rate_hz : float
        Tick rate the host is about to CONFIGure [Hz], > 0.

    Returns
    -------
    bool
        True e.g. at 4 kHz on 2 Mbaud (240 us of a 250 us period), False at 1 kHz (240 of
        1000 us) and for a device that is not a UART (``baud == 0``).
    """
    return link_round_trip(baud, bits_per_byte, n_axes) > ROUND_TRIP_SHARE / float(rate_hz)


def link_max_rate(baud: int, bits_per_byte: int = 10, n_axes: int = 1,
                  load: float = LINK_LOAD, velocity: bool = False,
                  compact: bool = False) -> float:
    """Largest tick rate a serial line carries: one STATE up and one FORCE down per tick.

    The line is full duplex, so the longer direction (device -> host: STATE, and VELOCITY
    when enabled) decides: a rate is carried when ``rate * up_bytes * bits_per_byte <= load
    * baud`` with ``up_bytes = state_frame_bytes(n) (+ velocity_frame_bytes(n))``
    (PROTOCOL.md §4, LINK).

    Parameters
    ----------
    baud : int
        Line rate [bit/s]; 0 means "not a UART" (no limit).
    bits_per_byte : int
        Bits per byte on the line (10 for 8N1).
    n_axes : int
        Axes per STATE/FORCE.
    load : float
        Share of the line the STATE frames may take, 0 < load <= 1.
    velocity : bool
        A VELOCITY frame goes up with every STATE (the host enabled it, §4 SENSORS).
    compact : bool
        STATE_COMPACT frames instead of STATE (the host enabled them, §4 "Compact frames").

    Returns
    -------
    float
        The largest rate [Hz]; ``inf`` for ``baud == 0``.
    """
    if baud <= 0:
        return math.inf
    up = (state_compact_frame_bytes(n_axes) if compact else state_frame_bytes(n_axes)) + (
        velocity_frame_bytes(n_axes) if velocity else 0)
    return load * baud / (bits_per_byte * up)


def crc16(data: bytes, crc: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data``.

    Parameters
    ----------
    data : bytes-like
        Bytes to checksum.
    crc : int, optional
        Initial register value, 0xFFFF for this protocol.

    Returns
    -------
    int
        CRC in 0..0xFFFF; ``crc16(b"123456789") == 0x29B1``.

    Notes
    -----
    Poly 0x1021, no reflection, no final XOR (``binascii.crc_hqx``). Hamming distance 4 for
    messages up to 32751 bits: every 1-, 2- and 3-bit error and every burst up to 16 bits is
    detected.
    """
    return crc_hqx(data, crc)


# --------------------------------------------------------------------------- errors


class FrameError(ValueError):
    """A frame cannot be decoded.

    Parameters
    ----------
    message : str
        What is wrong.
    reason : str
        Machine-readable class, the name of the :class:`DecoderStats` counter it feeds:
        ``"bad_cobs"``, ``"bad_crc"``, ``"overlong"``, ``"unknown_type"`` or
        ``"malformed"``.
    """

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Hello:
    """HELLO, device -> host, on connect and on HELLO_REQUEST.

    Parameters
    ----------
    protocol_version : int, 0..255
        Protocol version the device speaks (:data:`PROTOCOL_VERSION`).
    n_axes : int, 1..8
        Number of axes; fixes the length of STATE and FORCE bodies.
    device_id : int, 0..2**32-1
        Device identifier (serial number or model-specific id).
    position_scale : float
        Position sensor resolution [m/count], >= 0 (informational: STATE carries metres;
        0: not stated).
    force_scale : float
        Actuator step [N/unit], >= 0: 0, a continuous actuator; > 0, the device applies
        each FORCE as the reference firmware's binary32 step rule names it (PROTOCOL.md
        §4, HELLO; :func:`hapsim.applied.firmware_force`).
    force_limit : float
        Largest force magnitude the device will ever apply [N], >= 0.
    native_rate_hz : float
        Tick rate the device runs at by default [Hz], > 0.
    """

    TYPE: ClassVar[int] = MSG_HELLO
    protocol_version: int
    n_axes: int
    device_id: int
    position_scale: float
    force_scale: float
    force_limit: float
    native_rate_hz: float


@dataclass(frozen=True, slots=True)
class HelloRequest:
    """HELLO_REQUEST ("WHO"), host -> device: answer with HELLO.

    Parameters
    ----------
    protocol_version : int, 0..255
        Protocol version the host speaks.
    """

    TYPE: ClassVar[int] = MSG_HELLO_REQUEST
    protocol_version: int = PROTOCOL_VERSION


@dataclass(frozen=True, slots=True)
class Config:
    """CONFIG, host -> device: set rate, watchdog and force limit; arms the device.

    Parameters
    ----------
    rate_hz : float
        Tick rate [Hz], > 0 and <= what the device supports.
    watchdog_us : int, 1..2**32-1
        Watchdog timeout [us]: force is zeroed when no FORCE arrives within it.
    force_limit : float
        Force clamp [N], >= 0; the device uses ``min(force_limit, HELLO.force_limit)``.
    """

    TYPE: ClassVar[int] = MSG_CONFIG
    rate_hz: float
    watchdog_us: int
    force_limit: float


@dataclass(frozen=True, slots=True)
class Link:
    """LINK, device -> host, sent just before each HELLO: the device's serial line.

    The host checks with it that a STATE and a FORCE frame fit one tick at the rate it is
    about to CONFIGure (PROTOCOL.md §4, LINK).

    Parameters
    ----------
    baud : int, 0..2**32-1
        Line rate of the device's UART [bit/s]; 0: not a UART (USB, no limit announced).
    bits_per_byte : int, 0..255
        Bits on the line per byte: start + data + parity + stop (10 for 8N1).
    """

    TYPE: ClassVar[int] = MSG_LINK
    baud: int
    bits_per_byte: int = 10


@dataclass(frozen=True, slots=True)
class SensorsRequest:
    """SENSORS_REQUEST, host -> device: which extra sensor messages to send (PROTOCOL.md §4).

    The device answers :class:`Sensors` at once and keeps the setting until the next
    SENSORS_REQUEST or a reset (not cleared by CONFIG or STOP).

    Parameters
    ----------
    sensors : int, 0..0xFFFF
        OR of ``SENSOR_*`` bits the host asks for (:data:`SENSOR_VELOCITY`: a
        :class:`Velocity` before every STATE); 0 turns them all off.
    """

    TYPE: ClassVar[int] = MSG_SENSORS_REQUEST
    sensors: int


@dataclass(frozen=True, slots=True)
class Sensors:
    """SENSORS, device -> host: the answer to each SENSORS_REQUEST.

    A device that has no sensor beyond position answers ``offered = enabled = 0``; a device
    written before this message does not answer at all (the host waits a bounded time and
    takes silence as "nothing offered").

    Parameters
    ----------
    offered : int, 0..0xFFFF
        OR of the ``SENSOR_*`` bits the device can send.
    enabled : int, 0..0xFFFF
        The bits it sends from now on: ``requested & offered``.
    """

    TYPE: ClassVar[int] = MSG_SENSORS
    offered: int
    enabled: int


@dataclass(frozen=True, slots=True)
class State:
    """STATE, device -> host, once per device tick.

    Parameters
    ----------
    seq : int, 0..2**32-1
        Tick counter, +1 per STATE, wraps modulo 2**32.
    time_us : int, 0..2**64-1
        Device time at the position sample [us].
    status : int, 0..0xFFFF
        OR of ``STATUS_*`` bits.
    force_seq : int, 0..2**32-1
        ``seq`` field of the last FORCE the device applied (the delay in ticks is
        ``seq - force_seq``); meaningful only when ``status`` has
        :data:`STATUS_FORCE_APPLIED` (0 before any FORCE, but 0 is also a valid FORCE seq).
    position : tuple of float, length n_axes (1..8)
        Position per axis [m] (or [rad] for a rotary axis), IEEE-754 binary64.
    """

    TYPE: ClassVar[int] = MSG_STATE
    seq: int
    time_us: int
    status: int
    force_seq: int
    position: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Force:
    """FORCE, host -> device, in answer to a STATE.

    Parameters
    ----------
    seq : int, 0..2**32-1
        ``seq`` of the STATE this force was computed from.
    force : tuple of float, length n_axes (1..8)
        Force per axis [N] (or [N m] for a rotary axis), IEEE-754 binary64.
    """

    TYPE: ClassVar[int] = MSG_FORCE
    seq: int
    force: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Velocity:
    """VELOCITY, device -> host, just before the STATE with the same ``seq``, while enabled.

    Parameters
    ----------
    seq : int, 0..2**32-1
        ``seq`` of the STATE it belongs to (the velocity is measured at that STATE's
        position sample, ``time_us``).
    velocity : tuple of float, length n_axes (1..8)
        Measured velocity per axis [m/s] (or [rad/s] for a rotary axis), IEEE-754 binary64.
    """

    TYPE: ClassVar[int] = MSG_VELOCITY
    seq: int
    velocity: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class StateCompact:
    """STATE_COMPACT, device -> host: a STATE in 13 bytes (one axis), once per tick instead
    of STATE while the host enabled :data:`FEATURE_COMPACT` (PROTOCOL.md §4).

    :class:`CompactExpander` turns it back into the :class:`State` it stands for.

    Parameters
    ----------
    seq : int, 0..0xFFFF
        Low 16 bits of the tick counter (the device restarts it at 0 at each CONFIG).
    status : int, 0..0xFF
        Low 8 bits of the status (every status bit of version 1).
    lag : int, 0..255
        ``seq - force_seq`` (mod 2**32) saturated at :data:`COMPACT_LAG_MAX`; 0 while
        FORCE_APPLIED is clear.
    position : tuple of float, length n_axes (1..8)
        Position per axis [m] (or [rad]), IEEE-754 binary32 (a value that is not a binary32
        is rounded to nearest, ties to even, when encoded).
    """

    TYPE: ClassVar[int] = MSG_STATE_COMPACT
    seq: int
    status: int
    lag: int
    position: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class ForceCompact:
    """FORCE_COMPACT, host -> device: a FORCE in 11 bytes (one axis), sent instead of FORCE
    in a session with :data:`FEATURE_COMPACT` enabled (PROTOCOL.md §4).

    Parameters
    ----------
    seq : int, 0..0xFFFF
        Low 16 bits of the ``seq`` of the STATE answered (the device restores the rest
        from its own tick counter).
    force : tuple of float, length n_axes (1..8)
        Force per axis [N] (or [N m]), IEEE-754 binary32 (:func:`compact_force` rounds and
        saturates a float64 force).
    """

    TYPE: ClassVar[int] = MSG_FORCE_COMPACT
    seq: int
    force: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Ping:
    """PING, host -> device: the device answers with PONG at once.

    Parameters
    ----------
    nonce : int, 0..2**32-1
        Echoed in PONG.
    host_time_us : int, 0..2**64-1
        Host clock when sent [us]; echoed in PONG.
    """

    TYPE: ClassVar[int] = MSG_PING
    nonce: int
    host_time_us: int


@dataclass(frozen=True, slots=True)
class Pong:
    """PONG, device -> host, answer to PING.

    Parameters
    ----------
    nonce : int, 0..2**32-1
        Copied from the PING.
    host_time_us : int, 0..2**64-1
        Copied from the PING [us].
    device_time_us : int, 0..2**64-1
        Device clock when the PING was received [us].
    """

    TYPE: ClassVar[int] = MSG_PONG
    nonce: int
    host_time_us: int
    device_time_us: int


@dataclass(frozen=True, slots=True)
class Fault:
    """FAULT, device -> host.

    Parameters
    ----------
    code : int, 0..0xFFFF
        One of ``FAULT_*``.
    detail : int, 0..2**32-1
        Code-specific detail (e.g. the axis, the count, the offending value's bits).
    """

    TYPE: ClassVar[int] = MSG_FAULT
    code: int
    detail: int = 0


@dataclass(frozen=True, slots=True)
class Stop:
    """STOP, host -> device: zero force at once and disarm (re-arm with CONFIG)."""

    TYPE: ClassVar[int] = MSG_STOP


Message = Union[Hello, HelloRequest, Config, Link, SensorsRequest, Sensors, State, Force,
                Velocity, StateCompact, ForceCompact, Ping, Pong, Fault, Stop]

#: Message class by type id.
MESSAGE_TYPES = {cls.TYPE: cls for cls in (Hello, HelloRequest, Config, Link, SensorsRequest,
                                           Sensors, State, Force, Velocity, StateCompact,
                                           ForceCompact, Ping, Pong, Fault, Stop)}

# --------------------------------------------------------------------------- layouts

_HELLO = struct.Struct("<BBBI4d")
_HELLO_REQUEST = struct.Struct("<BB")
_CONFIG = struct.Struct("<BdId")
_LINK = struct.Struct("<BIB")
_SENSORS_REQUEST = struct.Struct("<BH")
_SENSORS = struct.Struct("<BHH")
_PING = struct.Struct("<BIQ")
_PONG = struct.Struct("<BIQQ")
_FAULT = struct.Struct("<BHI")
_STOP = struct.Struct("<B")
_STATE_HEAD = "<BIQHI"
_FORCE_HEAD = "<BI"
# Index n -> Struct for n axes (index 0 unused).
_STATE = (None,) + tuple(struct.Struct(f"{_STATE_HEAD}{n}d") for n in range(1, MAX_AXES + 1))
_FORCE = (None,) + tuple(struct.Struct(f"{_FORCE_HEAD}{n}d") for n in range(1, MAX_AXES + 1))
# Packet length (type + body, without CRC) -> (Struct, n_axes).
_STATE_BY_LEN = {s.size: (s, n) for n, s in enumerate(_STATE) if s is not None}
_FORCE_BY_LEN = {s.size: (s, n) for n, s in enumerate(_FORCE) if s is not None}
# VELOCITY has FORCE's layout (seq, f64[n]) under its own type id.
_VELOCITY_BY_LEN = _FORCE_BY_LEN
# STATE_COMPACT: seq u16, status u8, lag u8, f32[n]; FORCE_COMPACT: seq u16, f32[n].
_STATE_C = (None,) + tuple(struct.Struct(f"<BHBB{n}f") for n in range(1, MAX_AXES + 1))
_FORCE_C = (None,) + tuple(struct.Struct(f"<BH{n}f") for n in range(1, MAX_AXES + 1))
_STATE_C_BY_LEN = {s.size: s for s in _STATE_C if s is not None}
_FORCE_C_BY_LEN = {s.size: s for s in _FORCE_C if s is not None}
_CRC = struct.Struct(">H")

assert max(_STATE[MAX_AXES].size, _HELLO.size) + 2 <= MAX_PACKET


# --------------------------------------------------------------------------- encoding


def _pack_hello(m: Hello) -> bytes:
    if not 1 <= m.n_axes <= MAX_AXES:
        raise ValueError(f"Hello.n_axes must be 1..{MAX_AXES}, got {m.n_axes!r}")
    return _HELLO.pack(MSG_HELLO, m.protocol_version, m.n_axes, m.device_id,
                       m.position_scale, m.force_scale, m.force_limit, m.native_rate_hz)


def _pack_state(m: State) -> bytes:
    n = len(m.position)
    if not 1 <= n <= MAX_AXES:
        raise ValueError(f"State.position must have 1..{MAX_AXES} axes, got {n}")
    return _STATE[n].pack(MSG_STATE, m.seq, m.time_us, m.status, m.force_seq, *m.position)


def _pack_force(m: Force) -> bytes:
    n = len(m.force)
    if not 1 <= n <= MAX_AXES:
        raise ValueError(f"Force.force must have 1..{MAX_AXES} axes, got {n}")
    return _FORCE[n].pack(MSG_FORCE, m.seq, *m.force)


def _pack_velocity(m: Velocity) -> bytes:
    n = len(m.velocity)
    if not 1 <= n <= MAX_AXES:
        raise ValueError(f"Velocity.velocity must have 1..{MAX_AXES} axes, got {n}")
    return _FORCE[n].pack(MSG_VELOCITY, m.seq, *m.velocity)


def _pack_state_compact(m: StateCompact) -> bytes:
    n = len(m.position)
    if not 1 <= n <= MAX_AXES:
        raise ValueError(f"StateCompact.position must have 1..{MAX_AXES} axes, got {n}")
    return _STATE_C[n].pack(MSG_STATE_COMPACT, m.seq, m.status, m.lag, *m.position)


def _pack_force_compact(m: ForceCompact) -> bytes:
    n = len(m.force)
    if not 1 <= n <= MAX_AXES:
        raise ValueError(f"ForceCompact.force must have 1..{MAX_AXES} axes, got {n}")
    return _FORCE_C[n].pack(MSG_FORCE_COMPACT, m.seq, *m.force)


_PACKERS = {
    Hello: _pack_hello,
    HelloRequest: lambda m: _HELLO_REQUEST.pack(MSG_HELLO_REQUEST, m.protocol_version),
    Config: lambda m: _CONFIG.pack(MSG_CONFIG, m.rate_hz, m.watchdog_us, m.force_limit),
    Link: lambda m: _LINK.pack(MSG_LINK, m.baud, m.bits_per_byte),
    SensorsRequest: lambda m: _SENSORS_REQUEST.pack(MSG_SENSORS_REQUEST, m.sensors),
    Sensors: lambda m: _SENSORS.pack(MSG_SENSORS, m.offered, m.enabled),
    State: _pack_state,
    Force: _pack_force,
    Velocity: _pack_velocity,
    StateCompact: _pack_state_compact,
    ForceCompact: _pack_force_compact,
    Ping: lambda m: _PING.pack(MSG_PING, m.nonce, m.host_time_us),
    Pong: lambda m: _PONG.pack(MSG_PONG, m.nonce, m.host_time_us, m.device_time_us),
    Fault: lambda m: _FAULT.pack(MSG_FAULT, m.code, m.detail),
    Stop: lambda m: _STOP.pack(MSG_STOP),
}


def encode_packet(message: Message) -> bytes:
    """Packet of ``message`` before COBS: ``type | body | crc`` (CRC big-endian).

    Parameters
    ----------
    message : Message
        Any message class of this module (Hello .. Stop).

    Returns
    -------
    bytes
        ``3 + len(body)`` bytes, at most :data:`MAX_PACKET`.

    Raises
    ------
    TypeError
        ``message`` is not a protocol message.
    ValueError
        A field is out of its range (integer overflow, axis count not 1..8).
    """
    try:
        packer = _PACKERS[type(message)]
    except KeyError:
        raise TypeError(f"not a protocol message: {type(message).__name__}") from None
    try:
        raw = packer(message)
    except (struct.error, OverflowError) as exc:
        raise ValueError(f"{type(message).__name__}: field out of range: {exc}") from None
    return raw + _CRC.pack(crc_hqx(raw, CRC_INIT))


def encode(message: Message) -> bytes:
    """Whole frame of ``message``: ``COBS(type | body | crc) + b"\\x00"``.

    Parameters
    ----------
    message : Message
        Any message class of this module (Hello .. Stop).

    Returns
    -------
    bytes
        The frame, ending with its single 0x00 delimiter, at most :data:`MAX_FRAME`
        bytes. A STATE with one axis is 31 bytes, a FORCE with one axis 17 bytes.

    Raises
    ------
    TypeError
        ``message`` is not a protocol message.
    ValueError
        A field is out of its range (integer overflow, axis count not 1..8).
    """
    return _cobs.encode(encode_packet(message)) + b"\x00"


# --------------------------------------------------------------------------- decoding


def _unpack_hello(p: bytes):
    if len(p) != _HELLO.size:
        raise FrameError(f"HELLO packet of {len(p)} bytes, expected {_HELLO.size}", "malformed")
    _, ver, n, dev, ps, fs, fl, rate = _HELLO.unpack(p)
    if not 1 <= n <= MAX_AXES:
        raise FrameError(f"HELLO n_axes {n} not in 1..{MAX_AXES}", "malformed")
    return Hello(ver, n, dev, ps, fs, fl, rate)


def _unpack_state(p: bytes):
    try:
        s, _n = _STATE_BY_LEN[len(p)]
    except KeyError:
        raise FrameError(f"STATE packet of {len(p)} bytes is not 19 + 8 n, n in 1..{MAX_AXES}",
                         "malformed") from None
    v = s.unpack(p)
    return State(v[1], v[2], v[3], v[4], v[5:])


def _unpack_force(p: bytes):
    try:
        s, _n = _FORCE_BY_LEN[len(p)]
    except KeyError:
        raise FrameError(f"FORCE packet of {len(p)} bytes is not 5 + 8 n, n in 1..{MAX_AXES}",
                         "malformed") from None
    v = s.unpack(p)
    return Force(v[1], v[2:])


def _unpack_velocity(p: bytes):
    try:
        s, _n = _VELOCITY_BY_LEN[len(p)]
    except KeyError:
        raise FrameError(f"VELOCITY packet of {len(p)} bytes is not 5 + 8 n, n in "
                         f"1..{MAX_AXES}", "malformed") from None
    v = s.unpack(p)
    return Velocity(v[1], v[2:])


def _unpack_state_compact(p: bytes):
    try:
        s = _STATE_C_BY_LEN[len(p)]
    except KeyError:
        raise FrameError(f"STATE_COMPACT packet of {len(p)} bytes is not 5 + 4 n, n in "
                         f"1..{MAX_AXES}", "malformed") from None
    v = s.unpack(p)
    return StateCompact(v[1], v[2], v[3], v[4:])


def _unpack_force_compact(p: bytes):
    try:
        s = _FORCE_C_BY_LEN[len(p)]
    except KeyError:
        raise FrameError(f"FORCE_COMPACT packet of {len(p)} bytes is not 3 + 4 n, n in "
                         f"1..{MAX_AXES}", "malformed") from None
    v = s.unpack(p)
    return ForceCompact(v[1], v[2:])


def _fixed(s: struct.Struct, name: str, build):
    size = s.size
    unpack = s.unpack

    def unpacker(p: bytes):
        if len(p) != size:
            raise FrameError(f"{name} packet of {len(p)} bytes, expected {size}", "malformed")
        return build(*unpack(p)[1:])
    return unpacker


_UNPACKERS = {
    MSG_HELLO: _unpack_hello,
    MSG_HELLO_REQUEST: _fixed(_HELLO_REQUEST, "HELLO_REQUEST", HelloRequest),
    MSG_CONFIG: _fixed(_CONFIG, "CONFIG", Config),
    MSG_LINK: _fixed(_LINK, "LINK", Link),
    MSG_SENSORS_REQUEST: _fixed(_SENSORS_REQUEST, "SENSORS_REQUEST", SensorsRequest),
    MSG_SENSORS: _fixed(_SENSORS, "SENSORS", Sensors),
    MSG_STATE: _unpack_state,
    MSG_FORCE: _unpack_force,
    MSG_VELOCITY: _unpack_velocity,
    MSG_STATE_COMPACT: _unpack_state_compact,
    MSG_FORCE_COMPACT: _unpack_force_compact,
    MSG_PING: _fixed(_PING, "PING", Ping),
    MSG_PONG: _fixed(_PONG, "PONG", Pong),
    MSG_FAULT: _fixed(_FAULT, "FAULT", Fault),
    MSG_STOP: _fixed(_STOP, "STOP", Stop),
}


def decode_packet(packet: bytes) -> Message:
    """Message of a packet already COBS-decoded: ``type | body | crc``.

    Parameters
    ----------
    packet : bytes
        Decoded packet, CRC included.

    Returns
    -------
    Message
        The decoded message.

    Raises
    ------
    FrameError
        ``reason`` ``"bad_crc"`` (too short or CRC mismatch), ``"unknown_type"`` or
        ``"malformed"`` (body length or content invalid for its type).
    """
    n = len(packet)
    if n < 3:
        raise FrameError(f"packet of {n} bytes is too short for type and CRC", "bad_crc")
    if n > MAX_PACKET:
        raise FrameError(f"packet of {n} bytes exceeds MAX_PACKET={MAX_PACKET}", "overlong")
    # CRC sent MSB first: the CRC of the whole packet, CRC included, is zero.
    if crc_hqx(packet, CRC_INIT):
        raise FrameError("CRC mismatch", "bad_crc")
    try:
        unpack = _UNPACKERS[packet[0]]
    except KeyError:
        raise FrameError(f"unknown message type 0x{packet[0]:02X}", "unknown_type") from None
    return unpack(packet[:-2])


def decode_frame(frame: bytes) -> Message:
    """Message of one whole frame.

    Parameters
    ----------
    frame : bytes-like
        COBS bytes, with or without the one trailing 0x00 delimiter; no other 0x00.

    Returns
    -------
    Message
        The decoded message.

    Raises
    ------
    FrameError
        ``reason`` ``"overlong"`` (longer than :data:`MAX_FRAME`), ``"bad_cobs"`` (empty,
        interior 0x00 or bad COBS code), ``"bad_crc"``, ``"unknown_type"`` or
        ``"malformed"``. ``FrameError`` is a ``ValueError``.
    """
    frame = bytes(frame)
    if frame[-1:] == b"\x00":
        frame = frame[:-1]
    if len(frame) > MAX_FRAME - 1:
        raise FrameError(f"frame of {len(frame) + 1} bytes exceeds MAX_FRAME={MAX_FRAME}",
                         "overlong")
    if not frame:
        raise FrameError("empty frame", "bad_cobs")
    try:
        packet = _cobs.decode(frame)
    except _cobs.DecodeError as exc:
        raise FrameError(f"COBS: {exc}", "bad_cobs") from None
    return decode_packet(packet)


# --------------------------------------------------------------------------- compact


def compact_force(force: Force) -> ForceCompact:
    """The FORCE_COMPACT a host sends for ``force`` (PROTOCOL.md §4 "Compact frames").

    Parameters
    ----------
    force : Force
        The FORCE answering a STATE (``seq`` 32-bit, forces float64 [N]).

    Returns
    -------
    ForceCompact
        ``seq`` cut to its low 16 bits; each force rounded to binary32 (to nearest, ties to
        even, IEEE-754 as the device's own float64 -> float32 conversion of a full FORCE)
        and a finite force beyond the binary32 range saturated to :data:`F32_MAX` with its
        sign, so that a finite force stays finite (the device clamps it) and NaN or an
        infinity stays non-finite (the device zeroes the force and latches
        NON_FINITE_FORCE), as with a full FORCE.
    """
    out = []
    for x in force.force:
        if x > F32_MAX or x < -F32_MAX:
            x = math.copysign(F32_MAX, x) if math.isfinite(x) else x
        out.append(_F32.unpack(_F32.pack(x))[0])
    return ForceCompact(force.seq & 0xFFFF, tuple(out))


_F32 = struct.Struct("<f")


class CompactExpander:
    """Restore the :class:`State` a :class:`StateCompact` stands for (host side).

    PROTOCOL.md §4 "Compact frames": ``seq`` is the 32-bit number whose low 16 bits are
    the frame's and that is at or after (mod 2**16) the last armed STATE's (the first armed
    STATE after CONFIG is taken as is: the device restarts its counter at 0 at CONFIG);
    ``force_seq = seq - lag`` when FORCE_APPLIED is set (else 0); the device time is the
    tick's, ``time_us = round(seq * 1e6 / rate_hz)`` since CONFIG; positions are the
    binary32 values, exactly widened.

    Parameters
    ----------
    rate_hz : float
        Tick rate of the session [Hz] (CONFIG.rate_hz), > 0.
    """

    __slots__ = ("rate_hz", "_last")

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = float(rate_hz)
        self._last: int | None = None

    def restart(self, rate_hz: float | None = None) -> None:
        """Forget the last seq: the next armed STATE is the first of a session (at CONFIG).

        Parameters
        ----------
        rate_hz : float, optional
            New tick rate [Hz] (unchanged when None).
        """
        self._last = None
        if rate_hz is not None:
            self.rate_hz = float(rate_hz)

    @property
    def last(self) -> int | None:
        """The last armed STATE's 32-bit seq, the reference of the next expansion; None
        before the first armed STATE of a session. Settable: a reader that expands compact
        STATEs itself (the compiled host loop) hands its reference back here.

        Raises
        ------
        ValueError
            When set to a value outside 0 .. 2**32 - 1 (other than None).
        """
        return self._last

    @last.setter
    def last(self, seq: int | None) -> None:
        if seq is not None:
            seq = int(seq)
            if not 0 <= seq <= 0xFFFFFFFF:
                raise ValueError(f"CompactExpander.last must be a u32 seq or None, got {seq}")
        self._last = seq

    def expand(self, m: StateCompact) -> State:
        """The full STATE of ``m``.

        Parameters
        ----------
        m : StateCompact
            A decoded compact STATE.

        Returns
        -------
        State
            ``seq`` and ``force_seq`` 32-bit (``force_seq`` -1, "names no FORCE", for a
            saturated ``lag`` of :data:`COMPACT_LAG_MAX`: 255 or more ticks, so the FORCE is
            not known), ``time_us`` since CONFIG [us], ``status`` as sent, ``position`` the
            binary32 values [m]. Only an armed STATE moves the seq
            reference (a disarmed one, e.g. before CONFIG, is expanded against it).
        """
        last = self._last
        seq = m.seq if last is None else (last + ((m.seq - last) & 0xFFFF)) & 0xFFFFFFFF
        if m.status & STATUS_ARMED:
            self._last = seq
        if not m.status & STATUS_FORCE_APPLIED:
            fseq = 0
        elif m.lag >= COMPACT_LAG_MAX:
            # "255 or more": the FORCE is not known, and one held that long was zeroed by
            # the watchdog; the STATE names no FORCE (as a protocol without the field)
            fseq = -1
        else:
            fseq = (seq - m.lag) & 0xFFFFFFFF
        return State(seq, int(round(seq * 1e6 / self.rate_hz)), m.status, fseq, m.position)


# --------------------------------------------------------------------------- stream


@dataclass(slots=True)
class DecoderStats:
    """Counters of a :class:`StreamDecoder` (each frame counts in exactly one).

    Attributes
    ----------
    frames_ok : int
        Frames decoded into a message.
    bad_cobs : int
        Frames whose COBS encoding is invalid.
    bad_crc : int
        Frames too short to hold type and CRC, or whose CRC does not match.
    overlong : int
        Frames longer than :data:`MAX_FRAME` (dropped without being decoded).
    unknown_type : int
        Frames with a valid CRC and an unknown message type.
    malformed : int
        Frames with a valid CRC and a body invalid for their type.
    """

    frames_ok: int = 0
    bad_cobs: int = 0
    bad_crc: int = 0
    overlong: int = 0
    unknown_type: int = 0
    malformed: int = 0

    @property
    def bad_frames(self) -> int:
        """Total number of frames dropped [count]."""
        return self.bad_cobs + self.bad_crc + self.overlong + self.unknown_type + self.malformed

    def as_dict(self) -> dict[str, int]:
        """Counters as a plain ``dict`` (for logs and ``--json`` output).

        Returns
        -------
        dict of str to int
            ``frames_ok``, ``bad_cobs``, ``bad_crc``, ``overlong``, ``unknown_type``,
            ``malformed`` [frames] (PROTOCOL.md §8; :attr:`bad_frames` is their sum
            without ``frames_ok``).
        """
        return {"frames_ok": self.frames_ok, "bad_cobs": self.bad_cobs,
                "bad_crc": self.bad_crc, "overlong": self.overlong,
                "unknown_type": self.unknown_type, "malformed": self.malformed}


class StreamDecoder:
    """Stateful decoder of a byte stream into messages; never raises on input bytes.

    Bytes are buffered up to the next 0x00; each delimited frame is decoded, bad frames are
    counted in :attr:`stats` and dropped (never acted on). Consecutive 0x00 bytes (empty
    frames) are idle fill and are ignored. A frame longer than :data:`MAX_FRAME` stops
    being buffered once it reaches ``MAX_FRAME - 1`` bytes and is dropped at its delimiter,
    so the buffer never holds more than one maximum frame. Resynchronisation is automatic:
    the first 0x00 after garbage ends the garbage.

    Parameters
    ----------
    history : int, optional
        Number of raw frames kept in :attr:`last_frames` for diagnostics (default 16).

    Attributes
    ----------
    stats : DecoderStats
        Counters by outcome.
    last_frames : collections.deque of (bytes, str)
        The last ``history`` frames as ``(raw, outcome)``: ``raw`` is the COBS bytes as
        received without the delimiter (an over-long frame truncated to ``MAX_FRAME - 1``
        bytes), ``outcome`` is ``"ok"`` or the name of the counter it fed.
    """

    __slots__ = ("stats", "last_frames", "_buf", "_overflow", "expander")

    def __init__(self, history: int = 16) -> None:
        self.stats = DecoderStats()
        self.last_frames: deque[tuple[bytes, str]] = deque(maxlen=history)
        self._buf = b""
        self._overflow = False
        #: A :class:`CompactExpander`: when set, each STATE_COMPACT is returned as the
        #: :class:`State` it stands for (a host in a compact session); None: as is.
        self.expander: CompactExpander | None = None

    @property
    def buffered(self) -> int:
        """Number of bytes held, waiting for a delimiter [bytes], <= ``MAX_FRAME - 1``."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop the partial frame (e.g. after reopening the port); counters are kept."""
        self._buf = b""
        self._overflow = False

    @property
    def overflow(self) -> bool:
        """Whether the frame being received has passed ``MAX_FRAME - 1`` bytes (it is being
        dropped up to its delimiter; :attr:`buffered` holds none of it)."""
        return self._overflow

    def take_partial(self) -> bytes:
        """Hand over the partial frame held (the bytes after the last delimiter) and hold
        none: for a reader that continues the stream itself (a compiled loop), which gives
        back what it has not completed with :meth:`put_partial`.

        Returns
        -------
        bytes
            At most ``MAX_FRAME - 1`` bytes, no 0x00 (empty when none is held).
        """
        pre, self._buf = self._buf, b""
        return pre

    def put_partial(self, partial: bytes) -> None:
        """Hold ``partial`` as the start of the next frame (the bytes another reader took
        with :meth:`take_partial` and did not complete), replacing what was held.

        Parameters
        ----------
        partial : bytes
            A frame's start: no 0x00, at most ``MAX_FRAME - 1`` bytes.

        Raises
        ------
        ValueError
            ``partial`` holds a delimiter or is longer than a frame.
        """
        partial = bytes(partial)
        delimited = b"\x00" in partial
        if delimited or len(partial) > MAX_FRAME - 1:
            raise ValueError(f"not a partial frame: {len(partial)} bytes"
                             + (", with a delimiter" if delimited else ""))
        self._buf = partial

    def feed(self, chunk: bytes) -> list[Message]:
        """Feed received bytes; return the messages of the frames they complete.

        Parameters
        ----------
        chunk : bytes-like
            Any bytes, any split of the stream.

        Returns
        -------
        list of Message
            Messages in arrival order; empty when no good frame was completed.
        """
        parts = bytes(chunk).split(b"\x00")
        tail = parts.pop()
        out = []
        limit = MAX_FRAME - 1
        for part in parts:
            if self._buf:
                part = self._buf + part
                self._buf = b""
            if self._overflow or len(part) > limit:
                self._overflow = False
                self.stats.overlong += 1
                self.last_frames.append((part[:limit], "overlong"))
                continue
            if not part:
                continue
            try:
                msg = decode_packet(_cobs.decode(part))
            except FrameError as exc:
                reason = exc.reason
            except _cobs.DecodeError:
                reason = "bad_cobs"
            else:
                self.stats.frames_ok += 1
                self.last_frames.append((part, "ok"))
                if self.expander is not None and type(msg) is StateCompact:
                    msg = self.expander.expand(msg)
                out.append(msg)
                continue
            setattr(self.stats, reason, getattr(self.stats, reason) + 1)
            self.last_frames.append((part, reason))
        if tail:
            if not self._overflow:
                buf = self._buf + tail
                if len(buf) > limit:
                    self._overflow = True
                    buf = buf[:limit]
                self._buf = buf
        return out

    def format_last_frames(self) -> str:
        """The last frames as text for a log record (CONVENTIONS §11).

        Returns
        -------
        str
            One line per frame of :attr:`last_frames`, oldest first, ``outcome: hex``
            (``outcome`` ``ok`` or the counter it fed, ``hex`` the COBS bytes as received
            without the delimiter, space-separated); empty when no frame was seen.
        """
        return "\n".join(f"{outcome}: {raw.hex(' ')}" for raw, outcome in self.last_frames)

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
    "MSG_PING", "MSG_PONG", "MSG_FAULT", "MSG_STOP", "MESSAGE_TYPES", "SENSOR_VELOCITY",
    "STATUS_ARMED", "STATUS_WATCHDOG_TRIPPED", "STATUS_FORCE_CLAMPED", "STATUS_FAULT",
    "STATUS_RX_ERROR", "STATUS_OVERRUN", "STATUS_CONFIGURED", "STATUS_FORCE_APPLIED",
    "FAULT_WATCHDOG", "FAULT_BAD_CONFIG", "FAULT_SENSOR", "FAULT_AMPLIFIER",
    "FAULT_NON_FINITE_FORCE", "FAULT_AXES_MISMATCH", "FAULT_RX_ERRORS", "FAULT_OVERRUN",
    "FAULT_VERSION_MISMATCH", "FAULT_NAMES",
    "Hello", "HelloRequest", "Config", "Link", "SensorsRequest", "Sensors", "State", "Force",
    "Velocity", "Ping", "Pong", "Fault", "Stop",
    "Message", "FrameError", "DecoderStats", "StreamDecoder",
    "encode", "encode_packet", "decode_frame", "decode_packet", "crc16",
    "state_frame_bytes", "force_frame_bytes", "velocity_frame_bytes", "LINK_LOAD",
    "link_max_rate",
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


def link_max_rate(baud: int, bits_per_byte: int = 10, n_axes: int = 1,
                  load: float = LINK_LOAD, velocity: bool = False) -> float:
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

    Returns
    -------
    float
        The largest rate [Hz]; ``inf`` for ``baud == 0``.
    """
    if baud <= 0:
        return math.inf
    up = state_frame_bytes(n_axes) + (velocity_frame_bytes(n_axes) if velocity else 0)
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
        Position sensor resolution [m/count] (informational: STATE carries metres).
    force_scale : float
        Actuator resolution [N/unit] (informational: FORCE carries newtons).
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
                Velocity, Ping, Pong, Fault, Stop]

#: Message class by type id.
MESSAGE_TYPES = {cls.TYPE: cls for cls in (Hello, HelloRequest, Config, Link, SensorsRequest,
                                           Sensors, State, Force, Velocity, Ping, Pong, Fault,
                                           Stop)}

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
    except struct.error as exc:
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

    __slots__ = ("stats", "last_frames", "_buf", "_overflow")

    def __init__(self, history: int = 16) -> None:
        self.stats = DecoderStats()
        self.last_frames: deque[tuple[bytes, str]] = deque(maxlen=history)
        self._buf = b""
        self._overflow = False

    @property
    def buffered(self) -> int:
        """Number of bytes held, waiting for a delimiter [bytes], <= ``MAX_FRAME - 1``."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop the partial frame (e.g. after reopening the port); counters are kept."""
        self._buf = b""
        self._overflow = False

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

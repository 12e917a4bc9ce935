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
Neither direction has a start byte, sequence number or checksum: the host decoder takes
5-byte replies that start with ``id`` and decode to a finite angle within
``max_angle_deg``, and otherwise drops one byte and looks again (counted).
"""

from __future__ import annotations

import math
import struct

from hapsim.drivers.base import AlignedDecoder, Driver, MappedDecoder

__all__ = ["HaplyM3", "MAX_TORQUE", "setup_packet", "write_packet", "reply_packet",
           "ReplyDecoder", "CommandDecoder"]

#: The board's torque clamp [N m] (firmware ``MAX_TORQUE``).
MAX_TORQUE = 0.123
CMD_RESET, CMD_SETUP, CMD_WRITE = 0, 1, 2
_F = struct.Struct("<f")

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
                 direction: int = 0, offset_deg: float = 0.0, resolution: float = 4880.0) -> bytes:
    """Set-up command for one motor and one encoder (module notes).

    Parameters
    ----------
    device_id : int, 0..255
    motor_port, encoder_port : int, 1..4
        Board ports.
    direction : {0, 1}
        Rotational direction byte of both.
    offset_deg : float
        Encoder offset [deg].
    resolution : float
        Encoder counts per revolution.

    Returns
    -------
    bytes
    """
    return (bytes([CMD_SETUP, device_id & 0xFF, 1 << (motor_port - 1), direction,
                   1 << (encoder_port - 1), direction, 0, 0])
            + _F.pack(offset_deg) + _F.pack(resolution))


def write_packet(device_id: int, torque: float) -> bytes:
    """Write command ``[2][id][float32 torque]`` (no PWM pin set up)."""
    return bytes([CMD_WRITE, device_id & 0xFF]) + _F.pack(torque)


def reply_packet(device_id: int, angle_deg: float) -> bytes:
    """Reply ``[id][float32 angle deg]`` (one encoder, no analog pin)."""
    return bytes([device_id & 0xFF]) + _F.pack(angle_deg)


class ReplyDecoder(AlignedDecoder):
    """Host side: 5-byte replies ``[id][float32 deg]`` out of a byte stream.

    Parameters
    ----------
    device_id : int
    max_angle_deg : float
        Largest plausible angle [deg]; a reply beyond it (or not finite) is misaligned.

    Attributes
    ----------
    stats : dict
        ``frames`` (replies), ``skipped`` (bytes dropped realigning).
    """

    length = 5

    def __init__(self, device_id: int, max_angle_deg: float = 3600.0) -> None:
        super().__init__()
        self.id = device_id & 0xFF
        self.max = float(max_angle_deg)

    def parse(self, buf):
        """The angle [deg] of a reply at the start of ``buf``, or None."""
        if buf[0] != self.id:
            return None
        a = _F.unpack_from(buf, 1)[0]
        return a if math.isfinite(a) and abs(a) <= self.max else None


class CommandDecoder:
    """Device side (the mock): commands out of the host's bytes, as the firmware parses
    them (a set-up fixes the lengths of later writes and replies).

    Attributes
    ----------
    stats : dict
        ``writes``, ``setups``, ``resets``, ``unknown`` (bytes that are no command).
    motors, encoders : int
        Motors and encoders set up (this board: at most 4 each).
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.motors = 0
        self.encoders = 0
        self.analog = 0
        self.pwms = 0
        self.id = None
        self.resolution = None
        self.stats = {"writes": 0, "setups": 0, "resets": 0, "unknown": 0}

    def _setup_len(self, b) -> int | None:
        """Length of the set-up command at the start of ``b``; None if not all there."""
        if len(b) < 3:
            return None
        nm = bin(b[2] & 0x0F).count("1")
        i = 3 + nm
        if len(b) < i + 1:
            return None
        ne = bin(b[i] & 0x0F).count("1")
        i += 1 + ne
        if len(b) < i + 1:
            return None
        i += 1 + b[i]
        if len(b) < i + 1:
            return None
        i += 1 + b[i]
        return i + 8 * ne

    def feed(self, data: bytes) -> list:
        """Bytes in; ``("write", id, [torques])``, ``("setup", id)``, ``("reset", id)`` out."""
        buf = self._buf
        buf += data
        out = []
        while buf:
            c = buf[0]
            if c == CMD_RESET:
                if len(buf) < 2:
                    break
                out.append(("reset", buf[1]))
                self.stats["resets"] += 1
                self.motors = self.encoders = 0
                del buf[:2]
            elif c == CMD_SETUP:
                n = self._setup_len(buf)
                if n is None or len(buf) < n:
                    break
                self.id = buf[1]
                self.motors = bin(buf[2] & 0x0F).count("1")
                i = 3 + self.motors
                self.encoders = bin(buf[i] & 0x0F).count("1")
                i += 1 + self.encoders
                self.analog = buf[i]
                i += 1 + buf[i]
                self.pwms = buf[i]
                i += 1 + buf[i]
                if self.encoders:          # encoder 1's (offset, counts per revolution)
                    res = _F.unpack_from(buf, i + 4)[0]
                    self.resolution = res if math.isfinite(res) and res > 0 else None
                out.append(("setup", self.id))
                self.stats["setups"] += 1
                del buf[:n]
            elif c == CMD_WRITE:
                mine = len(buf) >= 2 and buf[1] == self.id
                n = 2 + ((self.pwms + 4 * self.motors) if mine else 0)
                if len(buf) < n:
                    break
                tq = [_F.unpack_from(buf, 2 + self.pwms + 4 * k)[0]
                      for k in range(self.motors)] if mine else []
                out.append(("write", buf[1], tq))
                self.stats["writes"] += 1
                del buf[:n]
            else:
                self.stats["unknown"] += 1
                del buf[:1]
        return out


class HaplyM3(Driver):
    """A Haply M3 board joint as a 1-DoF rotary axis (module notes).

    Parameters
    ----------
    device_id : int, 0..255
        The board's device id.
    resolution : float
        Encoder counts per revolution (sent in the set-up).
    """

    name = "haply"
    baud = 115200                     # USB CDC: ignored
    rtscts = False
    native_rate_hz = 1000.0
    force_limit = MAX_TORQUE
    force_scale = 0.0
    limits = LIMITS

    def __init__(self, device_id: int = 1, resolution: float = 4880.0) -> None:
        from hapsim.errors import ConfigError
        if not 0 <= int(device_id) <= 255:
            raise ConfigError(f"device id must be 0..255, got {device_id!r}", key="device_id")
        if not (math.isfinite(resolution) and resolution > 0):
            raise ConfigError(f"counts per revolution must be > 0, got {resolution!r}",
                              key="resolution")
        self.id = int(device_id)
        self.device_id = self.id
        self.resolution = float(resolution)
        self.position_scale = 2 * math.pi / self.resolution

    def arm(self) -> bytes:
        """Set-up (motor 1, encoder 1), then a zero-torque write."""
        return setup_packet(self.id, resolution=self.resolution) + self.encode_force(0.0)

    def encode_force(self, force: float) -> bytes:
        """Write of ``force`` [N m], clamped to the board's 0.123 N m (NaN/inf: 0)."""
        t = float(force) if math.isfinite(force) else 0.0
        return write_packet(self.id, max(-MAX_TORQUE, min(MAX_TORQUE, t)))

    def applied_force(self, force: float) -> float:
        """The torque the board receives [N m]: clamped, rounded to binary32."""
        return _F.unpack(self.encode_force(force)[2:])[0]

    def decoder(self):
        """A fresh host decoder returning the joint angle [rad]."""
        return MappedDecoder(ReplyDecoder(self.id), math.radians)

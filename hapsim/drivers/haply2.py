"""Haply 2DIY: the pantograph's two joints on a Haply board, the bytes of its two generations.

The board's command layout is the 1-DoF driver's (:mod:`hapsim.drivers.haply`: firmware
V1.5's ``setup_device``, ``write_states``, ``read_states``; no framing, no checksum;
IEEE-754 binary32 little-endian); the 2DIY uses two motor ports and two encoder ports, as
Haply's hAPI host library sets it up (``Device.java`` V2.2: ``add_actuator``,
``add_encoder``, ``device_set_parameters``, ``device_write_torques``,
``device_read_data``). Ports are listed in port order, whatever joint each drives:

host -> device ::

    set-up  [1][id][motor mask][motor direction per port][encoder mask]
            [encoder direction per port][0 analog][0 pwm]
            [per encoder port: float32 offset deg, float32 counts per revolution]
    write   [2][id][float32 torque N m of port 1][float32 torque N m of port 2]

device -> host, after each write ::

    [id][float32 angle deg of encoder port 1][float32 angle deg of encoder port 2]

so a write is 10 bytes, a reply 9, a set-up 26. The 2DIY wires joint 1 (hAPI's
actuator/encoder 1) to port 2 and joint 2 to port 1, in both generations; the
generations differ in their encoders and direction bytes (hAPI's examples,
``hardwareVersion`` 2 and 3):

========== =================== ================== ====================
generation motor direction      encoder direction  counts per revolution
           (joint 1, joint 2)   (joint 1, joint 2)
========== =================== ================== ====================
``gen2``   CCW (1), CW (0)      CCW (1), CW (0)    10752
``gen3``   CW (0), CW (0)       CCW (1), CCW (1)   4880
========== =================== ================== ====================

hAPI also sends its own encoder offsets (241 and -61 deg, 180 and 0 deg): the joint angles
of its kinematic convention at the pose the board is set up in. hapsim's pantograph
(:class:`hapsim.kinematics.Pantograph`) has its own convention, so this driver sends as
offsets the joint angles (in hapsim's convention) of the pose the handle is held at when
hapsim arms it (as the 1-DoF driver does with ``offset_deg``): the board's angles are then
hapsim's joints directly. The board (firmware V1.5) clamps each torque to 0.123 N m and has
no watchdog (module notes of :mod:`hapsim.drivers.haply`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from hapsim.drivers.haply import (CMD_SETUP, CMD_WRITE, DEFAULT_ID, F32_MAX, LONGEST_WAIT,
                                  MAX_TORQUE, ReplyDecoder, resync_bytes)
from hapsim.errors import ConfigError
from hapsim.option_values import option_value

__all__ = ["Generation", "GENERATIONS", "Haply2DIY", "Reply2Decoder", "JOINT_PORTS"]

_F = struct.Struct("<f")
_F2 = struct.Struct("<ff")

#: The board port (1..4) of each joint: joint 1 on port 2, joint 2 on port 1 (hAPI's
#: ``add_actuator(1, .., 2)``, ``add_actuator(2, .., 1)``, the same for the encoders).
JOINT_PORTS = (2, 1)


@dataclass(frozen=True)
class Generation:
    """A 2DIY generation's set-up: direction bytes per joint and encoder counts per
    revolution (hAPI's examples; module notes)."""

    name: str
    motor_direction: tuple
    encoder_direction: tuple
    resolution: float


#: The two generations (module notes).
GENERATIONS = {
    "gen2": Generation("gen2", (1, 0), (1, 0), 10752.0),
    "gen3": Generation("gen3", (0, 0), (1, 1), 4880.0),
}

LIMITS = """\
Haply 2DIY protocol limits (hapsim run --driver haply on a 2-D scene):
  against the emulated board only (hapsim.emulated.haply2_board; in real time behind a
    pty, hapsim.pipeline.haply2_host): a real board has no hand to start each record
  real time: no sequence numbers; a reply not read by its tick is an estimated sample
    (counted, bounded in the stated uncertainty); a board that lost its place is
    re-synchronised (zero torque first; counted) and its record is not measured
  no start byte, no checksum: a lost or corrupted byte shifts or alters a reply; the
    decoder realigns on the id and two plausible angles (whole encoder counts), and the
    host re-synchronises a board that lost its place
  angles float32 degrees of whole encoder counts (10752 or 4880 per revolution): a
    quantum of 1.7 or 3.7 mrad at the joint, tens of micrometres at the handle"""


class Reply2Decoder(ReplyDecoder):
    """Host side: 9-byte replies ``[id][float32 deg][float32 deg]`` out of a byte stream:
    :class:`hapsim.drivers.haply.ReplyDecoder` with two encoders (each angle finite,
    within ``max_angle_deg``, a whole number of counts of its port's resolution, within
    ``max_step_deg`` of the linear prediction of the last two replies taken; otherwise one
    byte is dropped; its ``desync_bytes``, 19 (two replies and one byte), dropped in a row
    count one ``desync``, again every 100 bytes).

    Parameters
    ----------
    device_id : int
    resolution : tuple of float or None
        Counts per revolution of encoder ports 1 and 2 (None: no whole-count check).
    max_angle_deg, max_step_deg : float
        As :class:`hapsim.drivers.haply.ReplyDecoder` [deg].

    Attributes
    ----------
    stats : dict
        ``frames``, ``skipped``, ``desync``.
    """

    def __init__(self, device_id: int, resolution=None, max_angle_deg: float = 3600.0,
                 max_step_deg: float = 2.0) -> None:
        super().__init__(device_id, max_angle_deg, resolution, max_step_deg, angles=2)


class Haply2DIY:
    """The host's codec of a Haply 2DIY (module notes).

    Parameters
    ----------
    generation : {"gen2", "gen3"}
        The set-up's direction bytes and encoder resolution.
    device_id : int, 1..255
    resolution : float, optional
        Encoder counts per revolution sent in the set-up (default the generation's).
    motor_direction, encoder_direction : (int, int), optional
        The direction bytes (0 CW, 1 CCW) of joint 1's and joint 2's motor / encoder
        (default the generation's): a joint wired backwards is set up with its byte
        flipped (:func:`hapsim.drivers.haply2_probe.find_directions` says which joint).

    Raises
    ------
    ConfigError
        An unknown generation (the valid ones named), a bad id, resolution or
        direction bytes.

    Attributes
    ----------
    name : str
        ``"haply"``.
    force_limit : float
        The board's torque clamp [N m].
    limits : str
    """

    name = "haply"
    force_limit = MAX_TORQUE
    limits = LIMITS

    def __init__(self, generation: str = "gen3", device_id: int = DEFAULT_ID,
                 resolution: float | None = None, motor_direction=None,
                 encoder_direction=None) -> None:
        if generation not in GENERATIONS:
            raise ConfigError(f"unknown 2DIY generation {generation!r}; valid: "
                              f"{', '.join(GENERATIONS)}", key="generation")
        device_id = option_value("device_id", device_id, low=1, high=255, whole=True)
        g = GENERATIONS[generation]
        res = g.resolution if resolution is None else option_value(
            "resolution", resolution, "counts per revolution", low=0, low_ok=False,
            high=F32_MAX)
        for key, v in (("motor_direction", motor_direction),
                       ("encoder_direction", encoder_direction)):
            if v is not None and (len(tuple(v)) != 2 or set(tuple(v)) - {0, 1}):
                raise ConfigError(f"must be two direction bytes (joint 1, joint 2), each 0 "
                                  f"(CW) or 1 (CCW), got {v!r}", key=key)
        g = Generation(g.name, g.motor_direction if motor_direction is None
                       else tuple(int(b) for b in motor_direction),
                       g.encoder_direction if encoder_direction is None
                       else tuple(int(b) for b in encoder_direction), g.resolution)
        self.generation = g
        self.id = int(device_id)
        self.resolution = _F.unpack(_F.pack(res))[0]      # binary32 on the wire
        self._f32 = np.zeros(1, np.float32)                # clamp1's rounding cell

    def setup_bytes(self, joints_deg) -> bytes:
        """The set-up: both motors and encoders, the encoders' offsets the joints' angles
        ``joints_deg`` (joint 1, joint 2) [deg] at the pose the handle is held at.

        Parameters
        ----------
        joints_deg : sequence of float, length 2
            The joints' angles (joint 1, joint 2) [deg]: the encoders' offsets.

        Returns
        -------
        bytes
            26 bytes (module notes).
        """
        g = self.generation
        by_port = sorted(range(2), key=lambda j: JOINT_PORTS[j])      # joints in port order
        mask = sum(1 << (JOINT_PORTS[j] - 1) for j in range(2))
        out = bytes([CMD_SETUP, self.id, mask]) + bytes(g.motor_direction[j] for j in by_port)
        out += bytes([mask]) + bytes(g.encoder_direction[j] for j in by_port) + bytes((0, 0))
        for j in by_port:
            out += _F.pack(float(joints_deg[j])) + _F.pack(self.resolution)
        return out

    def clamp1(self, t: float) -> float:
        """One torque [N m] as the board takes it: non-finite as 0, clamped to
        ``MAX_TORQUE``, rounded to binary32 (through a reused float32 cell: no
        allocation).

        Parameters
        ----------
        t : float
            The torque [N m].

        Returns
        -------
        float
            [N m]: clamped to +-``MAX_TORQUE`` (0.123 N m), then rounded to binary32.
        """
        t = float(t) if math.isfinite(t) else 0.0
        f32 = self._f32
        f32[0] = max(-MAX_TORQUE, min(MAX_TORQUE, t))
        return f32.item(0)

    def clamp(self, torques) -> tuple:
        """Torques [N m] as the board takes them (:meth:`clamp1` each, joint order).

        Parameters
        ----------
        torques : iterable of float
            Joint torques [N m], joint order.

        Returns
        -------
        tuple of float
            [N m], one per torque given.
        """
        return tuple(self.clamp1(t) for t in torques)

    def write_bytes(self, torques) -> bytes:
        """The write of the joint torques ``(tau_1, tau_2)`` [N m] (clamped, port order):
        10 bytes.

        Parameters
        ----------
        torques : (float, float)
            ``(tau_1, tau_2)``, joint 1's and joint 2's torque [N m].

        Returns
        -------
        bytes
            ``[2][id][float32 port 1's][float32 port 2's]`` (:meth:`write_into`).
        """
        buf = bytearray(10)
        self.write_into(buf, *torques)
        return bytes(buf)

    def write_into(self, buf: bytearray, tau1: float, tau2: float) -> None:
        """:meth:`write_bytes` into ``buf`` (10 bytes, reused: the real-time loop's, no
        allocation per sample).

        Parameters
        ----------
        buf : bytearray, length 10
        tau1, tau2 : float
            Joint torques [N m] (clamped as :meth:`clamp1`).
        """
        buf[0] = CMD_WRITE
        buf[1] = self.id
        _F2.pack_into(buf, 2, self.clamp1(tau2), self.clamp1(tau1))    # port 1 = joint 2

    def arm_bytes(self, joints_deg) -> bytes:
        """Zero torque whatever the board's parser is doing, then the set-up and a
        zero-torque write whose reply is the first sample: a zero write,
        :data:`~hapsim.drivers.haply.LONGEST_WAIT` zero bytes (zero torque inside a write,
        resets elsewhere), two bytes 3 (no command), the set-up, a zero write
        (:func:`hapsim.drivers.haply.resync_bytes`, as the 1-DoF joint's
        :meth:`hapsim.drivers.haply.HaplyM3.resync`). Firmware V1.5's single
        ``SerialUSB.read()`` of an empty buffer gives 255 and only its ``readBytes`` wait
        (at most 32 bytes: ``Haply_M3_Firmware_V1_5.h`` line 188), as the M3's, so 32 zeros
        outlast any wait; 556 (:data:`~hapsim.drivers.haply.LONGEST_COMMAND`, before) were
        278 resets, one a pass of at least 50 us (``.ino`` lines 59-64): 14 ms of board
        time with a garbage torque held before the set-up, and 600 bytes of which 1 lost
        in 200 loses at least one 95 % of the time (80 bytes now: 33 %).

        Parameters
        ----------
        joints_deg : sequence of float, length 2
            The set-up's offsets (joint 1, joint 2) [deg] (:meth:`setup_bytes`).

        Returns
        -------
        bytes
            80 bytes.
        """
        return resync_bytes(self.write_bytes((0.0, 0.0)), self.setup_bytes(joints_deg),
                            zeros=LONGEST_WAIT)

    def decoder(self) -> Reply2Decoder:
        """A fresh reply decoder (whole counts at the set-up's resolution).

        Returns
        -------
        Reply2Decoder
            Its values: ``(port 1, port 2)`` angles [deg] (:meth:`joints_of`).
        """
        return Reply2Decoder(self.id, (self.resolution, self.resolution))

    @staticmethod
    def joints_of(reply) -> tuple:
        """A reply's angles (port 1, port 2) [deg] as the joints (joint 1, joint 2) [rad].

        Parameters
        ----------
        reply : sequence of float, length 2
            A :class:`Reply2Decoder` value: the angles of ports 1 and 2 [deg].

        Returns
        -------
        tuple of float
            ``(q1, q2)`` [rad].
        """
        return (math.radians(reply[1]), math.radians(reply[0]))

"""Novint Falcon: the bytes of its USB link (FTDI serial) with the Novint SDK firmware.

Layout and handshake as libnifalcon publishes them (K. Machulis, BSD licence:
``src/firmware/FalconFirmwareNovintSDK.cpp`` ``formatInput``/``formatOutput``,
``src/core/FalconFirmware.cpp`` ``loadFirmware``, ``src/comm/FalconCommLibUSB.cpp``
``setFirmwareMode``/``setNormalMode``, ``include/falcon/core/FalconFirmware.h`` (LED and
homing flags), ``include/falcon/core/FalconKinematic.h`` ``getTheta`` and
``include/falcon/core/FalconGeometry.h``), described here in our words.

**Packets** (normal mode): 16 bytes both ways, ``'<'`` (0x3C), 14 bytes each carrying one
nibble plus 0x41 (``'A'``..``'P'``), ``'>'`` (0x3E). Host -> device: three int16 motor
commands, each as four nibbles least significant first (bytes 1-4, 5-8, 9-12), byte 13
the LED flags (green 0x2, blue 0x4, red 0x8) OR 0x1 for homing mode, byte 14 zero. Device
-> host: three int16 encoder counts the same way (bytes 1-12), byte 13 the homing status
in bits 4-6 (leg 1, 2, 3 homed) and the grip's buttons in bits 0-3, byte 14 unused. The
device answers each packet it receives with one packet (libnifalcon writes again only
after a reply).

**Units**: a leg's angle is ``theta = ticks * 360 * 0.01425 / (4 * 320 * 0.110) + 35``
degrees (shaft diameter 0.01425 m, 320 slots read in quadrature, the arm's pulley 0.110 m,
35 deg at count 0: 0.0364 deg per count); libnifalcon sends ``command = -10000 tau`` for
a leg torque ``tau`` in its kinematics' units (it does not state them in newton-metres;
:data:`TORQUE_PER_COUNT` keeps its scale, so the commanded torque is known to that
unpublished factor).

**Firmware-load handshake** (the Falcon boots into a loader; the host sends the firmware
each time it is powered): purge, latency timer 16 ms, 9600 baud 8N1, no flow control, RTS
low, DTR low then high (resets the loader); up to 100 times send ``0A 43 0D`` and expect
``0A 44 2C 0D`` back (some hosts see a leading 00); DTR low, baud divisor 0x15; send
``41`` and expect ``41``; then the firmware image in chunks of at most 62 bytes, each
echoed byte for byte (the check); then normal mode: latency 1 ms, baud divisor 0x2, purge.
The line settings are USB control transfers (no bytes on the data stream): the emulator
(:mod:`hapsim.emulated.falcon_device`) takes them as calls.
"""

from __future__ import annotations

import math

from hapsim.drivers.decoders import AlignedDecoder

__all__ = ["LED_GREEN", "LED_BLUE", "LED_RED", "HOMING_MODE", "HOMED", "host_packet",
           "device_packet", "parse_host_packet", "commands_zero", "parse_device_packet", "DevicePacketDecoder",
           "theta_deg", "ticks_of", "DEG_PER_TICK", "THETA_OFFSET_DEG", "TORQUE_PER_COUNT",
           "WORKSPACE_RAD", "ENVELOPE_RAD",
           "CHECK_SEND", "CHECK_REPLY", "LOADER_SEND", "FIRMWARE_CHUNK", "FalconFirmwareLoader",
           "torque_command", "JUMP_PACKETS"]

LED_GREEN, LED_BLUE, LED_RED = 0x2, 0x4, 0x8
#: Byte 13's bit 0 from the host: homing mode (the legs seek their encoder index).
HOMING_MODE = 0x1
#: Homing status of legs 1, 2, 3 (bits of the device's byte 13, shifted down a nibble).
HOMED = (0x1, 0x2, 0x4)
#: Degrees per encoder count (module notes).
DEG_PER_TICK = 360.0 * 0.01425 / (4 * 320 * 0.110)
#: A leg's angle at encoder count 0 [deg].
THETA_OFFSET_DEG = 35.0
#: libnifalcon's torque per motor-command count (``command = -10000 tau``), in its
#: kinematics' torque unit.
TORQUE_PER_COUNT = 1e-4
#: The legs' workspace in a run [rad]: the largest departure of any leg from the scene's
#: operating point a run may reach (the emulated Falcon's truth, ``excursion``, is held
#: to it by tools/driver_timing.py and the tests). The delta of configs/delta_sphere.yaml
#: leaves its kinematics (no forward solution, or a singular Jacobian) 0.9 rad from rest
#: (either leg, sampled): 0.5 rad is inside with a margin of 1.8. Named in
#: :mod:`hapsim.pipeline.falcon_run` and :mod:`hapsim.emulated.falcon_device` too.
WORKSPACE_RAD = 0.5
#: The legs' envelope in a run [rad]: a reading of a leg farther than this from the
#: operating point stops the loop (a stop on the motion: the legs then braked,
#: :func:`hapsim.emulated.falcon_device.brake_legs`). The runs of tools/driver_timing.py
#: moved the legs at most 0.001 rad (10 seeds each way, docs/drivers.md); a fifth of
#: :data:`WORKSPACE_RAD` leaves the braking 0.4 rad, its travel ``v T (d + 1 + 1/g)``
#: about 6 ms of the speed at 1 kHz: up to ~65 rad/s.
ENVELOPE_RAD = WORKSPACE_RAD / 5
#: The loader handshake's first message and its answer (module notes).
CHECK_SEND = bytes((0x0A, 0x43, 0x0D))
CHECK_REPLY = bytes((0x0A, 0x44, 0x2C, 0x0D))
#: The second check: ``'A'`` echoed once the loader runs at the loading baud.
LOADER_SEND = b"A"
#: Firmware bytes per write, each chunk echoed (libnifalcon: 62, a full-speed USB packet
#: less the FTDI's two status bytes).
FIRMWARE_CHUNK = 62

_LT, _GT, _A = 0x3C, 0x3E, 0x41


def _nibbles(values) -> list:
    out = []
    for v in values:
        u = int(v) & 0xFFFF
        out += [u & 0xF, (u >> 4) & 0xF, (u >> 8) & 0xF, (u >> 12) & 0xF]
    return out


def _int16(nibs) -> int:
    u = nibs[0] | nibs[1] << 4 | nibs[2] << 8 | nibs[3] << 12
    return u - 0x10000 if u & 0x8000 else u


def host_packet(commands, leds: int = 0, homing: bool = False) -> bytes:
    """Host -> device packet of three motor commands (module notes).

    Parameters
    ----------
    commands : sequence of 3 int
        Motor commands, clamped to int16 (-32768..32767).
    leds : int
        LED flags (:data:`LED_GREEN`, :data:`LED_BLUE`, :data:`LED_RED`).
    homing : bool
        Homing mode (:data:`HOMING_MODE`).

    Returns
    -------
    bytes
        16 bytes.
    """
    c = [max(-32768, min(32767, int(v))) for v in commands]
    body = _nibbles(c) + [((leds & 0x0E) | (HOMING_MODE if homing else 0)) & 0xF, 0]
    return bytes([_LT] + [b + _A for b in body] + [_GT])


def device_packet(encoders, homed: int = 0, grip: int = 0) -> bytes:
    """Device -> host packet (the emulator's reply): three int16 encoder counts, the
    homing status (bits 0-2 for legs 1-3) and the grip's buttons (4 bits).

    Parameters
    ----------
    encoders : sequence of int, length 3
        The legs' counts (clamped to int16).
    homed : int
        Homing status bits (0-2).
    grip : int
        The grip's buttons (4 bits).

    Returns
    -------
    bytes
        16 bytes: ``<``, twelve count nibbles, byte 13, a nibble, ``>``.
    """
    e = [max(-32768, min(32767, int(v))) for v in encoders]
    b13 = ((homed & 0x7) << 4) | (grip & 0xF)
    body = _nibbles(e)
    return bytes([_LT] + [b + _A for b in body] + [b13 + _A, _A, _GT])


def _body_ok(p, last: int) -> bool:
    return (len(p) == 16 and p[0] == _LT and p[15] == _GT
            and all(_A <= b <= _A + 15 for b in p[1:last]))


def commands_zero(p: bytes) -> bool:
    """Whether host packet ``p`` (:func:`host_packet`) commands zero on every motor: its
    twelve command nibbles all ``'A'`` (an int16 zero is four zero nibbles), read in
    place, nothing decoded or allocated (the host's watchdog asks it of every packet of
    a real-time loop).

    Parameters
    ----------
    p : bytes
        16 bytes.

    Returns
    -------
    bool
    """
    return p.count(_A, 1, 13) == 12


def parse_host_packet(p: bytes):
    """The device's reading of a host packet: ``(commands, leds, homing)``, or None when
    it is not one (delimiters, nibble bytes out of ``'A'..'P'``).

    Parameters
    ----------
    p : bytes
        16 bytes.

    Returns
    -------
    tuple or None
        ``(commands, leds, homing)``: the three int16 motor commands, the LED bits, the
        homing-mode flag.
    """
    if not _body_ok(p, 15):
        return None
    nib = [b - _A for b in p[1:15]]
    cmds = tuple(_int16(nib[4 * i:4 * i + 4]) for i in range(3))
    return cmds, nib[12] & 0x0E, bool(nib[12] & HOMING_MODE)


def parse_device_packet(p: bytes):
    """The host's reading of a device packet: ``(encoders, homed, grip)``, or None.

    Byte 13 carries two fields (homing status in bits 4-6, grip in bits 0-3): it may take
    any value from 0x41; the twelve encoder bytes and byte 14 are nibbles.

    Parameters
    ----------
    p : bytes
        16 bytes.

    Returns
    -------
    tuple or None
        ``(encoders, homed, grip)``: the three int16 counts, the homing bits, the grip's
        buttons; None when ``p`` is no device packet.
    """
    if not (len(p) == 16 and p[0] == _LT and p[15] == _GT
            and all(_A <= b <= _A + 15 for b in p[1:13]) and _A <= p[14] <= _A + 15
            and _A <= p[13] <= _A + 0x7F):
        return None
    nib = [b - _A for b in p[1:13]]
    enc = tuple(_int16(nib[4 * i:4 * i + 4]) for i in range(3))
    b13 = p[13] - _A
    return enc, (b13 >> 4) & 0x7, b13 & 0x0F


class DevicePacketDecoder(AlignedDecoder):
    """Device packets out of a byte stream: realigned on ``'<'`` ... ``'>'`` with valid
    nibbles (one byte dropped per failed position; counted in ``skipped``), and checked
    for plausibility, since the packet has no checksum (a flipped bit that keeps a byte in
    ``'A'..'P'`` is another count) and no sequence number (a lost packet is not seen):
    the second packet after a start within :data:`START_STEP` of the first, then each count's
    step from the last at most ``max_step`` counts plus twice the last step (8 counts, 0.3 deg: a lost packet at constant
    velocity passes, a flipped high nibble of a leg at rest does not; the faster the legs
    move, the larger a flip that passes). A well-formed packet beyond it is dropped whole
    (``implausible``); :data:`JUMP_PACKETS` of them in a row are a real jump (the device
    reset, say) and the last is taken (counted too), the prediction restarted. A change of
    the homing status is taken the same way (implausible until it stays
    :data:`JUMP_PACKETS` packets: a flipped status bit would otherwise restart the
    prediction and let the next packets in unchecked), and restarts the prediction.

    Parameters
    ----------
    max_step : int
        Counts [-].

    Attributes
    ----------
    stats : dict
        ``frames``, ``skipped``, ``implausible``.
    """

    length = 16

    def __init__(self, max_step: int = 8) -> None:
        super().__init__()
        self.max_step = int(max_step)
        self._prev = self._prev2 = None
        self._homed = None
        self._off = 0
        self.stats["implausible"] = 0

    def parse(self, buf):
        """``(encoders, homed, grip)`` of a packet at the start of ``buf``, or None.

        Parameters
        ----------
        buf : bytearray
            At least :attr:`length` (16) bytes.

        Returns
        -------
        tuple or None
            As :func:`parse_device_packet`: three int16 counts, the homing bits, the grip's
            buttons.
        """
        return parse_device_packet(bytes(buf[:16]))

    def _plausible(self, enc, homed) -> bool:
        if self._prev is None:
            return True                     # nothing to compare with
        if homed != self._homed:
            # a leg does not lose its index: a changed status is a flipped bit until it
            # stays JUMP_PACKETS packets (homing itself seen that much later)
            return False
        if self._prev2 is None:             # the velocity not known yet: near the last
            return all(abs(enc[i] - self._prev[i]) <= START_STEP for i in range(3))
        # a step at most twice the last one (a packet lost on the way, and the last step
        # itself may span a lost one) plus max_step
        return all(abs(enc[i] - self._prev[i])
                   <= self.max_step + 2 * abs(self._prev[i] - self._prev2[i])
                   for i in range(3))

    def accept(self, value) -> bool:
        """A packet taken unless implausible (counted): :data:`JUMP_PACKETS` implausible
        ones in a row are a real jump of the counts, taken as the new start.

        Parameters
        ----------
        value : tuple
            ``(encoders, homed, grip)`` of :meth:`parse`.

        Returns
        -------
        bool
            Whether the packet is taken.
        """
        enc, homed, _ = value
        if not self._plausible(enc, homed):
            self.stats["implausible"] += 1
            self._off += 1
            if self._off < JUMP_PACKETS:
                return False
            self._prev = None               # a real jump: start again from it
        self._off = 0
        if homed != self._homed:
            self._prev = None
        self._homed = homed
        self._prev2, self._prev = (None, enc) if self._prev is None else (self._prev, enc)
        return True


#: The largest step [counts] between the first two packets after a start, when the
#: velocity is not known yet: 64 counts (2.3 deg) in one ~1 ms packet is ~40 rad/s at a
#: leg, beyond a hand's motion; a flipped bit of a count's two high nibbles is caught.
START_STEP = 64

#: Implausible packets in a row taken as a real jump of the counts.
JUMP_PACKETS = 3


def theta_deg(ticks: int) -> float:
    """A leg's angle [deg] at encoder count ``ticks`` (libnifalcon ``getTheta``).

    Parameters
    ----------
    ticks : int
        The leg's encoder count.

    Returns
    -------
    float
        ``DEG_PER_TICK * ticks + THETA_OFFSET_DEG`` [deg].
    """
    return DEG_PER_TICK * ticks + THETA_OFFSET_DEG


def ticks_of(theta: float) -> int:
    """The encoder count of a leg at ``theta`` [deg] (nearest; the inverse of
    :func:`theta_deg`).

    Parameters
    ----------
    theta : float
        The leg's angle [deg].

    Returns
    -------
    int
    """
    return int(round((theta - THETA_OFFSET_DEG) / DEG_PER_TICK))


class FalconFirmwareLoader:
    """The host's side of the firmware-load handshake as a sequence of steps.

    Each step is ``("line", settings)`` (USB control transfers: baud divisor, latency,
    DTR/RTS, purge) or ``("send", bytes, expect)`` (bytes written, the answer required).

    Parameters
    ----------
    image : bytes
        The firmware image (the Novint SDK's, which hapsim does not ship).
    check_tries : int
        Attempts of the first check (libnifalcon: 100).
    """

    def __init__(self, image: bytes, check_tries: int = 100) -> None:
        self.image = bytes(image)
        self.check_tries = int(check_tries)

    def steps(self):
        """The handshake in order (module notes); the image in echoed chunks."""
        yield ("line", {"purge": True, "latency_ms": 16, "baud": 9600, "bits": "8N1",
                        "flow": None, "rts": 0, "dtr": 0})
        yield ("line", {"dtr": 1})
        yield ("check", CHECK_SEND, CHECK_REPLY, self.check_tries)
        yield ("line", {"dtr": 0, "baud_divisor": 0x15})
        yield ("send", LOADER_SEND, LOADER_SEND)
        for i in range(0, len(self.image), FIRMWARE_CHUNK):
            chunk = self.image[i:i + FIRMWARE_CHUNK]
            yield ("send", chunk, chunk)
        yield ("line", {"latency_ms": 1, "baud_divisor": 0x2, "purge": True})


def torque_command(tau: float) -> int:
    """libnifalcon's motor command of a leg torque ``tau`` (its unit):
    ``-tau / TORQUE_PER_COUNT`` rounded, clamped to int16 (non-finite: 0).

    Parameters
    ----------
    tau : float
        The leg's torque, in libnifalcon's unit.

    Returns
    -------
    int
        The command, in -32768..32767.
    """
    if not math.isfinite(tau):
        return 0
    return max(-32768, min(32767, int(round(-tau / TORQUE_PER_COUNT))))

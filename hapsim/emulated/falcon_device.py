"""The Novint Falcon emulated byte for byte: its loader's handshake, the firmware's packet
loop, homing, LEDs, and the delta's joint-space dynamics as the plant.

States (:class:`FalconDevice`), from the handshake libnifalcon performs
(:mod:`hapsim.drivers.falcon`):

``loader``
    After power-up or a DTR low-to-high edge: answers ``0A 43 0D`` with ``0A 44 2C 0D``
    while the line runs at 9600 baud; other bytes are ignored.
``loader-fast``
    DTR low and the loading baud (divisor 0x15) set: answers ``'A'`` with ``'A'``, then
    takes the firmware image, echoing every byte.
``running``
    Normal mode (divisor 0x2) after an image was loaded (the expected image, when one is
    given): the firmware's packet loop. Each 16-byte host packet (realigned on ``'<'`` and
    ``'>'`` with valid nibbles; a bad one dropped and counted) sets the three motor
    commands (held until the next: no watchdog is modelled, libnifalcon publishes none), the
    LEDs and the homing mode, advances the plant one period with the commands ``d``
    packets back, and is answered by one packet: the encoder counts, the homing status and
    the grip's buttons.

Encoders: before a leg is homed its count is relative to where it was at power-up (the
quadrature counter starts at 0); homing mode held for ``homing_packets`` packets homes
all three legs (they found their index), after which a count is absolute,
``ticks_of(theta)`` with ``theta`` the leg's angle in libnifalcon's convention (35 deg at
count 0), which is hapsim's delta joint angle (:class:`hapsim.kinematics.Delta`). The
plant's leg torque is ``-command * newton_metres_per_count`` (libnifalcon's
``command = -10000 tau``; the emulator takes its unit as N m, an assumption: the scale
is not published in newton-metres).

Its time (``clock="wall"``, the default): the Falcon's firmware runs its own loop at
about 1 kHz, which sets the pace of libnifalcon's exchange (one packet written, its reply
read, the next written: ``FalconComm`` and ``FalconFirmwareNovintSDK::runIOLoop`` wait
for the reply); the firmware is Novint's binary, not published, so what the emulator
takes from it is only that pace: a packet is taken at the firmware's next tick of the
scene's period on the device's own clock (``time.monotonic`` in this process, or the
time a caller gives), its commands set then (plus the scene's delay beyond one period)
and held until the next (no watchdog is published), the encoders read at that tick and
the reply ready then (:attr:`FalconDevice.ready_at`, which
:class:`hapsim.emulated.ftdi_usb.VirtualFT232R` honours). Between ticks the delta's legs
are integrated over the real time that passed
(:meth:`hapsim.joint_device.LocalJointDeviceND.advance_torque`). ``clock="lockstep"``
(named, for deterministic tests): each packet is one period, the reply at once.

The host's loop over it (:func:`drive_falcon`, the driver's, here beside the device it
was first written against) stops on the legs' motion (a leg beyond :data:`ENVELOPE_RAD`,
or a paced host too late) and then brakes the legs to rest (:func:`brake_legs`,
:mod:`hapsim.braking`) before the caller's zero commands.
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from hapsim.drivers.falcon import (CHECK_REPLY, CHECK_SEND, ENVELOPE_RAD, TORQUE_PER_COUNT,
                                   WORKSPACE_RAD, device_packet, parse_host_packet,
                                   ticks_of)
from hapsim.drivers.falcon_usb import ft232r_baud
from hapsim.errors import ConfigError, DeviceError, KinematicsError, error_record
from hapsim.joint_device import LocalJointDeviceND

__all__ = ["FalconDevice", "load_firmware", "home", "drive_falcon", "brake_legs",
           "EmulatorLink", "LOADER_BAUD", "LOADING_BAUD", "NORMAL_BAUD", "WORKSPACE_RAD",
           "ENVELOPE_RAD"]

#: The UART rates the emulated MCU listens at [baud]: its loader (9600), the loading rate
#: (FT232R divisor 0x15: 3 MHz / 21) and the firmware's (divisor 0x2: 1.5 Mbaud); a rate
#: within 3 % of one is that one (a UART's tolerance), another is not heard.
LOADER_BAUD, LOADING_BAUD, NORMAL_BAUD = 9600.0, 3e6 / 21, 1.5e6




def _near(baud, want: float) -> bool:
    return baud is not None and abs(baud - want) <= 0.03 * want


class FalconDevice:
    """An emulated Falcon (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D scene whose device is a delta (the plant, at its operating point).
    expected_image : bytes, optional
        The firmware the device accepts (None: any non-empty image).
    homing_packets : int
        Packets in homing mode until the legs are homed.
    power_up_joints_deg : sequence of 3 float, optional
        Where the legs were at power-up [deg] (the unhomed counts' zero; default the
        operating point).
    newton_metres_per_count : float
        Leg torque per motor-command count [N m].
    clock : {"wall", "lockstep"}
        The device's clock (module notes).
    encoder_offset : sequence of 3 float, optional
        Where each leg's encoder index sits off its nominal angle, in counts (a real
        encoder's zero is at an unknown fraction of a count): a homed count is
        ``ticks_of`` of the angle moved by it, so the host's reading is off by a
        constant and its counts' edges fall elsewhere along the motion (default 0:
        libnifalcon's nominal zero). The tests of the wire's rounding term draw it
        (:mod:`hapsim.analysis.wire_rounding`).

    Raises
    ------
    ConfigError
        Not a 3-D delta scene, a sub-sample delay, an unknown clock, an encoder offset
        not 3 finite numbers.

    Attributes
    ----------
    state : str
        ``"off"``, ``"loader"``, ``"loader-fast"``, ``"running"``.
    leds : int
        LED flags of the last packet.
    homed : int
        Homing status bits.
    stats : dict
        ``packets``, ``bad_bytes`` (dropped realigning), ``loaded`` (image bytes).
    ready_at : float
        Wall clock: the device's time [s] its last reply is ready at.
    excursion : float
        The largest leg displacement from the operating point [rad] (the truth).
    longest_hold_s : float
        Wall clock: the longest time [s] a non-zero command was held until the next
        packet took effect.
    """

    def __init__(self, scene, *, expected_image: bytes | None = None,
                 homing_packets: int = 20, power_up_joints_deg=None,
                 newton_metres_per_count: float = TORQUE_PER_COUNT,
                 clock: str = "wall", encoder_offset=(0.0, 0.0, 0.0)) -> None:
        if clock not in ("wall", "lockstep"):
            raise ConfigError(f"unknown clock {clock!r}; valid: wall, lockstep", key="clock")
        off = np.asarray(encoder_offset, float)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise ConfigError(f"the encoder offset must be 3 finite counts, got "
                              f"{encoder_offset!r}", key="encoder_offset")
        #: Each leg's encoder index off its nominal angle [counts] (``encoder_offset``).
        self.encoder_offset = off
        self.clock = clock
        #: The device itself on the wall clock, None in lockstep.
        self.wall = self if clock == "wall" else None
        self.tick_s = float(scene.period)
        self.ready_at = 0.0
        self.excursion = 0.0
        self._t0 = time.monotonic()
        self._t = 0.0                         # the device's time the plant has reached [s]
        self._k = -1                          # the last tick that took a packet
        self._due: deque = deque()            # (time [s], commands) not yet in effect
        self._took = None                     # when the commands in effect took it [s]
        #: Wall clock: the longest time [s] a non-zero command was held with no packet
        #: after it (the firmware holds each one: no watchdog published).
        self.longest_hold_s = 0.0
        dev = scene.device
        if scene.dimension != 3 or dev is None or dev.kind != "delta":
            raise ConfigError("the Falcon drives a 3-D scene with a delta device",
                              file=scene.path, key="device.kind")
        self.scene = scene
        self.expected = None if expected_image is None else bytes(expected_image)
        self.homing_packets = int(homing_packets)
        self.nm_per_count = float(newton_metres_per_count)
        self.plant = LocalJointDeviceND(scene, np.zeros(3), np.zeros(3))
        pu = (np.degrees(dev.joints) if power_up_joints_deg is None
              else np.asarray(power_up_joints_deg, float))
        self._power_up = [ticks_of(v) for v in pu]
        if float(dev.delay) % 1.0:
            # its joint-space plant applies whole periods (no split hold there)
            raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is not "
                              "emulated by this board (its joint-space model applies whole "
                              "periods): use a whole delay", file=scene.path,
                              key="device.delay")
        self.delay = int(dev.delay)
        #: Wall clock: what brings the firmware's own delay of one period to the scene's
        #: [s] (never negative).
        self.extra_latency_s = max(0.0, self.delay - 1.0) * self.tick_s
        self._fifo = deque([(0, 0, 0)] * self.delay)
        self.commands = (0, 0, 0)
        self.state = "off"
        self.dtr = 0
        self.baud = None
        self.divisor = None
        self.leds = 0
        self.homed = 0
        self._homing_count = 0
        self._image = bytearray()
        self._buf = bytearray()
        self.stats = {"packets": 0, "bad_bytes": 0, "loaded": 0}

    # ------------------------------------------------------------------ line settings
    def line(self, **settings) -> None:
        """USB control transfers: ``dtr``, ``rts``, ``baud``, ``baud_divisor``,
        ``latency_ms``, ``purge``, ``bits``, ``flow`` (module notes for their effects).

        Parameters
        ----------
        **settings
            ``dtr`` (0 or 1: a rising edge resets the MCU into its loader), ``baud``
            [baud], ``baud_divisor`` (the FT232R's register: :func:`ft232r_baud`),
            ``purge`` (bool: the bytes held dropped); ``rts``, ``latency_ms``, ``bits``,
            ``flow`` and any other are ignored.
        """
        if settings.get("purge"):
            self._buf.clear()
        if "baud" in settings:
            self.baud, self.divisor = settings["baud"], None
        if "baud_divisor" in settings:                 # the FT232R's divisor register
            self.divisor = settings["baud_divisor"]
            self.baud = ft232r_baud(self.divisor)
        if "dtr" in settings:
            new = int(settings["dtr"])
            if self.dtr == 0 and new == 1:          # the MCU resets into its loader
                self.state = "loader"
                self._image.clear()
                self.homed = 0
                self._homing_count = 0
                self.commands = (0, 0, 0)
                self._due.clear()
            self.dtr = new
        if self.state == "loader" and self.dtr == 0 and _near(self.baud, LOADING_BAUD):
            self.state = "loader-fast"
            self._a_seen = False
        if self.state == "loader-fast" and _near(self.baud, NORMAL_BAUD):
            ok = len(self._image) > 0 and (self.expected is None
                                           or bytes(self._image) == self.expected)
            self.state = "running" if ok else "loader"
            self._buf.clear()

    # ------------------------------------------------------------------ bytes
    def _counts(self) -> tuple:
        from hapsim.drivers.falcon import DEG_PER_TICK      # (the count a test sets)
        q = np.degrees(self.plant.joints()) + self.encoder_offset * DEG_PER_TICK
        out = []
        for i in range(3):
            t = ticks_of(q[i])
            out.append(t if self.homed >> i & 1 else t - self._power_up[i])
        return tuple(out)

    def now(self) -> float:
        """The device's own clock [s]: ``time.monotonic`` since it was made.

        Returns
        -------
        float
            [s], >= 0.
        """
        return time.monotonic() - self._t0

    def run_to(self, t: float) -> None:
        """Wall clock: the legs integrated to the device's time ``t`` [s], the commands in
        effect held, each packet's taking effect at its time.

        Parameters
        ----------
        t : float
            The device's time to run to [s] (:meth:`now`'s clock); nothing is integrated
            when the legs are there already.
        """
        while self._t < t:
            nxt = t
            if self._due and self._due[0][0] < nxt:
                nxt = max(self._due[0][0], self._t)
            tau = np.array([-c * self.nm_per_count for c in self.commands], float)
            self.plant.advance_torque(tau, nxt - self._t)
            self._t = nxt
            self._take_due()
        self._take_due()
        self.excursion = max(self.excursion,
                             float(np.abs(self.plant.joints() - self.plant.q0).max()))

    def _take_due(self) -> None:
        """The packets whose time has come take effect, each timed against the one
        before (:attr:`longest_hold_s`)."""
        while self._due and self._due[0][0] <= self._t:
            t, cmds = self._due.popleft()
            if any(self.commands) and self._took is not None:
                self.longest_hold_s = max(self.longest_hold_s, t - self._took)
            self._took = t
            self.commands = cmds

    def feed(self, data: bytes, now: float | None = None) -> bytes:
        """Bytes from the host in, the device's bytes out (module notes).

        Parameters
        ----------
        data : bytes
        now : float, optional
            The device's time the bytes came at [s] (wall clock; default :meth:`now`).

        Returns
        -------
        bytes
            The answer; on the wall clock the packets' replies are ready at
            :attr:`ready_at`.
        """
        if self.wall is not None and now is None:
            now = self.now()
        if self.state == "loader":
            if _near(self.baud, LOADER_BAUD) and CHECK_SEND in bytes(data):
                return CHECK_REPLY
            return b""
        if self.state == "loader-fast":
            out = bytearray()
            for b in data:
                if not self._a_seen:
                    if b == 0x41:
                        self._a_seen = True
                        out.append(b)
                    continue
                self._image.append(b)
                self.stats["loaded"] += 1
                out.append(b)
            return bytes(out)
        if self.state != "running":
            return b""
        buf = self._buf
        buf += data
        out = bytearray()
        while len(buf) >= 16:
            pk = parse_host_packet(bytes(buf[:16]))
            if pk is None:
                del buf[:1]
                self.stats["bad_bytes"] += 1
                continue
            del buf[:16]
            out += self._packet(*pk, now=now)
        return bytes(out)

    def _packet(self, commands, leds, homing, now=None) -> bytes:
        self.stats["packets"] += 1
        self.leds = leds
        if homing and self.homed != 0x7:
            self._homing_count += 1
            if self._homing_count >= self.homing_packets:
                self.homed = 0x7
        if self.wall is not None:
            # the firmware's next tick on its own clock: the legs run to it, the packet's
            # commands are set there, the encoders read there, the reply ready then
            self._k = max(math.floor(now / self.tick_s) + 1, self._k + 1)
            t = self._k * self.tick_s
            self.run_to(t)
            self._due.append((t + self.extra_latency_s, tuple(commands)))
            self.run_to(t)
            self.ready_at = t
            return device_packet(self._counts(), self.homed, 0)
        self._fifo.append(tuple(commands))
        due = self._fifo.popleft()
        self.commands = due
        tau = np.array([-c * self.nm_per_count for c in due], float)
        self.plant.step_torque(tau)
        return device_packet(self._counts(), self.homed, 0)

    def let_go(self, x0, v0) -> None:
        """The hand's start of an identification record: the handle put at ``x0`` from the
        operating point, moving at ``v0``, and let go (the legs by Newton steps on the
        plant's kinematics, :class:`hapsim.joint_device.LocalJointDeviceND`); the commands
        held and those not yet in effect are zero, as after the homing's zero packets.

        Parameters
        ----------
        x0, v0 : array_like, shape (3,)
            The handle's displacement [m] and velocity [m/s]
            (:func:`hapsim.lockstep.excitation_starts`).

        On the wall clock the hand lets go now: the legs run to the device's time first
        (:meth:`run_to`), so the next packet's tick integrates the start from this instant,
        not from the last packet's tick.
        """
        if self.wall is not None:
            self.run_to(self.now())
        self.plant = LocalJointDeviceND(self.scene, x0, v0)
        self.commands = (0, 0, 0)
        self._fifo = deque([(0, 0, 0)] * self.delay)
        self._due.clear()

    def counts(self) -> tuple:
        """The three encoder counts the device reports now (relative to the power-up
        pose until homed): the truth a host's readings are compared with in the tests.

        Returns
        -------
        tuple of int
            The three legs' counts, leg order.
        """
        return self._counts()

    def joints_deg(self) -> np.ndarray:
        """The legs' true angles [deg] (tests).

        Returns
        -------
        ndarray, shape (3,)
            [deg], leg order (libnifalcon's convention; no encoder offset).
        """
        return np.degrees(self.plant.joints())


class EmulatorLink:
    """A :class:`FalconDevice` (or anything with ``line`` and ``feed``) as a link of
    :func:`hapsim.drivers.falcon_usb.load_firmware_link`: ``exchange`` feeds the bytes and
    returns the whole answer (no USB in between; :mod:`hapsim.emulated.ftdi_usb` puts the
    real pyftdi path there).

    Parameters
    ----------
    device : object
        ``line(**settings)``, ``feed(bytes) -> bytes``.
    """

    def __init__(self, device) -> None:
        self.device = device

    def line(self, **settings) -> None:
        """The settings passed on.

        Parameters
        ----------
        **settings
            As the device's ``line`` (:meth:`FalconDevice.line`).
        """
        self.device.line(**settings)

    def exchange(self, send: bytes, n: int, done=None, timeout=None) -> bytes:
        """The device's answer to ``send`` (all of it, whatever ``n``).

        Parameters
        ----------
        send : bytes
            What the host writes.
        n, done, timeout
            Ignored (the :class:`hapsim.drivers.falcon_usb.FalconUSB`-like signature).

        Returns
        -------
        bytes
            The device's ``feed(send)``.
        """
        return self.device.feed(send)


def load_firmware(device, image: bytes, check_tries: int = 100) -> dict:
    """Run the host's firmware-load handshake against a device with ``line(**settings)``
    and ``feed(bytes) -> bytes`` (:class:`FalconDevice`) directly, without USB
    (:func:`hapsim.drivers.falcon_usb.load_firmware_link` over :class:`EmulatorLink`).

    Parameters
    ----------
    device : object
    image : bytes
        The firmware image.
    check_tries : int
        Attempts of the first check.

    Returns
    -------
    dict
        ``checks`` (attempts of the first check), ``chunks`` (image chunks echoed),
        ``bytes`` (image bytes echoed).

    Raises
    ------
    hapsim.errors.DeviceError
        The first check never answered, ``'A'`` not echoed, or a chunk's echo short or
        differing (naming the image byte).
    """
    from hapsim.drivers.falcon_usb import load_firmware_link
    return load_firmware_link(EmulatorLink(device), image, check_tries)


def home(device_feed, leds: int = 0, limit: int = 10000, decoder=None) -> int:
    """Send homing-mode packets (zero commands) until every leg reports homed.

    Parameters
    ----------
    device_feed : callable
        ``bytes -> bytes``.
    leds : int
        LED flags to show meanwhile.
    limit : int
        Most packets.
    decoder : hapsim.drivers.falcon.DevicePacketDecoder, optional
        The decoder to read the replies with (the loop's, so that it starts with the
        legs' last counts and step); default a new one.

    Returns
    -------
    int
        Packets sent.

    Raises
    ------
    hapsim.errors.DeviceError
        Not homed after ``limit`` packets.
    """
    from hapsim.drivers.falcon import DevicePacketDecoder, host_packet
    from hapsim.errors import DeviceError
    dec = DevicePacketDecoder() if decoder is None else decoder
    for k in range(1, limit + 1):
        got = dec.feed(device_feed(host_packet((0, 0, 0), leds, homing=True)))
        if got and got[-1][1] == 0x7:
            return k
    raise DeviceError(f"the Falcon's legs were not homed after {limit} packets")


def brake_legs(send, scene, q_last, t_last: float, *,
               hold_bound_s: float | None = None) -> dict:
    """Brake the Falcon's legs to rest after a stop on the motion (:mod:`hapsim.braking`):
    each packet's commands the torques ``tau = -B q'``, ``B = g M_q / T`` from the scene's
    joint inertia, ``q'`` the backward difference of the legs' last two readings, clamped
    to the commands' range (int16 counts, :func:`hapsim.drivers.falcon.torque_command`),
    until three speeds in a row are below the rest speed
    (:func:`hapsim.braking.brake_rest` over :data:`WORKSPACE_RAD`) or
    :data:`hapsim.braking.BRAKE_MAX_S`; the caller then sends zero commands.

    Parameters
    ----------
    send : callable
        ``(3,) int commands -> decoded replies`` (a list of ``(counts, homed, buttons)``,
        :class:`hapsim.drivers.falcon.DevicePacketDecoder`'s).
    scene : hapsim.scene.SceneND
        The 3-D delta scene (its rate, joint inertia and friction, operating point).
    q_last : ndarray, shape (3,), or None
        The legs' last reading [rad] (the first difference's start).
    t_last : float
        Its time (``time.perf_counter``) [s].
    hold_bound_s : float, optional
        A Falcon on its own clock (paced): the readings' times are the host's clock and
        the braking's length its seconds; a torque from a reading older than this is
        sent as zero (the firmware holds each command, no watchdog published). None
        (the emulator in lockstep): one period a packet.

    Returns
    -------
    dict
        :meth:`hapsim.braking.Brake.report`'s: ``damping`` [N m s/rad], ``periods``
        (packets), ``seconds``, ``v_start``/``v_end`` (the legs' velocities [rad/s]),
        ``ended`` (``"rest"`` or ``"time"``), ``late`` (paced: gaps of more than two
        periods between its packets, as the loop counts its stalls).

    Raises
    ------
    hapsim.errors.DeviceError
        From ``send``: the link failed.
    """
    from hapsim.braking import BRAKE_MAX_S, Brake, brake_damping, brake_rest
    from hapsim.drivers.falcon import theta_deg, torque_command
    dev = scene.device
    T = scene.period
    paced = hold_bound_s is not None
    law = Brake(brake_damping(dev.joint_inertia, scene.rate_hz), 32767 * TORQUE_PER_COUNT,
                brake_rest(WORKSPACE_RAD, dev.joint_inertia, dev.joint_friction))
    if q_last is not None:
        law.observe(q_last, None)
    t0 = time.perf_counter()
    t_prev, k_prev = t_last, 0
    periods, ended, late = 0, "time", 0
    t_sent = t0
    while (time.perf_counter() - t0 if paced else periods * T) < BRAKE_MAX_S:
        now = time.perf_counter()
        if paced and now - t_sent > 2.0 * T:
            late += 1                           # a gap the firmware held a command over
        t_sent = now
        tau = law.command()
        if paced and time.perf_counter() - t_prev > hold_bound_s:
            tau = np.zeros(3)                   # no fresh reading: not held on one
        got = send(tuple(torque_command(t) for t in tau))
        periods += 1
        if got and got[-1][1] == 0x7:
            now = time.perf_counter()
            law.observe(np.radians([theta_deg(e) for e in got[-1][0]]),
                        now - t_prev if paced else (periods - k_prev) * T)
            t_prev, k_prev = now, periods
            if law.at_rest:
                ended = "rest"
                break
    return law.report(periods, time.perf_counter() - t0 if paced else periods * T, ended,
                      late)


def drive_falcon(device_feed, scene, samples: int, *, faults=None, leds: int = 0x2,
                 decoder=None, hold_bound_s: float | None = None,
                 late_stop: bool = False, envelope_rad: float | None = None,
                 brake: bool = False, start=None) -> dict:
    """Drive a homed Falcon over its packets in lockstep, one packet per sample.

    Each sample: the reply's encoder counts are the legs' angles (``theta_deg``), the
    effector at the delta's forward kinematics (:class:`hapsim.kinematics.Delta`, exact;
    ``forward_jacobian`` from the last position),
    the n-D engine's force on the port, the leg torques ``J(q)^T F`` sent as commands
    (:func:`hapsim.drivers.falcon.torque_command`, in libnifalcon's unit taken as N m). A
    packet that does not come back (lost or corrupted on either way: both sides realign on
    ``'<'``/``'>'``) leaves the sample missing (counted; the last position held for the
    engine); a reply whose legs are not all homed, or that the kinematics refuses, is
    no sample either.

    Parameters
    ----------
    device_feed : callable
        ``bytes -> bytes`` (a :class:`FalconDevice` after :func:`load_firmware` and
        :func:`home`, possibly through faults).
    scene : hapsim.scene.SceneND
        A 3-D scene with a delta device.
    samples : int
        Packets sent.
    faults : object, optional
        ``rx(bytes)``, ``tx(bytes)`` (:class:`hapsim.emulated.driver_mock.ByteFaults`).
    leds : int
        LED flags shown while running (green).
    decoder : hapsim.drivers.falcon.DevicePacketDecoder, optional
        The homing's decoder (its last counts and step check the loop's first replies);
        default a new one (the first reply then taken unchecked).
    hold_bound_s : float, optional
        A Falcon on its own clock (no watchdog published) holds each command until the
        next: once the newest reading is older than this [s] (``time.perf_counter``),
        the commands sent are zero until a reply comes (counted in ``held_zero``). None
        (lockstep): no such rule.
    late_stop : bool
        A Falcon on its own clock: the host's lateness is watched as the 1-DoF loop
        watches it (:data:`hapsim.drivers.base.LATE_WINDOW`, :data:`hapsim.drivers.base.LATE_STOP`):
        each gap between two packets counts its excess over two periods (a packet that
        comes just after the firmware's tick waits for the next: two periods on time),
        and when the last ``LATE_WINDOW`` packets' sum passes ``LATE_STOP`` of
        their periods the loop stops, zero commands sent (``stopped``: the packet and
        the reason). The firmware held each command over every gap; a host that late
        feeds the scene's loop energy through the varying delay.
    envelope_rad : float, optional
        A reading of a leg farther than this [rad] from the scene's operating point stops
        the loop (``stopped``: a stop on the motion). None: no such stop.
    brake : bool
        After a stop (the late-stop rule's or the envelope's: both on the motion), brake
        the legs to rest before the caller's zero commands (:func:`brake_legs`).
    start : callable, optional
        Called just before the loop's first packet, after its warm-up: the hand's start
        of an identification record (:meth:`FalconDevice.let_go`), so that on the wall
        clock the legs coast unheld for no longer than the first packet takes.

    Returns
    -------
    dict
        ``position`` (N, 3) [m] (NaN where missing), ``joints`` (N, 3) [rad],
        ``commands`` (N, 3) sent, ``missing``, ``unhomed``, ``decoder`` (counters),
        ``held_zero`` (packets sent at zero for want of a fresh reading), ``stopped``
        (None, or ``(packet, reason)`` where the late-stop rule or the envelope ended the
        loop, or the Falcon was lost: "device lost: ..."), ``brake`` (None, or
        :func:`brake_legs`'s report after a stop on the motion), ``error`` (None, or the
        DeviceError's ``type`` and ``message`` when ``device_feed`` raised one after the
        loop's first packet: the rows up to it are kept).

    Raises
    ------
    DeviceError
        ``device_feed``'s, at the loop's first packet.
    """
    from hapsim.drivers.base import LATE_STOP, LATE_WINDOW
    from hapsim.drivers.falcon import (DevicePacketDecoder, host_packet, theta_deg,
                                       torque_command)
    from hapsim.engine import Engine
    from hapsim.kinematics import device
    kin = device("delta", scene.device.geometry)
    eng = Engine(scene)
    port = eng.port
    dec = DevicePacketDecoder() if decoder is None else decoder
    rx = (lambda b: b) if faults is None else faults.rx
    tx = (lambda b: b) if faults is None else faults.tx
    N = int(samples)
    pos = np.full((N, 3), np.nan)
    joints = np.full((N, 3), np.nan)
    cmds = np.zeros((N, 3), np.int64)
    missing = unhomed = 0
    guess = None
    if late_stop:
        # the compiled kinematics and engine loaded before the loop's first packet (a
        # first call's compilation would be taken for the host's lateness, and the
        # firmware would hold the first packet over it: measured 6-10 ms, a stall in
        # every run of tools/driver_timing.py before). The operating point is the first
        # reading's guess: the full solve's search for a start costs 3.5 ms, three
        # periods, which the first packet waited
        try:
            guess, _ = kin.forward_jacobian(np.asarray(scene.device.joints, float), None)
            kin.forward_jacobian(np.asarray(scene.device.joints, float), guess)
        except (ConfigError, KinematicsError):
            guess = None
        warm = Engine(scene)
        warm.step()
        warm.set_port_position(warm.x[:, warm.port].copy())
        warm.step()
    if start is not None:
        start()
    got = dec.feed(tx(device_feed(rx(host_packet((0, 0, 0), leds)))))
    x = J = None
    started = False
    held_zero = 0
    t_read = t_prev = time.perf_counter()
    T = scene.period
    late_ring = [0.0] * LATE_WINDOW
    late_sum = 0.0
    stopped = None
    lost = None
    q_op = np.asarray(scene.device.joints, float)
    for k in range(N):
        ok = False
        if got:
            enc, homed, _ = got[-1]
            if homed != 0x7:
                unhomed += 1
            else:
                q = np.radians([theta_deg(e) for e in enc])
                try:
                    # from the last position: Newton's few steps, not a fresh search
                    x, J = kin.forward_jacobian(q, guess if x is None else x)
                    ok = True
                    joints[k], pos[k] = q, x
                    t_read = time.perf_counter()
                except ConfigError:
                    pass
                if envelope_rad is not None and np.max(np.abs(q - q_op)) > envelope_rad:
                    i = int(np.argmax(np.abs(q - q_op)))
                    stopped = (k, f"safety: leg {i + 1} {np.degrees(q[i] - q_op[i]):+.1f} deg "
                                  f"from the operating point, beyond the envelope of "
                                  f"{np.degrees(envelope_rad):.1f} deg")
                    t_read = time.perf_counter()    # (the braking's first reading)
                    break
        if not ok:
            missing += 1
        if x is not None:
            if not started:
                eng.x[:, port] = x
                eng.xp[:, port] = x
                started = True
            eng.set_port_position(x)
        eng.step()
        c = (0, 0, 0) if J is None else tuple(torque_command(t) for t in J.T @ eng.port_force)
        if hold_bound_s is not None and time.perf_counter() - t_read > hold_bound_s:
            # no fresh reading for the bound: the force was computed from where the legs
            # were, and the firmware would hold it (no watchdog published): zero
            c = (0, 0, 0)
            held_zero += 1
        if late_stop:
            now = time.perf_counter()
            gap = now - t_prev
            t_prev = now
            late = gap - 2.0 * T if gap > 2.0 * T and k > 0 else 0.0
            late_sum += late - late_ring[k % LATE_WINDOW]
            late_ring[k % LATE_WINDOW] = late
            if late_sum > LATE_STOP * LATE_WINDOW * T:
                stopped = (k, f"safety: the host was {late_sum * 1e3:.0f} ms late over its "
                              f"last {LATE_WINDOW} packets: it cannot keep the Falcon's "
                              f"{scene.rate_hz:g} Hz here (a loaded machine?); zero "
                              "commands sent")
                break
        cmds[k] = c
        try:
            got = dec.feed(tx(device_feed(rx(host_packet(c, leds)))))
        except DeviceError as exc:
            # the Falcon gone (unplugged, its link failed) after the first packet: the
            # loop ends there, its rows kept, as every run's loss (nothing to brake)
            lost = exc
            stopped = (k + 1, f"device lost: {str(exc).splitlines()[0]}")
            break
    braked = None
    if stopped is not None and brake and lost is None:
        # the legs' last reading (the envelope's, or the last before a late stop) starts
        # the braking's velocity
        seen = np.flatnonzero(~np.isnan(joints[:stopped[0] + 1, 0]))
        last = q if stopped[1].startswith("safety: leg") else (
            joints[seen[-1]] if seen.size else None)     # t_read: its time
        braked = brake_legs(lambda c: dec.feed(tx(device_feed(rx(host_packet(c, leds))))),
                            scene, last, t_read, hold_bound_s=hold_bound_s)
    return {"position": pos, "joints": joints, "commands": cmds, "missing": missing,
            "unhomed": unhomed, "decoder": dict(dec.stats), "held_zero": held_zero,
            "stopped": stopped, "brake": braked,
            "error": error_record(lost)}

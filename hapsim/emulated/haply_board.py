"""The Haply M3 board (firmware V1.5), byte for byte: its command parser
(:class:`hapsim.emulated.haply_firmware.CommandDecoder`), its set-up's wait and encoder
offset, its passes, driving the joint's physics (:class:`hapsim.emulated.actuated.Actuated`);
served on a pty by :func:`hapsim.emulated.driver_mock.serve`.
"""

from __future__ import annotations

import math

from hapsim.emulated.actuated import Actuated, offline_record
from hapsim.option_values import option_value
from hapsim.emulated.haply_firmware import PASS_S, pass_at

__all__ = ["HaplyDevice", "haply_offline_loop"]


class HaplyDevice(Actuated):
    """A Haply M3 board (firmware V1.5) whose motor 1 / encoder 1 joint is the mock
    device's axis (rotary: mass = inertia [kg m^2], force = torque [N m], position = angle
    [rad]).

    The board as its firmware is: no watchdog (the motor holds its torque until a write
    changes it, through resets and set-ups), the parser of :class:`CommandDecoder` (no
    framing: misaligned bytes are other commands), a reply ``[addr]`` + a float32 per
    analog pin and encoder of ``addr`` to every write (1 byte when nothing has that
    address), the angle ``360 * count / resolution`` with the set-up's resolution and the
    count set to the set-up's offset.

    Its time (``clock="wall"``, the default): the firmware's ``loop()`` takes one command
    per pass and answers a write in the same pass, after setting the motor's duty
    (``Haply_M3_Firmware_V1_5.ino``, ``loop``: ``write_states`` then ``read_states``;
    HaplyHaptics/Haply-Arduino-Firmware-Versions, commit edcf50f), so the angle a reply
    carries is sampled when its write arrives and the torque acts from then on, held
    until the next write (no watchdog: :class:`hapsim.emulated.actuated.Actuated`, ``natural_delay`` 1). A set-up
    costs :data:`SETUP_S`: ``initialize_encoder`` (``Haply_M3_Firmware_V1_5.h``) builds a
    ``new Encoder(...)``, whose constructor waits ``delayMicroseconds(2000)`` for the
    pins' R-C filter (``Arduino_Support_Libraries/Encoder/Encoder.h``, ``Encoder(uint8_t,
    uint8_t)``) before the count is written with the offset; the commands after it wait,
    the joint does not. A pass begins :data:`PASS_S` after the one before, a command
    waiting or not (``loop``: ``if(micros() - lastPublished >= 50)``,
    ``Haply_M3_Firmware_V1_5.ino`` line 61; :func:`hapsim.emulated.haply_firmware.pass_at`:
    a write that comes to an idle board waits for the next pass) and takes one command:
    the 278 resets of 556 zero bytes take 14 ms of passes, the torque held meanwhile. A
    single ``read()`` of a byte not arrived gives 255 (:class:`CommandDecoder` with
    ``absent=255``). ``clock="lockstep"``: each write is one period.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`hapsim.emulated.actuated.Actuated`.
    cpr : float
        The encoder's real counts per revolution (the set-up's resolution only scales
        counts to degrees: a wrong one is a wrong angle).
    motor_sign : {1, -1}
        The wiring of motor 1 against encoder 1: the sign of the count's motion under a
        positive torque when both direction bytes are 0 (firmware CW). Each direction
        byte of 1 flips its side (the motor's direction pin, the encoder's pins), so
        the host's bytes drive the joint the right way when ``(-1)^(motor byte + encoder
        byte)`` equals it, and as positive feedback otherwise.
    torque_levels : {256, 0}
        The motor's torque levels. 256 (the default, the firmware's): ``create_torque``
        computes a 12-bit duty ``(int)(4095 * |torque| / 0.123)``
        (``Haply_M3_Firmware_V1_5.h:467-492``, the clamp at ``MAX_TORQUE`` .h:54,
        485-487) and ``pwm_write_duty`` writes it at the Due's ``PWM_RESOLUTION`` of 8
        bits (randomvibe's ``pwm01.h:58-66, 110-120``; ArduinoCore-sam
        ``variants/arduino_due_x/variant.h:229``) on a period of 255 counts: the motor
        gets ``(duty >> 4) / 255`` of 0.123 N m (within a level of the torque)
        (:func:`hapsim.drivers.output_stage.m3_output`). 0 (named): the float applied
        exactly, as this board did before.

    Attributes
    ----------
    decoder : CommandDecoder
    torque : float
        The torque motor 1 holds [N m].

    Raises
    ------
    hapsim.errors.ConfigError
        A ``cpr`` or ``resolution`` that is no finite number > 0, a ``motor_sign`` other
        than 1 or -1, ``torque_levels`` other than 256 or 0, an unknown ``clock``.
    """

    #: What a set-up takes on the board [s]: the Encoder constructor's 2 ms wait.
    SETUP_S = 2e-3
    #: The time between two passes of the firmware's ``loop()`` [s] (one command each):
    #: :data:`hapsim.emulated.haply_firmware.PASS_S`.
    PASS_S = PASS_S

    def __init__(self, device, rate_hz: float, excitation=None, *, cpr: float = 4880.0,
                 resolution: float | None = None, seed: int = 0, motor_sign: int = 1,
                 clock: str = "wall", torque_levels: int = 256) -> None:
        from hapsim.drivers import haply as hp
        from hapsim.emulated.haply_firmware import CommandDecoder
        from hapsim.errors import ConfigError
        if torque_levels not in (256, 0):
            raise ConfigError(f"must be 256 (the firmware's duty at the Due's 8 bits) or 0 "
                              f"(the float applied), got {torque_levels!r}",
                              key="torque_levels")
        self.torque_levels = int(torque_levels)
        if motor_sign not in (1, -1):
            raise ConfigError(f"must be 1 or -1, got {motor_sign!r}", key="motor_sign")
        self.motor_sign = int(motor_sign)
        self._hp = hp
        super().__init__(device, rate_hz, excitation, hp.MAX_TORQUE, seed, clock=clock)
        # the firmware's single reads of an empty buffer: 255 (CommandDecoder notes)
        self.decoder = CommandDecoder(absent=255)
        # (resolution: the set-up packet's name for it; given, it is the count)
        self.cpr = option_value("cpr" if resolution is None else "resolution",
                                cpr if resolution is None else resolution,
                                "counts per revolution", low=0, low_ok=False)
        self._base = 0
        self._base0 = None
        #: The largest error [rad] of the board's frame against the joint's true angle,
        #: over the set-ups after the first: each re-synchronisation sets the count to
        #: the host's estimate of the angle, and the frame walks by that estimate's error
        #: (the truth only an emulator knows).
        self.frame_walk = 0.0
        #: The board's time [s] its last answer is ready at (:func:`serve` writes it then).
        self.ready_at = 0.0
        self._busy_until = 0.0

    def _counts(self) -> int:
        return round(self.physics.sample() / (2 * math.pi) * self.cpr)

    def angle_deg(self, port: int = 0) -> float:
        """Encoder ``port``'s reading [deg] (firmware ``read_encoder_value``, rounded to
        binary32 on the wire).

        Parameters
        ----------
        port : int
            The encoder port, 0..3 (port - 1); only 0, the handle's joint, is read (any
            other gives 0.0).

        Returns
        -------
        float
            ``360 * count / resolution`` [deg] (not yet rounded); a set-up's resolution 0
            or not finite gives +-inf (nan at count 0).
        """
        dec = self.decoder
        if port != 0:
            return 0.0
        res = dec.encoder_res[0]
        c = self._counts() - self._base
        if dec.encoder_direction[0]:
            c = -c
        if not (math.isfinite(res) and res):       # a garbage set-up's resolution
            return math.copysign(math.inf, c) if c else math.nan
        return 360.0 * c / res

    def feed(self, data: bytes, now: float = math.inf) -> bytes:
        """Bytes from the host in, the replies out (one per write).

        Parameters
        ----------
        data : bytes
            What the host wrote.
        now : float
            The board's time the bytes arrived at [s] (needed on the wall clock).

        Returns
        -------
        bytes
            The replies; on the wall clock they are ready at :attr:`ready_at`.
        """
        import struct
        out = b""
        dec = self.decoder
        wall = self.wall is not None
        # (the first pass after the bytes came: passes go on every PASS_S, idle or not)
        t = pass_at(now, self._busy_until) if wall else now
        for cmd in dec.commands(data):
            if wall:
                # the pass after the last one (PASS_S) or after a set-up's wait
                t = max(t, self._busy_until)
                self._busy_until = t + self.PASS_S
            if cmd[0] == "setup":
                if wall:
                    self.wall.run_to(t)
                    self._busy_until = t + self.SETUP_S
                    t = self._busy_until
                    self.wall.run_to(t)           # the count is written after the wait
                if dec.encoder_addr[0]:           # the count is set to the offset
                    off = dec.encoder_offset[0] * dec.encoder_res[0] / 360.0
                    off = int(off) if math.isfinite(off) and abs(off) < 2**31 else 0
                    c = self._counts()
                    self._base = c - (-off if dec.encoder_direction[0] else off)
                    if self._base0 is None:
                        self._base0 = self._base
                    self.frame_walk = max(self.frame_walk, abs(self._base - self._base0)
                                          * 2.0 * math.pi / self.cpr)
                continue
            if cmd[0] != "write":
                continue
            _, addr, tq = cmd
            tau = tq.get(0)
            if tau is not None:
                if not math.isfinite(tau):
                    tau = 0.0                     # (the firmware: a NaN duty is 0)
                tau = max(-self._hp.MAX_TORQUE, min(self._hp.MAX_TORQUE, tau))
                if self.torque_levels:
                    # create_torque's 12-bit duty at the Due's 8 bits (class notes)
                    from hapsim.drivers.output_stage import m3_output
                    tau = float(m3_output([tau])[0][0])
                if dec.motor_direction[0]:
                    tau = -tau
                tau *= self.motor_sign
            if wall:
                self.apply(tau, now=t)            # the joint has run to t; the torque acts
            else:
                self.apply(tau)
            na, encs = dec.reply_layout(addr)
            out += bytes([addr]) + struct.pack("<f", 0.0) * na
            for p in encs:
                a = self.angle_deg(p)
                if abs(a) > 3.4028234663852886e38:    # binary32 overflows to inf
                    a = math.copysign(math.inf, a)
                out += struct.pack("<f", a)
        if wall:
            self.ready_at = t
        return out


def haply_offline_loop(scene, n: int, *, write_late=None, device=None,
                       resolution: float = 4880.0, torque_levels: int = 256):
    """The Haply M3 THS closed offline on a simulated clock: the board on its own time
    (:class:`HaplyDevice` with ``clock="wall"``, fed the simulated time of each write),
    hapsim's engine as the host; deterministic, no pty, no real time.

    The host loop's arithmetic (:class:`hapsim.drivers.transport.DriverTransport`): row
    ``k`` is the reply to command ``k`` (the joint read when the board took it), the
    force computed from it goes out with command ``k + 1``. The host writes command ``k``
    at ``k T + write_late[k]`` and stamps the row with that time (the transport's
    ``time_us``, the telemetry's ``time``, from 62.5 ms on: the arming before); the board
    takes it at its next pass (:func:`hapsim.emulated.haply_firmware.pass_at`) and holds
    its torque until it takes the next (firmware V1.5: no watchdog, no tick), so hold
    ``k`` lasts ``T + write_late[k] - write_late[k - 1]``, each end put off to its pass
    (whole passes of ``write_late`` keep the holds as they are).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated scene whose device speaks ``haply`` (its rate, delay 1, force limit
        and excitation).
    n : int
        Rows [samples].
    write_late : array_like of float, shape (n + 1,), optional
        How late the host writes each command after its tick [s] (0: on time).
    device : hapsim.scene.Device, optional
        The board's true joint when it is not the scene's (a hidden inertia).
    resolution : float, optional
        The encoder's counts per revolution (the set-up's and the board's).
    torque_levels : {256, 0}
        The board's torque levels (:class:`HaplyDevice`; 0, named: the float applied).

    Returns
    -------
    tuple
        ``(columns, driver, board)``: telemetry columns (``time`` [s], ``position``
        [rad], ``force`` [N m], ``seq``, ``flags``, ``late``, ``force_seq``, ``status``),
        shape (n,); the :class:`hapsim.drivers.haply.HaplyM3` whose replies they are
        (its ``loop_delay`` and ``own_clock`` set); the board.
    """
    import numpy as np

    from hapsim.drivers.haply import HaplyM3
    sc = scene
    x0 = float(getattr(sc.excitation, "x0", 0.0) or 0.0)
    drv = HaplyM3(resolution=resolution, **HaplyM3.embedded_options({}, x0))    # armed at the hand's start
    drv.loop_delay = int(sc.device.delay)
    drv.own_clock = True                       # the board keeps its time (simulated)
    board = HaplyDevice(device or sc.device, sc.rate_hz, sc.excitation, clock="wall",
                        resolution=drv.resolution, torque_levels=torque_levels)
    now = [0.0]
    dec = drv.decoder()
    T = sc.period
    late = np.zeros(n + 1) if write_late is None else np.asarray(write_late, float)
    # the arming (278 resets in 50 us passes, the set-up's 2 ms: 16 ms of the board's
    # time, which starts at 0) done well before row 0, at rest
    t0 = 0.0625                                  # exact in binary64
    board.feed(drv.arm(), 0.0)
    dec.feed(board.feed(drv.encode_force(0.0), t0 / 2))

    def command(j: int, f: float) -> float:
        now[0] = t0 + j * T + float(late[j])
        return dec.feed(board.feed(drv.encode_force(f), now[0]))[-1]

    cols = offline_record(sc, drv, command, n, lambda k: now[0])
    return cols, drv, board


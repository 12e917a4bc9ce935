"""A Hapkit running the WHC2017 sketch with the host-force function, byte for byte and on its
own 0.992 ms tick: the sketch's ``loop`` reading a command on a tick, then reading the handle
and applying the force at the next tick or the command's end, driving the handle's physics (:class:`hapsim.emulated.actuated.Actuated`); served on a pty
by :func:`hapsim.emulated.driver_mock.serve`.
"""

from __future__ import annotations

import math
import statistics

from hapsim.drivers.hapkit_serial import FIRMWARE_TICK_S, whole_ticks
from hapsim.emulated.actuated import Actuated, offline_record
from hapsim.option_values import option_value

__all__ = ["HapkitSerialDevice", "SketchReader", "hapkit_serial_offline_loop"]


class SketchReader:
    """The sketch's reads of the host's bytes, as its firmware makes them: no framing.

    On a tick with a byte waiting, ``loop`` reads one header byte and
    ``receive_data`` nine more with ``Serial.readBytes`` (haphub/WHC2017
    ``hFirmware/Hapkit_Arduino_Control/Hapkit_arduino/``: ``Hapkit_arduino.ino``, ``loop``;
    ``Hapkit_arduino.h``, ``receive_data``): the function byte and two binary32 values,
    whatever they are. ``readBytes`` waits for each byte up to
    :data:`hapsim.drivers.hapkit_serial.SKETCH_READ_TIMEOUT_S` (15.6 ms); a byte not come
    by then leaves the buffer's old content (a local array at the same place of the stack
    each call: taken as the last command's bytes) and the next byte starts a command. So
    a host byte lost makes the command complete with the next command's first byte, and
    every later command is read one byte out of step (its function byte the host's first
    float's first byte: 0, no force) until the host is silent longer than the timeout.
    (Before, the emulated board realigned on the header and the function byte, which the
    sketch does not: with 1 byte in 200 lost its loop lost no more than the commands hit,
    where the sketch's is out of step from the first loss on.)

    Parameters
    ----------
    timeout_s : float
        ``readBytes``' wait per byte [s].

    Attributes
    ----------
    stats : dict
        ``frames`` (commands read), ``misparsed`` (whose function byte is not the host
        force's), ``timeouts`` (completed by the timeout), ``non_finite`` (a host-force
        command whose force is no finite number: applied as 0).
    function : int
        The last command's function byte (what the reply echoes).
    t_last : float or None
        When the last byte came [s] (the board's time).
    """

    def __init__(self, timeout_s: float | None = None, function: int = 255) -> None:
        from hapsim.drivers.hapkit_serial import HOST_FORCE_FUNCTION, SKETCH_READ_TIMEOUT_S
        self.timeout_s = float(SKETCH_READ_TIMEOUT_S if timeout_s is None else timeout_s)
        self.host_function = int(function if function is not None else HOST_FORCE_FUNCTION)
        self._cur = bytearray()
        self._stale = bytearray(9)
        self.t_last = None
        self.function = 0
        self.stats = {"frames": 0, "misparsed": 0, "timeouts": 0, "non_finite": 0}

    def feed(self, data: bytes, now: float) -> list:
        """Bytes that came at the board's time ``now`` [s]; the commands completed, in order.

        Parameters
        ----------
        data : bytes
            The host's bytes.
        now : float
            The board's time they came at [s].

        Returns
        -------
        list of (float, int, float, float)
            ``(t, function, a, b)``: when the command was complete [s] (its last byte's
            time, or the timeout's end), its function byte and its two values.
        """
        out = self.expire(now)
        for b in data:
            out += self.take(b, now)              # (every byte at ``now``: the read's rule)
        return out

    def expire(self, now: float) -> list:
        """The command a ``readBytes`` still waits for, completed by its timeout if the
        host has been silent longer than it by ``now`` [s]; ``[]`` or one command.

        Parameters
        ----------
        now : float
            The board's time [s].

        Returns
        -------
        list of (float, int, float, float)
            ``[]`` or one command ``(t, function, a, b)``, as :meth:`feed`'s.
        """
        if self._cur and self.t_last is not None and now - self.t_last > self.timeout_s:
            return self.time_out()
        return []

    def take(self, byte: int, t: float) -> list:
        """One byte read at ``t`` [s], the timeout kept by the caller (the sketch's loop,
        :meth:`HapkitSerialDevice._run`); the command it completes, ``[]`` or one.

        Parameters
        ----------
        byte : int
            The byte, 0..255.
        t : float
            The board's time it is read at [s].

        Returns
        -------
        list of (float, int, float, float)
            ``[]`` or one command ``(t, function, a, b)``, as :meth:`feed`'s.
        """
        self._cur.append(int(byte))
        self.t_last = float(t)
        return [self._finish(t)] if len(self._cur) == 10 else []

    def time_out(self) -> list:
        """``readBytes``' timeout: the command under way completed with the buffer's old
        bytes at the last byte's time plus :attr:`timeout_s`; ``[]`` when none is.

        Returns
        -------
        list of (float, int, float, float)
            ``[]`` or one command ``(t, function, a, b)``, as :meth:`feed`'s.
        """
        if not self._cur:
            return []
        self.stats["timeouts"] += 1
        return [self._finish(self.t_last + self.timeout_s)]

    def _finish(self, t: float) -> tuple:
        import struct
        body = bytes(self._cur[1:]) + bytes(self._stale[len(self._cur) - 1:])
        self._stale = bytearray(body)
        self._cur = bytearray()
        self.function = body[0]
        a, b = struct.unpack_from("<ff", body, 1)
        self.stats["frames"] += 1
        if body[0] != self.host_function:
            self.stats["misparsed"] += 1
        elif not math.isfinite(b):
            self.stats["non_finite"] += 1
        return (float(t), body[0], a, b)


def sketch_force(function: int, host_function: int, b: float, x: float, v: float) -> float:
    """The force the sketch renders for a command's function byte (``renderingAlgorithm``
    of ``Hapkit_Kinematics_Simulation.h``; haphub/WHC2017): the host's force ``b`` [N] for
    ``host_function`` (the case the driver's firmware adds; non-finite: 0), 0 none, 1 a
    wall at 5 mm (400 N/m), 2 a damper (15 N s/m on the velocity ``v`` [m/s]), 3 a spring
    (100 N/m on the handle's position ``x`` [m]), any other none.

    Parameters
    ----------
    function : int
        The command's function byte, 0..255.
    host_function : int
        The function byte of the host's force.
    b : float
        The command's second value: the host's force [N].
    x : float
        The handle's position [m].
    v : float
        The handle's velocity [m/s].

    Returns
    -------
    float
        The force [N].
    """
    if function == host_function:
        return float(b) if math.isfinite(b) else 0.0
    if function == 1:
        return -400.0 * (x - 0.005) if x > 0.005 else 0.0
    if function == 2:
        return -15.0 * v
    if function == 3:
        return -100.0 * x
    return 0.0


class HapkitSerialDevice(Actuated):
    """A Hapkit running the WHC2017 sketch with the host-force function: its handle is the
    mock device's moving mass.

    Its time, ``clock="wall"`` (the default): the sketch runs a fixed 0.992 ms tick on its
    own clock (:data:`TICK_S`, from power-on: the board's time 0) and its ``loop``
    (haphub/WHC2017 ``Hapkit_arduino.ino:96-135``, read line by line: :meth:`_run`) takes
    the tick's one-bit flag and either reads a command (a byte waiting) or samples the
    handle, renders and replies (none waiting). The host's bytes come one each 10 bits at
    57600 baud (:data:`BYTE_S`), so a command's read ends 1.56 ms after its first byte,
    past the next tick: the handle is read at the command's end for a command whose first
    byte comes up to 0.57 ms before a tick, on the tick after the read's for the rest,
    and the reply leaves ``render_s`` and the 9 bytes' wire time at 57600 baud
    (:data:`REPLY_WIRE_S`, 1.56 ms) after the read (measured on the independent sketch
    model, which reads the same lines: a reply 3.59 ms after the write over the first
    region; this board, ``render_s`` 0.45 ms, 3.75 ms). Before, this board read the handle
    on the tick after the command's last byte, with the command's bytes all come at the
    write: a step of one tick in the write-to-reply time, where the sketch's has a flat
    part, a ramp and a jump of 0.42 ms, which the host's tick probe took for outliers (4
    of 16, its refusal threshold). The handle is integrated exactly over the real time
    between events (:class:`WallClock`), the force held whatever the host does: the
    sketch has no silence rule. Its loop delay is one host period (the read and the
    force in one branch, the force computed from that read one command later); a scene
    stating more delays each force by the rest
    (:attr:`hapsim.emulated.actuated.Actuated.extra_latency_s`).
    ``clock="lockstep"`` (named, for deterministic tests): one period per command, the
    reply at once.

    Its output, as the sketch's (haphub/WHC2017 ef6028f,
    ``Hapkit_Kinematics_Simulation.h``, cited ``sim.h:line`` as
    :mod:`hapsim.drivers.output_stage` does): the rendered ``force`` is turned to the
    motor pulley's torque ``Tp = rp/rs * rh * force`` (sim.h:191) and ``forceOutput``
    writes ``(int)(255 * sqrt(|Tp| / 0.0183))`` (sim.h:218-228): 256 levels on a
    square-root curve, the force cut to the level below
    (:func:`hapsim.drivers.output_stage.sketch_board_output`), on either clock. On the wall
    clock the level takes effect :data:`hapsim.drivers.hapkit_serial.RENDER_S` after the
    handle's read (``analogRead``, the binary32 render and ``analogWrite`` in one branch
    of ``loop``, ``Hapkit_arduino.ino:111-122``), and the reply leaves after it. The
    reply's second float is ``Tp`` (``outdata[1] = Tp``, ``Hapkit_arduino.ino:129`` at the
    head; ``reply="force"``: the rendered force, its copy of 2017-04-07). ``levels=0`` and
    ``render_s=0`` (named) are a sketch that applies the float at its read, as this board
    did before.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`hapsim.emulated.actuated.Actuated`.
    force_limit : float
        The firmware's force clamp [N].
    clock : {"wall", "lockstep"}
        The board's clock (above).
    levels : {256, 0}
        The output's levels: 256 (the sketch's ``forceOutput``) or 0 (the float applied).
    render_s : float, optional
        Wall clock: the time from the handle's read to the new duty [s], >= 0 (default
        :data:`hapsim.drivers.hapkit_serial.RENDER_S`; lockstep: none).
    reply : {"Tp", "force"}
        What the reply's second float is (above).
    count_m : float, optional
        The sketch's position step at the handle [m], >= 0 (default
        :data:`hapsim.drivers.hapkit_serial.SKETCH_COUNT_M`, 17.19 um: ``xh = rh (m
        updatedPos + b)``, ``Hapkit_Kinematics_Simulation.h:130-138``, counted from the
        power-up pose at 0; 0: the handle read exactly). A device stating its own
        ``position_resolution`` keeps it.
    clock_ppm : float, optional
        Wall clock: how far the board's oscillator runs from the host's clock [parts per
        million], positive slower (default 0). The sketch's tick is 62 counts of Timer1 at
        16 MHz / 256 (``Hapkit_arduino.h:59-68``): a board whose 16 MHz source is off by
        ``e`` ticks every ``TICK_S (1 + e)`` host seconds, and the host's writes, aligned
        to its ticks once at the arming, walk across them by ``e`` ticks a tick. Within
        (-1e5, 1e5).

    Attributes
    ----------
    decoder : SketchReader or hapsim.drivers.hapkit_serial.CommandDecoder
        The sketch's reads (wall clock), or the lockstep device's realigning decoder.
    ready_at : float
        Wall clock: the board's time [s] its last reply has left at (:func:`serve` writes
        it then).

    Raises
    ------
    hapsim.errors.ConfigError
        A ``force_limit`` that is no finite number > 0, a ``count_m`` or ``render_s`` < 0,
        ``levels`` other than 256 or 0, an unknown ``reply`` or ``clock``, a
        ``clock_ppm`` outside (-1e5, 1e5).
    """

    #: The sketch's control tick [s]: Timer1 reloaded to 65474 at 16 MHz / 256, 62 counts
    #: of 16 us, 0.992 ms (:data:`hapsim.drivers.hapkit_serial.FIRMWARE_TICK_S`,
    #: ``Hapkit_arduino.h:59-68``), on the host's clock; an instance's is its board's
    #: (``clock_ppm``: an oscillator off the host's clock).
    TICK_S = FIRMWARE_TICK_S
    #: A 9-byte reply's time on the wire at 57600 baud, 10 bits a byte [s].
    REPLY_WIRE_S = 9 * 10 / 57600
    #: One byte's time on the wire at 57600 baud [s] (the host's bytes come at this pace).
    BYTE_S = 10 / 57600
    #: The sketch's UART takes the host's bytes by interrupt into its ring buffer while
    #: ``loop`` reads, renders or waits (the Arduino core's ``HardwareSerial``): the pty's
    #: server reads on while a reply waits for its time
    #: (:func:`hapsim.emulated.driver_mock.serve`), so a command written meanwhile is
    #: stamped when it came, not after the reply (a reply 3.75 ms after its write is
    #: within a tick of the next write at 4 ticks a period).
    listens_while_answering = True

    def __init__(self, device, rate_hz: float, excitation=None, *, force_limit: float = 2.0,
                 clock: str = "wall", seed: int = 0, levels: int = 256,
                 render_s: float | None = None, reply: str = "Tp",
                 count_m: float | None = None, clock_ppm: float = 0.0) -> None:
        import dataclasses

        from hapsim.drivers import hapkit_serial as hk
        from hapsim.errors import ConfigError
        count_m = (hk.SKETCH_COUNT_M if count_m is None
                   else option_value("count_m", count_m, "m", low=0))
        if count_m > 0 and not float(getattr(device, "position_resolution", 0.0) or 0.0):
            # the sketch's reading, a whole number of counts (MockPhysics.sample rounds)
            device = dataclasses.replace(device, position_resolution=count_m)
        self.count_m = count_m
        if levels not in (256, 0):
            raise ConfigError(f"must be 256 (the sketch's forceOutput) or 0 (the float "
                              f"applied), got {levels!r}", key="levels")
        if reply not in ("Tp", "force"):
            raise ConfigError(f"must be 'Tp' or 'force', got {reply!r}", key="reply")
        render_s = (hk.RENDER_S if render_s is None
                    else option_value("render_s", render_s, "s", low=0))
        if not (isinstance(clock_ppm, (int, float)) and abs(float(clock_ppm)) < 1e5):
            raise ConfigError(f"must be a number of parts per million within (-1e5, 1e5), "
                              f"got {clock_ppm!r}", key="clock_ppm")
        # the tick on the host's clock: the board's oscillator off by clock_ppm
        self.TICK_S = FIRMWARE_TICK_S * (1.0 + float(clock_ppm) * 1e-6)
        self.clock_ppm = float(clock_ppm)
        self._hk = hk
        self.levels = int(levels)
        self.render_s = render_s
        self.reply = reply
        self._rendered: list = []                     # lockstep: rendered, queued
        self._phases: list = []                       # where in its tick each came
        self._ticks: list = []                        # the tick that took each
        self._sampled: list = []                      # wall: each reply's read [s]
        super().__init__(device, rate_hz, excitation,
                         option_value("force_limit", force_limit, "N", low=0, low_ok=False),
                         seed, clock=clock)
        # the wall clock's board reads as the sketch does (SketchReader); the lockstep
        # test device, paced by the commands, has no time for its reads' timeout and
        # realigns on the header and function bytes (CommandDecoder)
        self.decoder = SketchReader() if clock == "wall" else hk.CommandDecoder()
        self.ready_at = 0.0
        # the wall clock's loop (:meth:`_run`): the bytes come and not yet read (when each
        # has come [s], the byte), when the receive line is free [s], the last tick whose
        # flag the loop took, when the loop is free [s], a read under way, the last
        # command read (SketchReader's tuple) and whether its reply is due
        from collections import deque
        self._rx: deque = deque()
        self._rx_free = 0.0
        self._tick = -1
        self._loop_t = 0.0
        self._reading = False
        self._command = None
        self._reply_due = False
        self._fed_at = None                           # the host's last write [s]

    def feed(self, data: bytes, now: float = math.inf) -> bytes:
        """Bytes from the host in (at the board's time ``now`` [s], needed on the wall
        clock), the replies out: lockstep one per command; wall clock one per render that
        follows a read (:meth:`_run`).

        Parameters
        ----------
        data : bytes
            What the host wrote.
        now : float
            The board's time the bytes came at [s] (wall clock: needed; lockstep: ignored).

        Returns
        -------
        bytes
            The 9-byte replies (:func:`hapsim.drivers.hapkit_serial.reply_packet`); on the
            wall clock the last is ready at :attr:`ready_at`.

        Raises
        ------
        ValueError
            Wall clock: ``now`` not finite.
        """
        if self.wall is not None:
            if not math.isfinite(now):
                raise ValueError("a board on the wall clock needs the time of each write")
            for byte in data:
                # the UART's receive line: one byte each 10 bits at 57600 baud, after the
                # byte before (the USB-serial bridge sends a write's bytes back to back)
                self._rx_free = max(float(now), self._rx_free) + self.BYTE_S
                self._rx.append((self._rx_free, byte))
            self._fed_at = float(now)
            return self._run(float(now))
        out = b""
        for f in self.decoder.feed(data):
            # the force rendered (clamped; a corrupted float: 0), through the output stage
            r = f if math.isfinite(f) else 0.0
            r = max(-self.limit, min(self.limit, r))
            self._rendered.append(r)
            self.apply(self._output(r))
            # the sketch replies with the handle it read and what it renders from that
            # tick on (as on the wall clock): the queue's head, not the period's just ended
            head = self._rendered[-self.delay] if 0 < self.delay <= len(self._rendered) \
                else (r if self.delay == 0 else 0.0)
            del self._rendered[:-max(self.delay, 1)]
            out += self._hk.reply_packet(self.decoder.function, self.physics.sample(),
                                         self._reply_value(head))
        return out

    def _output(self, force: float) -> float:
        """The force the motor makes for a rendered ``force`` [N] (class notes)."""
        if not self.levels:
            return float(force)
        from hapsim.drivers.output_stage import sketch_board_output
        return float(sketch_board_output([force])[0])

    def _reply_value(self, force: float) -> float:
        """The reply's second float for a rendered ``force`` [N]: its ``Tp`` [N m] (binary32,
        sim.h:191) or the force itself (``reply="force"``)."""
        if self.reply == "force":
            return float(force)
        from hapsim.drivers.output_stage import sketch_tp
        return float(sketch_tp([force])[0])

    def _run(self, now: float) -> bytes:
        """Wall clock: the sketch's ``loop`` (``Hapkit_arduino.ino:96-135``) run as far as
        the bytes come by ``now`` [s] decide it; the replies it writes.

        The Timer1 interrupt sets a one-bit flag each tick (``.ino:137-140``); ``loop``
        takes it, and then either (a byte waiting) reads a command -- the header with
        ``Serial.read()``, 9 bytes with ``readBytes``, which waits for each up to
        :data:`hapsim.drivers.hapkit_serial.SKETCH_READ_TIMEOUT_S` (:class:`SketchReader`)
        -- and nothing else, or (none waiting) samples the handle, renders, and writes a
        reply if a command was read since the last (``reply``, ``.ino:111-132``). A read
        ends with the command's last byte, 1.56 ms of wire after its first, more than a
        tick: the flag a tick set meanwhile is taken at once, so the sample is at the
        command's end, not at a tick, for a command whose first byte comes less than
        ``2 T - 1.5625 ms`` (0.57 ms) before a tick, and on the tick after the read's for
        the rest (the probe's model, :func:`hapsim.drivers.tick_align.fit_tick_jump`). A
        command whose bytes come while another is read is read next, with no render
        between: one reply for both.

        The render after a read is decided by the bytes come by then; one after the
        first time a byte written after ``now`` could come is decided on the bytes written
        by ``now`` (the emulator cannot see a write not yet made): a byte coming before it
        would have been read first. A
        render with no reply due and a force that does not depend on the handle (the
        host's function, none) changes nothing and is not run.
        """
        T = self.TICK_S
        rd = self.decoder
        q = self._rx
        out = b""
        # what is decided: a byte the host has not yet written comes after this [s]
        now = max(float(now), self._rx_free) + self.BYTE_S
        while True:
            if self._reading:
                # readBytes: the next byte, or its timeout from when the wait began
                wait_end = self._loop_t + rd.timeout_s
                if q and q[0][0] <= wait_end:
                    t_b, byte = q.popleft()
                    self._loop_t = max(self._loop_t, t_b)
                    done = rd.take(byte, self._loop_t)
                elif q or now > wait_end:
                    done = rd.time_out()
                    self._loop_t = wait_end
                else:
                    return out                        # waiting for a byte still to come
                if done:
                    self._reading = False
                    self._command = done[-1]
                    self._reply_due = True
                continue
            # the flag: at once if a tick passed since the one taken, else the next tick
            k = self._tick + 1
            if self._loop_t >= k * T:
                k = max(k, math.floor(self._loop_t / T))
                t = self._loop_t
            else:
                t = k * T
            if q and q[0][0] <= t:
                # a byte waiting: the header read (Serial.read), then readBytes
                t_b, byte = q.popleft()
                self._tick = k
                self._loop_t = t
                self._phases.append(t_b / T - math.floor(t_b / T))
                self._ticks.append(k)
                rd.take(byte, t)
                self._reading = True
                continue
            fn = self._command[1] if self._command is not None else rd.function
            live = fn in (1, 2, 3) and fn != rd.host_function
            if not self._reply_due and not live:
                # nothing a render changes: the loop idles to the next byte or ``now``
                until = min(q[0][0], now) if q else now
                if until <= t:
                    return out
                self._tick = max(k, math.floor(until / T))
                if q and q[0][0] <= self._tick * T:
                    self._tick -= 1                   # that tick finds the byte
                continue
            if t > now and not self._reply_due:
                return out                            # a render still to come
            self._tick = k
            out += self._render(t)
            self._loop_t = t + self.render_s

    def _render(self, t: float) -> bytes:
        """Wall clock: the branch with no byte waiting at ``t`` [s]: the handle read, the
        force the last command's function renders applied ``render_s`` later (plus the
        scene's delay beyond the board's), and the reply when a command was read since
        the last one (``.ino:111-132``)."""
        rd = self.decoder
        fn, b = (self._command[1], self._command[3]) if self._command is not None \
            else (rd.function, 0.0)
        self.wall.run_to(t)
        x = self.physics.sample()                     # the handle read
        f = sketch_force(fn, rd.host_function, b, x, self.physics.v)
        if abs(f) > self.limit:
            f = math.copysign(self.limit, f)
            self.clamped += 1
        self.held = self.wall.held
        self.last_command = f
        self.wall.schedule(t + self.render_s + self.extra_latency_s, self._output(f))
        if not self._reply_due:
            return b""
        self._reply_due = False
        if len(self._sampled) < 100_000:
            self._sampled.append(t)
        self.applied.append(self._output(f))
        self.ready_at = t + self.render_s + self.REPLY_WIRE_S
        return self._hk.reply_packet(fn, x, self._reply_value(f))

    def idle(self, silent_s: float) -> bytes:
        """The sketch has no silence rule: it holds its force. On the wall clock its loop
        runs on to the host's last byte plus ``silent_s`` [s]: a command whose bytes
        stopped coming is completed by ``readBytes``' timeout (:class:`SketchReader`),
        then rendered and answered.

        Parameters
        ----------
        silent_s : float
            Time since the host's last write [s].

        Returns
        -------
        bytes
            The replies the loop writes meanwhile (``b""`` in lockstep or before a write).
        """
        if self.wall is None or self._fed_at is None:
            return b""
        return self._run(self._fed_at + float(silent_s))

    @property
    def tick_arrivals(self) -> dict:
        """Where in the sketch's tick the commands' header bytes came (wall clock), for
        the host's timing: ``commands``; ``near_boundary``, those within a tenth of a tick
        of the tick's end or start (a header coming there is read at one tick or the next
        by a jitter of 0.1 ms: the reading 0.42 ms off);
        ``median_phase``, the median arrival phase [fraction of a tick, 0 at a tick], and
        ``phase_sd`` their standard deviation [fraction of a tick];
        ``sample_interval_ms``, the 1st, 50th and 99th percentiles of the intervals
        between the replies' readings [ms] (the first 100,000; intervals over two periods,
        the probes' and an arming's, left out);
        ``off_period``, the commands taken another number of ticks after the one before
        than the period holds (a force held a tick longer or shorter; a gap of more than
        two periods, the probes' and an arming's, not counted), with ``off_at`` the
        first 1000 of them (their index among the commands)."""
        ph = sorted(self._phases)
        near = sum(1 for p in ph if p < 0.1 or p > 0.9)
        per = whole_ticks(self.physics.period)     # (the board's own count of ticks)
        off = []
        if per is not None:
            t = self._ticks
            off = [i for i in range(1, len(t))
                   if t[i] - t[i - 1] != per and t[i] - t[i - 1] <= 2 * per]
        gaps = sorted(b - a for a, b in zip(self._sampled, self._sampled[1:])
                      if b - a <= 2.0 * self.physics.period)
        pct = (lambda f: round(1e3 * gaps[min(int(f * len(gaps)), len(gaps) - 1)], 4)
               if gaps else None)
        return {"commands": len(ph), "near_boundary": near,
                "sample_interval_ms": {"p1": pct(0.01), "median": pct(0.5),
                                       "p99": pct(0.99)},
                "median_phase": ph[len(ph) // 2] if ph else None,
                "phase_sd": statistics.pstdev(ph) if ph else None,
                "off_period": len(off), "off_at": off[:1000]}


def hapkit_serial_offline_loop(scene, n: int, *, read_late=None, device=None,
                               phase: float = 0.5, levels: int = 256,
                               render_s: float | None = None, lost_replies=(),
                               count_m: float = 0.0, clock_ppm: float = 0.0):
    """The Hapkit-serial THS closed offline on a simulated clock: the sketch on its own
    0.992 ms tick (:class:`HapkitSerialDevice` with ``clock="wall"``, fed the simulated time
    of each command), hapsim's engine as the host; deterministic, no pty, no real time.

    The host loop's arithmetic: row ``k`` is the reply to command ``k`` (the handle read
    at the tick that took it), the force computed from it goes out with command ``k + 1``.
    The host writes command ``k`` at ``k T + phase`` ticks, in the middle of a tick as the
    transport aligns them (:meth:`hapsim.drivers.tick_align.TickAligned.tick_phase`): of
    the board's ticks when its oscillator keeps the host's time, of the nominal 0.992 ms
    when it does not (``clock_ppm``: the writes then walk across the board's ticks); the
    board reads command ``k`` ``read_late[k]`` ticks after it came (its own read latency:
    a USB-serial bridge's frame, its process scheduled late), unseen by the host (nothing
    is marked in the driver's ``mistimed_seqs``): a latency past the tick's end takes the
    command at a later tick, the reply's position read that much late and the force before
    held that much longer (:attr:`HapkitSerialDevice.tick_arrivals` counts them).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated scene whose device speaks ``hapkit-serial`` (its rate a whole number
        of ticks, its delay, force limit and excitation).
    n : int
        Rows [samples].
    read_late : dict of int to float, optional
        ``{command: ticks}``: the board's read latency of those commands [ticks].
    device : hapsim.scene.Device, optional
        The board's true device when it is not the scene's (a hidden mass or friction).
    phase : float
        Where in its tick the host's writes come [fraction of a tick].
    levels, render_s
        The board's output levels and render latency (:class:`HapkitSerialDevice`;
        ``levels=0, render_s=0``, named: a sketch that applies the float at its read, the
        driver told so: its ``levels`` 0).
    count_m : float
        The board's position step [m] and the driver's (:class:`HapkitSerialDevice`'s
        ``count_m``); 0 (the default here): read exactly, the exact records the offline
        tests compare to round-off.
    clock_ppm : float
        The board's oscillator off the host's clock [ppm], positive slower
        (:class:`HapkitSerialDevice`'s ``clock_ppm``; 0, the default: on the host's time).
    lost_replies : collection of int, optional
        Commands whose reply the host never reads (a lossy link's): the board took the
        command, the host steps that row with the position extrapolated from the two rows
        before (:mod:`hapsim.host.host_clock`'s estimate) and flags it
        ``FLAG_ESTIMATED``.

    Returns
    -------
    tuple
        ``(columns, driver, board)``: telemetry columns (``time`` [s], ``position`` [m],
        ``force`` [N], ``seq``, ``flags``, ``late``, ``force_seq``, ``status``), shape
        (n,); the :class:`hapsim.drivers.hapkit_serial.HapkitSerial` whose replies they
        are (its ``loop_delay`` and ``own_tick`` set, no hold marked; ``tick_moved`` what
        the probe at a run's stop would find, :meth:`hapsim.drivers.tick_align.
        TickAligned.end_probe`); the board.
    """
    from hapsim.drivers.hapkit_serial import HapkitSerial
    sc = scene
    drv = HapkitSerial(levels=levels, count_m=count_m)
    drv.loop_delay = int(sc.device.delay)
    drv.mistimed_seqs = set()
    drv.own_tick = True                        # the sketch keeps its tick (simulated)
    board = HapkitSerialDevice(device or sc.device, sc.rate_hz, sc.excitation, clock="wall",
                               levels=levels, render_s=render_s, count_m=count_m,
                               clock_ppm=clock_ppm)
    dec = drv.decoder()
    T, tick = sc.period, FIRMWARE_TICK_S             # (the host's count of a tick)
    late = dict(read_late or {})

    lost = {int(j) for j in lost_replies}
    seen: list = []

    def command(j: int, f: float) -> float:
        now = j * T + (phase + float(late.get(j, 0.0))) * tick
        x = dec.feed(board.feed(drv.encode_force(f), now))[-1]
        if j in lost and len(seen) >= 2:
            x = 2.0 * seen[-1] - seen[-2]            # the reply never read: the estimate
        seen.append(x)
        return x

    cols = offline_record(sc, drv, command, n, lambda k: k * T)
    # the probe at the run's stop (TickAligned.end_probe), right after the last command:
    # the board's boundary against the host's nominal grid from time 0, folded into half
    # a tick either way (its fit taken as exact)
    walk = n * T / tick - n * T / board.TICK_S
    # and the board's rate from the stop's two groups of placements (the walk's whole
    # ticks: walk_from_placements), exact
    drv.tick_moved = {"moved": (walk + 0.5) % 1.0 - 0.5, "seconds": n * T, "found": True,
                      "walk": walk, "walk_rate": walk, "walk_sd": 0.0,
                      "rate_ppm": walk / (n * T / tick) * 1e6}
    if lost:
        from hapsim.drivers.base import FLAG_ESTIMATED
        for j in lost:
            if 2 <= j < n:
                cols["flags"][j] |= FLAG_ESTIMATED
    return cols, drv, board

"""Mocks of the driver protocols' devices, byte for byte, on a pseudo-terminal.

The physics is the mock device's (:class:`hapsim.emulated.mock.MockPhysics`: exact ZOH,
optional Coulomb friction, noise); the bytes are the device's protocol. The device answers
each host packet: it applies the force of the packet ``d`` packets back (the scene's
``device.delay``; zero before that), advances one period, and replies with one record of
the new position -- so the host's clock paces it (the protocols are host-clocked). A
packet that does not decode is dropped (the force last applied is held). What a silence
does is each firmware's own rule (the FireFader ``.ino`` disables its force after 0.1 s;
the Haply board and the Hapkit sketch have no watchdog and hold it). Seeded byte loss and
corruption in either direction (:class:`ByteFaults`) test the host against a lossy link.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import sys
import time
from collections import deque

from hapsim.device_model import MockPhysics
from hapsim.spawn import PtyChild

__all__ = ["FireFaderDevice", "HaplyDevice", "HapkitSerialDevice", "ByteFaults", "serve",
           "WallClock", "WALL_CLOCK_MOCKS",
           "EmbeddedDriverMock", "firefader_offline_loop", "main"]

#: The drivers whose mock keeps its own time (``clock="wall"``) unless a run asks for
#: lockstep by name (``--lockstep``).
WALL_CLOCK_MOCKS = ("firefader", "hapkit-serial", "haply")


class _Actuated:
    """The physics side shared by the driver mocks: delay, clamp, and the device's clock.

    Two clocks (``clock``):

    - ``"wall"``: the device keeps its own time (:class:`WallClock`): its physics runs
      with the monotonic time :func:`serve` gives each packet, holding the last force
      while the host is silent or late, as a board does. A packet's force takes effect
      when it arrives plus the latency that brings the loop to the device's delay
      (:attr:`extra_latency_s`); the sample a reply carries is taken when its packet
      arrives.
    - ``"lockstep"`` (named, for deterministic tests): one period per command; the force
      of the packet ``delay`` packets back is applied over it.

    Parameters
    ----------
    device : hapsim.scene.Device
        Mass (or inertia), friction, delay and imperfections of the driven axis.
    rate_hz : float
        Period the host runs at [Hz] (lockstep: one period per command).
    excitation : hapsim.scene.Excitation, optional
        Initial displacement / velocity / hand force.
    limit : float
        The device's own force clamp [N] (or [N m]); the device section's is also applied.
    seed : int
        Sensor-noise seed.
    clock : {"wall", "lockstep"}
        The device's clock (above).

    Attributes
    ----------
    applied : list of float
        Forces applied per command (for tests).

    Raises
    ------
    ConfigError
        An unknown ``clock``.
    """

    #: The delay [periods] a host-clocked board on the wall clock has by itself: the
    #: sample of a reply is taken when the packet arrives, and the force computed from it
    #: arrives with the next packet, one period later.
    natural_delay = 1.0

    def __init__(self, device, rate_hz, excitation, limit, seed, clock="lockstep"):
        from hapsim.errors import ConfigError
        if clock not in ("wall", "lockstep"):
            raise ConfigError(f"unknown clock {clock!r}; valid: wall, lockstep", key="clock")
        self.clock = clock
        self.physics = MockPhysics(device, rate_hz, excitation, seed=seed)
        self.delay = int(device.delay)
        self.limit = min(float(device.force_limit), float(limit))
        self._fifo: deque = deque([0.0] * self.delay)
        self.applied: list = []
        self.held = 0.0
        self.clamped = 0
        self.last_command = 0.0
        self.wall = WallClock(self.physics) if clock == "wall" else None
        #: Latency [s] added to each force on the wall clock: what brings a board whose
        #: own delay is :attr:`natural_delay` to the scene's (never negative: a board is
        #: not faster than its protocol).
        self.extra_latency_s = (max(0.0, float(device.delay) - self.natural_delay)
                                / float(rate_hz))

    def apply(self, force, now: float | None = None) -> None:
        """Lockstep: queue ``force``, apply the one due (``delay`` commands back), advance a
        period. Wall clock: run the physics to ``now`` [s], then the force takes effect at
        ``now + extra_latency_s``. ``None``: this command changes no force (the one held
        goes on)."""
        if force is not None:
            self.last_command = force
            if not math.isfinite(force):
                force = 0.0                 # a corrupted float is no reason to push hard
        if self.wall is not None:
            self.wall.run_to(now)
            self.held = self.wall.held
            if force is None:
                return
            if abs(force) > self.limit:
                force = math.copysign(self.limit, force)
                self.clamped += 1
            self.applied.append(force)
            self.wall.schedule(now + self.extra_latency_s, force)
            return
        self._fifo.append(force)
        due = self._fifo.popleft()
        if due is None:
            due = self.held
        if abs(due) > self.limit:
            due = math.copysign(self.limit, due)
            self.clamped += 1
        self.held = due
        self.applied.append(due)
        self.physics.advance(due)

    def commands(self) -> int:
        """Force commands applied so far."""
        return len(self.applied)

    def held_from_now(self) -> float:
        """Lockstep: the force the device holds over the coming period [N], the head of
        its delay queue (clamped; the one held goes on where a queued command set none)
        -- what a firmware that reports "the force applied" says at the instant it read
        the position it sends (the wall clock's reply takes it from its schedule)."""
        due = self._fifo[0] if self._fifo else None
        if due is None:
            return self.held
        if not math.isfinite(due):
            return 0.0
        return math.copysign(self.limit, due) if abs(due) > self.limit else due

    def settles_on(self) -> float:
        """The force the device holds once the commands in its delay queue are applied
        (the last one that sets a force), [N]: what it is left with when the host is gone."""
        if self.wall is not None:
            return self.wall.settles_on()
        for f in reversed(self._fifo):
            if f is not None:
                return 0.0 if not math.isfinite(f) else max(-self.limit, min(self.limit, f))
        return self.held

    def apply_now(self, force: float) -> None:
        """The device sets ``force`` itself, at once (a firmware's silence rule): the queue
        is emptied too."""
        self._fifo = deque([None] * self.delay)
        self.held = force
        if self.wall is not None:
            self.wall.set_now(force)
            return
        self.physics.hold_now(force)

    def idle(self, silent_s: float) -> bytes:
        """The host has been silent ``silent_s`` [s]; by default nothing happens (the
        device holds its force: no watchdog)."""
        return b""

    #: From the end of a command read to the end of its answer on the wire [s]: what
    #: :func:`serve` waits before writing the answer (0: at once, a USB device's time).
    reply_delay_s = 0.0


class WallClock:
    """A device's own time: its physics integrated exactly over the real time between
    events, holding the force in effect (a board's motor holds its last PWM duty).

    Events are the packets' arrival times and the times their forces take effect; the
    physics is stepped from one to the next by :meth:`MockPhysics.advance_interval`, cut
    at the period boundaries (the hand force is per period).

    Parameters
    ----------
    physics : hapsim.device_model.MockPhysics
        The device's plant (``hold: zoh``).

    Attributes
    ----------
    t : float
        The device's time the physics has reached [s] (0 at the first packet's clock).
    held : float
        The force in effect [N].
    """

    def __init__(self, physics) -> None:
        self.physics = physics
        self.t = 0.0
        self.held = 0.0
        #: The largest |position| the physics reached [m] (or [rad]): the true excursion,
        #: whatever the host believes.
        self.excursion = abs(physics.x)
        self._due: deque = deque()       # (time [s], force [N]) not yet in effect

    def schedule(self, at: float, force: float) -> None:
        """The force ``force`` [N] takes effect at ``at`` [s] (in time order: a later
        packet's force never takes effect before an earlier one's)."""
        if self._due and at < self._due[-1][0]:
            at = self._due[-1][0]
        self._due.append((float(at), float(force)))

    def set_now(self, force: float) -> None:
        """The device sets its force itself, at once (a firmware's silence rule); what was
        due is dropped."""
        self._due.clear()
        self.held = float(force)

    def settles_on(self) -> float:
        """The force in effect once everything due has taken effect [N]."""
        return self._due[-1][1] if self._due else self.held

    def run_to(self, now: float) -> None:
        """Integrate the physics to ``now`` [s] (nothing when ``now`` is not later).

        Raises
        ------
        ValueError
            ``now`` is not finite (a wall-clock device needs the packet's time).
        """
        if not math.isfinite(now):
            raise ValueError("a device on the wall clock needs the time of each packet")
        ph = self.physics
        T = ph.period
        due = self._due
        while self.t < now:
            boundary = (ph.n + 1) * T
            nxt = min(now, boundary)
            if due and due[0][0] < nxt:
                nxt = max(due[0][0], self.t)
            ph.advance_interval(nxt - self.t, self.held)
            self.t = nxt
            if abs(ph.x) > self.excursion:
                self.excursion = abs(ph.x)
            if nxt >= boundary:
                ph.end_period()
            while due and due[0][0] <= self.t:
                self.held = due.popleft()[1]
        while due and due[0][0] <= self.t:
            self.held = due.popleft()[1]


class FireFaderDevice(_Actuated):
    """A FireFader whose fader A is the mock device's moving mass, running the published
    firmware's loop (``Hardware/FireFader/Firmware/haptics_firmware/haptics_firmware.ino``
    of eberdahl/Open-Source-Haptics-For-Artists, commit 6bbe9cd, E. Berdahl 2010-2013), an
    older copy of it, or the older ``.pde``.

    ``.ino`` (the default): the board hunts for a 127, takes the next two bytes as the
    forces of faders A and B *whatever they are* (a 127 or a -128 included), and runs a pass
    once no byte is waiting (``loop``, lines 283-315): packets that waited are merged, the
    last counts. The pass sets the motor to ``2 fA`` of the PWM's 254, or 0 while the
    force-enable filter ``e`` is below 20 (``setPWM``, lines 188-216), samples the fader,
    answers with one record, then updates the motor's heat estimate ``h <- (16383 h >> 14)
    + (pwm >> 5)`` (signed, lines 366-368) and the enable ``e <- (31 e >> 5) + 5 [4 < pot <
    251 and h >> 10 < 40 and touch > 30]`` (lines 380-382; touch filtered ``c <- (7 c >> 3)
    + sense``, lines 227-255): from power-on, or after about 0.1 s without a byte (65000
    idle polls, lines 264-277, which also zero the motor), the force is off for 5 passes
    (:func:`hapsim.drivers.firefader.pass_pwm`, :func:`~hapsim.drivers.firefader.enable_step`).
    ``.ino-scaled``: the copy in ``haptics_firmware_old_lesssensitive_capsensing_level``,
    whose ``setPWM`` scales by ``(e - 1) / 128`` (line 204) instead of gating.
    ``.pde``: no enable, no heat, no silence rule: each force byte is applied as it
    arrives, and records stream out on every pass whether asked or not.

    Time, ``clock="wall"`` (the default): the board keeps its own time. Its fader is
    integrated exactly over the real time between events (:class:`WallClock`), the motor
    holding its PWM duty whatever the host does. A pass starts when a packet has come and
    no byte waits (``loop``, lines 292-315), or when the previous pass ends, whichever is
    later; it sets the PWM at once (``setPWM``, lines 320-321), reads pot A ``adc_s``
    later (after the two capacitive senses, 175 us each, lines 324-325, the two current
    reads, 75 us each, lines 328-330, and pot B, 150 us, line 341: pot A's eight
    conversions, line 343, end ~0.8 ms into the pass; :data:`ADC_S` from the packet, the
    issue's measured board) and its record's last byte leaves ``reply_s`` after the
    packet (the 7 bytes at 57600 baud, 1.22 ms, line 103, which ``Serial.flush``, line
    358, waits out: :data:`REPLY_S`). Bytes that come during a pass wait for the next
    (they are merged, the last packet counts). The silence rule runs on the same clock:
    ``waitForSerialInput`` (lines 264-277) counts 65000 polls, about
    :data:`hapsim.drivers.firefader.SILENCE_S`, while no byte waits, then zeroes the
    enable and both motors; so a host silent longer than that from the end of a pass (or
    from its last byte) finds the force off from that instant on, and the next 5 passes
    off. The loop's own delay is ``1 - adc_s / T`` periods (the force set at the packet,
    the pot read ``adc_s`` later): a scene stating more delays each force by the rest
    (:attr:`_Actuated.extra_latency_s`), never less.

    Time, ``clock="lockstep"`` (named, for deterministic tests): the physics advances one
    period per host write (one host tick: the host's time, which goes on whether the
    firmware runs a pass or not); a write that ends in no pass (its start byte lost, a
    packet waiting for a byte) holds the motor's PWM over its period. The silence rule
    counts those periods too: host writes of which no byte arrived (the link lost them
    all), :data:`hapsim.drivers.firefader.SILENCE_S` of them in a row, zero the enable
    and the motor (:attr:`silent_ticks`); the wall clock is never the device's time
    here (:func:`serve` does not call :meth:`idle` with the time a slow host took:
    before, a lockstep mock whose host was descheduled 0.1 s took the wall clock's
    silence for its own, and its record was another on a loaded host).

    A value byte lost makes the firmware take the next packet's 127 as fader B's
    force and swallow that packet's forces (the pass applies fader A's byte of the damaged
    packet: the other fader's, 0, when a is lost; a, when b is).

    End stops: with ``travel`` the fader's position is held within
    ``[stop_low, stop_low + travel]`` (an inelastic stop: the velocity is zeroed there);
    the pot reads ``CENTRE + x / metres_per_count`` clipped to 0..254.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    full_scale : float
        Force at 127 counts with the enable on [N] (the hardware's: the host may believe
        another).
    metres_per_count : float
        The fader's position per pot count [m] (the hardware's).
    firmware : {"ino", "ino-scaled", "pde"}
    touch : bool
        A hand on the fader (capacitive sense 10 per pass, else 1).
    boot_s : float
        The Nano's bootloader time after the port opens [s]: bytes before it are lost.
    pass_time : bool
        ``.ino``: the record leaves after the firmware's pass, as on the board (wall
        clock: ``reply_s`` after the packet; lockstep: :attr:`reply_delay_s` = the 3-byte
        packet's wire time, a pty delivers it at once, the pass's reads,
        :data:`hapsim.drivers.firefader.PASS_READS_S`, and the 7-byte record's wire time
        at 57600 baud, 2.99 ms; packets that come meanwhile wait and are merged into the
        next pass); False: at once (wall clock: at the pot's read).
    travel : float, optional
        The travel between the end stops [m] (None: no stops).
    stop_low : float, optional
        The low end stop's position [m] (default ``-travel / 2``).
    adc_s : float, optional
        The board's own sub-sample timing [s]: the pass sets the PWM when the packet has
        come and reads pot A ``adc_s`` later (the ``.ino``'s ``loop``: ``setPWM`` first,
        then the capacitive sense, currents and pot B, ~1.1 ms, lines 295-317), so the
        fader holds the previous packet's force until the new packet, then the new one
        until the read. None (the default): the scene's ``device.delay`` sets both (its
        whole part as packets of delay, its fraction as the split hold of
        :class:`hapsim.device_model.MockPhysics`); given, the board ignores the scene's
        delay (no queue: the ``.ino`` has none) and the loop's delay *is* ``1 -
        adc_s / T`` periods (:mod:`hapsim.analysis.subsample`, the sensor-side delay).
        On the wall clock None means :data:`ADC_S` (the board's), the scene's delay
        adding a latency to the force when it states more than ``1 - adc_s / T``.
    reply_s : float, optional
        Wall clock: from the packet to its record's last byte on the wire [s] (default
        :data:`REPLY_S`); at least ``adc_s``.
    clock : {"wall", "lockstep"}
        The board's clock (above; :class:`_Actuated`).

    Attributes
    ----------
    decoder : PacketDecoder
        Its counters are the device's view of bad bytes (the ``.pde``'s parser; the
        ``.ino``'s counts ``frames`` and the ``skipped`` bytes it hunted over).
    enable, heat, cap : int
        The firmware's filter states.
    host_ticks : int
        Host writes seen (each one period; lockstep).
    ready_at : float
        Wall clock: the board's time [s] its last record has left at (:func:`serve`
        writes it then).
    silences : list of float
        The board's times [s] its silence rule zeroed the force at (lockstep: host ticks
        times the period, from the first write).
    silent_ticks : int
        Lockstep: host writes in a row of which no byte arrived.

    Raises
    ------
    ConfigError
        An unknown firmware or clock, a travel that is no positive length, an ``adc_s``
        outside the period or a ``reply_s`` before the read.
    """

    #: From the packet to pot A's read on the board [s]: the issue's measured FireFader
    #: (the ``.ino``'s reads before pot A's last conversion sum to ~0.8 ms of the pass by
    #: its comments, lines 324-343; the pass starts when the packet's last byte is in).
    ADC_S = 1.1e-3
    #: From the packet to the record's last byte on the wire [s]: the issue's measured
    #: board (the read, pot A's remaining conversions and the 7-byte record's 1.22 ms at
    #: 57600 baud, which ``Serial.flush`` waits out, line 358).
    REPLY_S = 2.5e-3

    def __init__(self, device, rate_hz: float, excitation=None, *, full_scale: float = 0.39,
                 metres_per_count: float | None = None, firmware: str = "ino",
                 touch: bool = True, boot_s: float = 0.0, pass_time: bool = True,
                 travel: float | None = None, stop_low: float | None = None,
                 adc_s: float | None = None, reply_s: float | None = None,
                 clock: str = "wall", seed: int = 0) -> None:
        import dataclasses

        from hapsim.drivers import firefader as ff
        from hapsim.errors import ConfigError
        if firmware not in ("ino", "ino-scaled", "pde"):
            raise ConfigError(f"unknown FireFader firmware {firmware!r}; valid: ino, "
                              "ino-scaled, pde", key="firmware")
        self._ff = ff
        wall = clock == "wall"
        if pass_time and firmware != "pde" and not wall:
            self.reply_delay_s = (3 + 7) * 10 / 57600 + ff.PASS_READS_S
        self.full_scale = float(full_scale)
        self.mpc = float(metres_per_count or ff.METRES_PER_COUNT)
        self.firmware = firmware
        self.touch = bool(touch)
        self.boot_s = float(boot_s)
        if travel is not None and not (math.isfinite(travel) and travel > 0):
            raise ConfigError(f"must be a positive length [m], got {travel!r}", key="travel")
        self.stops = (None if travel is None else
                      (float(-travel / 2 if stop_low is None else stop_low),
                       float((-travel / 2 if stop_low is None else stop_low) + travel)))
        self.adc_s = None if adc_s is None else float(adc_s)
        T = 1.0 / float(rate_hz)
        if self.adc_s is not None:
            if not (math.isfinite(self.adc_s) and 0.0 < self.adc_s < T):
                raise ConfigError(f"must be a time inside the period (0, {T:g}) [s], got "
                                  f"{adc_s!r}", key="adc_s")
            # the board's own timing: no queue; over the time from one read to the next
            # the fader holds the old force for T - adc_s, the new one for adc_s: the
            # split hold of a delay 1 - adc_s / T (0 whole periods)
            device = dataclasses.replace(device, delay=1.0 - self.adc_s / T)
        elif wall:
            self.adc_s = self.ADC_S if firmware != "pde" else 0.0
        if wall:
            rs = (self.REPLY_S if reply_s is None else float(reply_s)) if pass_time \
                else self.adc_s
            if firmware == "pde":
                rs = 0.0
            if not (math.isfinite(rs) and rs >= self.adc_s):
                raise ConfigError(f"must be a time [s] not before the pot's read "
                                  f"({self.adc_s:g} s), got {reply_s!r}", key="reply_s")
            self.reply_s = rs
            # the loop's own delay: the force at the packet, the pot adc_s later
            self.natural_delay = 1.0 - self.adc_s / T
        super().__init__(device, rate_hz, excitation, math.inf, seed, clock=clock)
        self.decoder = ff.PacketDecoder()
        self.enable = 0
        self.heat = 0
        self.cap = 0
        self.passes = 0
        self.merged = 0
        self.pwm = 0
        self.enables: list = []
        self.host_ticks = 0
        self.silent_ticks = 0
        self._state = 0                       # 0 hunting a 127, 1 byte A next, 2 byte B
        self._fa = self._fb = 0
        self._ready = None                    # a packet read, its pass not run yet
        self._owed = 0                        # host ticks not yet advanced
        self.ready_at = 0.0
        self.silences: list = []
        self._busy_until = 0.0                # wall clock: the pass running ends then
        self._quiet_from = 0.0                # wall clock: no byte waiting since then
        self._last_now = 0.0

    def position_count(self) -> int:
        """Fader A's reading: the sampled position in counts from the centre, 0..254."""
        ff = self._ff
        c = ff.CENTRE + round(self.physics.sample() / self.mpc)
        return int(min(max(c, 0), ff.POSITION_MAX))

    def _force(self, pwm: int) -> float:
        return pwm / 254.0 * self.full_scale

    def _advance(self, force) -> None:
        """One period (:meth:`_Actuated.apply`), the end stops enforced."""
        self.apply(force)
        if self.stops is not None:
            ph = self.physics
            lo, hi = self.stops
            if ph.x <= lo or ph.x >= hi:
                ph.x = min(max(ph.x, lo), hi)
                ph.v = 0.0

    def _run_to(self, t: float) -> None:
        """Wall clock: the fader integrated to the board's time ``t`` [s], the motor's
        force held, the end stops enforced at each period's end (and at ``t``)."""
        w = self.wall
        T = self.physics.period
        while w.t < t:
            w.run_to(min(t, w.t + T))
            if self.stops is not None:
                ph = self.physics
                lo, hi = self.stops
                if ph.x <= lo or ph.x >= hi:
                    ph.x = min(max(ph.x, lo), hi)
                    ph.v = 0.0
        self.held = w.held

    def _silence(self, now: float) -> None:
        """Wall clock: the ``.ino``'s silence rule up to the board's time ``now`` [s]: no
        byte waiting for :data:`hapsim.drivers.firefader.SILENCE_S` zeroes the enable and
        the motor at that instant (``waitForSerialInput``, lines 264-277)."""
        if self.firmware == "pde":
            return
        at = self._quiet_from + self._ff.SILENCE_S
        if now > at and (self.enable or self.pwm or self.wall.settles_on()):
            self._run_to(at)
            self.enable = 0
            self.pwm = 0
            self.apply_now(0.0)
            self.silences.append(at)

    def _pass(self, count_a: int, ticks: int, start: float | None = None) -> bytes:
        """One pass of the firmware's loop for a packet whose force byte A is ``count_a``
        (signed): lockstep, over ``ticks`` host periods (the ones before its last held);
        wall clock, starting at the board's time ``start`` [s]."""
        ff = self._ff
        if self.firmware == "pde":
            self.pwm = 2 * count_a
        else:
            self.pwm = ff.pass_pwm(count_a, self.enable, self.firmware == "ino-scaled")
        f = self._force(self.pwm)
        if self.wall is not None:
            self._run_to(start)
            self.apply(f, now=start)          # setPWM: the duty from the pass's start
            self._run_to(start + self.adc_s)  # ... held to pot A's read
            self._busy_until = self.ready_at = start + self.reply_s
            self._quiet_from = self.ready_at
        else:
            for _ in range(ticks - 1):        # host ticks merged into this pass
                self._advance(None)
            self._advance(f)
        pot = self.position_count()
        self.enables.append(self.enable)
        if self.firmware != "pde":
            self.cap = ((self.cap * 7) >> 3) + (10 if self.touch else 1)
            self.enable, self.heat = ff.enable_step(self.enable, self.heat, self.pwm, pot,
                                                    self.cap > 30)
            cap = min(self.cap, 254)
        else:
            cap = 0
        self.passes += 1
        return ff.encode_record(pot, ff.CENTRE, (0, 0, cap, 0))

    def step(self, count_a: int) -> bytes:
        """One packet: one pass of the firmware, one record."""
        return self._pass(count_a, 1)

    def _parse(self, b: int):
        """The ``.ino``'s reading of one byte: a completed packet ``(fA, fB)`` (signed) or
        None."""
        if self._state == 0:
            if b == 127:
                self._state = 1
            else:
                self.decoder.stats["skipped"] += 1
            return None
        v = b - 256 if b > 127 else b
        if self._state == 1:
            self._fa, self._state = v, 2
            return None
        self._state = 0
        self.decoder.stats["frames"] += 1
        return (self._fa, v)

    @staticmethod
    def host_writes(data: bytes) -> list:
        """The host's bytes of one read as its writes: a new one at each 127 (no force
        byte the host sends is 127); bytes before the first 127 continue a write already
        counted (the first element, possibly empty)."""
        out = [bytearray()]
        for b in data:
            if b == 127:
                out.append(bytearray())
            out[-1].append(b)
        return [bytes(w) for w in out]

    def feed(self, data: bytes, now: float = math.inf, writes=None) -> bytes:
        """Bytes from the host in (at ``now`` [s] since the port opened), the records out.

        Parameters
        ----------
        data : bytes
            What one read got (after the link's faults).
        now : float
            [s] since the port opened (the bootloader drops what comes before ``boot_s``).
        writes : list of bytes, optional
            ``data`` split into the host's writes as they came off the link (each after
            its faults; the first continues an earlier write, possibly empty): each
            write but the first is one host tick. Default: :meth:`host_writes` of
            ``data`` (exact for a clean link).

        Returns
        -------
        bytes
            The records of the passes run (``.ino``: at most one per read, after the last
            write: the bytes of a write still on the wire are not yet waiting, those of
            the later writes of one read are, and make the loop read on).
        """
        if now < self.boot_s:
            return b""                        # the bootloader has them
        if self.wall is not None:
            return self._feed_wall(data, now)
        if self.firmware == "pde":
            pk = self.decoder.feed(data)
            if not pk:
                return b""
            self.last_count = pk[-1][0]
            for _ in pk:
                self.apply(None)
            return b""
        if writes is None:
            writes = self.host_writes(data)
        ticks = len(writes) - 1
        self.host_ticks += ticks
        self._owed += ticks
        done = None
        last = len(writes) - 1
        for i, w in enumerate(writes):
            if w:
                self.silent_ticks = 0
            elif i > 0:
                # a host tick of which no byte arrived: the firmware's idle polls ran
                # over its period; SILENCE_S of them zero the enable and the motor
                self.silent_ticks += 1
                if (self.silent_ticks * self.physics.period >= self._ff.SILENCE_S - 1e-12
                        and (self.enable or self.pwm)):
                    self.enable = 0
                    self.pwm = 0
                    self.apply_now(0.0)
                    self.silences.append((self.host_ticks - ticks + i) * self.physics.period)
            for b in w:
                pk = self._parse(b)
                if pk is None:
                    continue
                if self._ready is not None:
                    self.merged += 1
                self._ready = pk
                if i == last and done is None:
                    done = pk                 # nothing waits: the loop ends, a pass runs
                    self._ready = None
        if done is None:
            return b""                        # no pass: the motor holds its PWM (the
            #                                   periods are advanced at the next pass)
        n, self._owed = max(self._owed, 1), 0
        return self._pass(done[0], n)

    def _feed_wall(self, data: bytes, now: float) -> bytes:
        """:meth:`feed` on the wall clock (class notes): the bytes came at the board's time
        ``now`` [s]; a pass runs when the last of them completes a packet (otherwise the
        firmware waits inside a packet, or hunts for a 127, and runs none)."""
        # (the silence rule runs from idle, when the emulator has seen the silence: bytes
        # it reads late because its own process was descheduled came in time for all it
        # knows, and a real board would have seen them as they came)
        self._last_now = max(self._last_now, now)
        if self.firmware == "pde":
            self._run_to(now)
            for pk in self.decoder.feed(data):
                self.last_count = pk[0]
                self.pwm = 2 * pk[0]
                self.apply(self._force(self.pwm), now=now)
            return b""
        end = None
        for b in data:
            pk = self._parse(b)
            end = pk
            if pk is None:
                continue
            if self._ready is not None:
                self.merged += 1
            self._ready = pk
        self._quiet_from = max(now, self._busy_until)
        if end is None:
            return b""
        self._ready = None
        return self._pass(end[0], 1, start=max(now, self._busy_until))

    def idle(self, silent_s: float) -> bytes:
        """The host has been silent for ``silent_s`` [s] since its last bytes: ``.ino``
        disables the force after 0.1 s (on the wall clock at the instant the firmware's
        polls ran out, :meth:`_silence`, once the emulator has seen the silence last that
        long: :func:`serve` calls this while no byte waits, every ``poll``); ``.pde``
        streams a record (one pass) on every call."""
        if self.wall is not None:
            now = self._last_now + silent_s
            if self.firmware == "pde":
                self._run_to(now)
                self.passes += 1
                return self._ff.encode_record(self.position_count(), self._ff.CENTRE,
                                              (0, 0, 0, 0))
            self._silence(now)
            return b""
        if self.firmware == "pde":
            return self._pass(getattr(self, "last_count", 0), 1)
        if silent_s > 0.1 and (self.enable or self.pwm):
            self.enable = 0
            self.pwm = 0
            self.apply_now(0.0)
        return b""


class HaplyDevice(_Actuated):
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
    until the next write (no watchdog: :class:`_Actuated`, ``natural_delay`` 1). A set-up
    costs :data:`SETUP_S`: ``initialize_encoder`` (``Haply_M3_Firmware_V1_5.h``) builds a
    ``new Encoder(...)``, whose constructor waits ``delayMicroseconds(2000)`` for the
    pins' R-C filter (``Arduino_Support_Libraries/Encoder/Encoder.h``, ``Encoder(uint8_t,
    uint8_t)``) before the count is written with the offset; the commands after it wait,
    the joint does not. A pass begins at least :data:`PASS_S` after the one before
    (``loop``: ``if(micros() - lastPublished >= 50)``, ``Haply_M3_Firmware_V1_5.ino`` line
    61) and takes one command: the 278 resets of 556 zero bytes take 14 ms of passes, the
    torque held meanwhile. A single ``read()`` of a byte not arrived gives 255
    (:class:`CommandDecoder` with ``absent=255``). ``clock="lockstep"``: each write is one
    period.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    cpr : float
        The encoder's real counts per revolution (the set-up's resolution only scales
        counts to degrees: a wrong one is a wrong angle).
    motor_sign : {1, -1}
        The wiring of motor 1 against encoder 1: the sign of the count's motion under a
        positive torque when both direction bytes are 0 (firmware CW). Each direction
        byte of 1 flips its side (the motor's direction pin, the encoder's pins), so
        the host's bytes drive the joint the right way when ``(-1)^(motor byte + encoder
        byte)`` equals it, and as positive feedback otherwise.

    Attributes
    ----------
    decoder : CommandDecoder
    torque : float
        The torque motor 1 holds [N m].
    """

    #: What a set-up takes on the board [s]: the Encoder constructor's 2 ms wait.
    SETUP_S = 2e-3
    #: The shortest time between two passes of the firmware's ``loop()`` [s] (one command
    #: each): ``micros() - lastPublished >= 50``.
    PASS_S = 50e-6

    def __init__(self, device, rate_hz: float, excitation=None, *, cpr: float = 4880.0,
                 resolution: float | None = None, seed: int = 0, motor_sign: int = 1,
                 clock: str = "wall") -> None:
        from hapsim.drivers import haply as hp
        from hapsim.emulated.haply_firmware import CommandDecoder
        from hapsim.errors import ConfigError
        if motor_sign not in (1, -1):
            raise ConfigError(f"must be 1 or -1, got {motor_sign!r}", key="motor_sign")
        self.motor_sign = int(motor_sign)
        self._hp = hp
        super().__init__(device, rate_hz, excitation, hp.MAX_TORQUE, seed, clock=clock)
        # the firmware's single reads of an empty buffer: 255 (CommandDecoder notes)
        self.decoder = CommandDecoder(absent=255)
        self.cpr = float(resolution or cpr)
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
        binary32 on the wire)."""
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
        t = max(now, self._busy_until) if wall else now
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


class HapkitSerialDevice(_Actuated):
    """A Hapkit running the WHC2017 sketch with the host-force function: its handle is the
    mock device's moving mass.

    Its time, ``clock="wall"`` (the default): the sketch runs a fixed 1 kHz tick on its
    own clock (:data:`TICK_S`, from power-on: the board's time 0) and answers each
    command on the tick after it has come, with one 9-byte reply (the driver's reading of
    ``Hapkit_arduino.ino`` and ``Board.java``: :mod:`hapsim.drivers.hapkit_serial`, whose
    module notes this follows; the sketch's source is not in this project's reference
    library, so the order within a tick is taken as the driver states it: the handle read
    at the tick, the command's force applied from it). The handle is integrated exactly
    over the real time between ticks that change something (:class:`WallClock`), the
    force held whatever the host does: the sketch has no silence rule. The reply's last
    byte leaves the 9 bytes' wire time at 57600 baud (:data:`REPLY_WIRE_S`, 1.56 ms)
    after its tick. Its loop delay is one host period (the read and the force at the same
    tick, the force computed from that read one command later), to the tick's grid; a
    scene stating more delays each force by the rest (:attr:`_Actuated.extra_latency_s`).
    ``clock="lockstep"`` (named, for deterministic tests): one period per command, the
    reply at once.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    force_limit : float
        The firmware's force clamp [N].
    clock : {"wall", "lockstep"}
        The board's clock (above).

    Attributes
    ----------
    decoder : CommandDecoder
    ready_at : float
        Wall clock: the board's time [s] its last reply has left at (:func:`serve` writes
        it then).
    """

    #: The sketch's control tick [s] (1 kHz).
    TICK_S = 1e-3
    #: A 9-byte reply's time on the wire at 57600 baud, 10 bits a byte [s].
    REPLY_WIRE_S = 9 * 10 / 57600

    def __init__(self, device, rate_hz: float, excitation=None, *, force_limit: float = 2.0,
                 clock: str = "wall", seed: int = 0) -> None:
        from hapsim.drivers import hapkit_serial as hk
        self._hk = hk
        self._phases: list = []                       # where in its tick each came
        super().__init__(device, rate_hz, excitation, force_limit, seed, clock=clock)
        self.decoder = hk.CommandDecoder()
        self.ready_at = 0.0
        self._tick = -1                               # the last tick that took a command

    def feed(self, data: bytes, now: float = math.inf) -> bytes:
        """Bytes from the host in (at the board's time ``now`` [s], needed on the wall
        clock), one 9-byte reply per command out."""
        out = b""
        wall = self.wall is not None
        for f in self.decoder.feed(data):
            if wall:
                # the tick after the command came (several in one read: one tick each)
                k = max(math.floor(now / self.TICK_S) + 1, self._tick + 1)
                self._phases.append(now / self.TICK_S - math.floor(now / self.TICK_S))
                self._tick = k
                tick = k * self.TICK_S
                self.wall.run_to(tick)
                x = self.physics.sample()             # the handle read at the tick
                self.apply(f, now=tick)               # the force from the tick on
                out += self._hk.reply_packet(self.decoder.function, x,
                                             self.wall.settles_on())
                self.ready_at = tick + self.REPLY_WIRE_S
                continue
            self.apply(f)
            # the sketch replies with the handle it read and the force it applies from
            # that tick on (as on the wall clock): the queue's head, not the force of the
            # period just ended
            out += self._hk.reply_packet(self.decoder.function, self.physics.sample(),
                                         self.held_from_now())
        return out

    def idle(self, silent_s: float) -> bytes:
        """The sketch has no silence rule: it holds its force."""
        return b""

    @property
    def tick_arrivals(self) -> dict:
        """Where in the sketch's tick the commands came (wall clock), for the host's
        timing: ``commands``; ``near_boundary``, those within a tenth of a tick of the
        tick's end or start (a command coming there is taken at one tick or the next by
        a jitter of 0.1 ms: a sample interval a tick off the host's period);
        ``median_phase``, the median arrival phase [fraction of a tick, 0 at a tick]."""
        ph = sorted(self._phases)
        near = sum(1 for p in ph if p < 0.1 or p > 0.9)
        return {"commands": len(ph), "near_boundary": near,
                "median_phase": ph[len(ph) // 2] if ph else None}


class ByteFaults:
    """Seeded byte faults on a driver mock's link, in both directions.

    Parameters
    ----------
    spec : dict, optional
        Probabilities per byte: ``drop_rx`` / ``corrupt_rx`` (host -> device: a byte lost,
        or one bit of it flipped), ``drop_tx`` / ``corrupt_tx`` (device -> host); ``seed``.

    Attributes
    ----------
    counts : dict
        Bytes dropped and corrupted per direction.
    """

    KEYS = ("drop_rx", "corrupt_rx", "drop_tx", "corrupt_tx")

    def __init__(self, spec: dict | None = None) -> None:
        import numpy as np
        spec = dict(spec or {})
        self.p = {k: float(spec.get(k, 0.0)) for k in self.KEYS}
        self.on = any(self.p.values())
        self._rng = np.random.default_rng(int(spec.get("seed", 0)))
        self.counts = {k: 0 for k in self.KEYS}

    def _apply(self, data: bytes, drop: str, corrupt: str) -> bytes:
        if not self.on or not data:
            return data
        n = len(data)
        pd, pc = self.p[drop], self.p[corrupt]
        u = self._rng.random(n)
        bits = self._rng.integers(0, 8, n)
        out = bytearray()
        for k, b in enumerate(data):
            if u[k] < pd:
                self.counts[drop] += 1
                continue
            if u[k] < pd + pc:
                self.counts[corrupt] += 1
                b ^= 1 << int(bits[k])
            out.append(b)
        return bytes(out)

    def rx(self, data: bytes) -> bytes:
        """Host -> device bytes, after the faults."""
        return self._apply(data, "drop_rx", "corrupt_rx")

    def tx(self, data: bytes) -> bytes:
        """Device -> host bytes, after the faults."""
        return self._apply(data, "drop_tx", "corrupt_tx")


def serve(fd: int, dev, *, stop=None, faults: dict | None = None,
          poll: float = 0.02, handled=None) -> dict:
    """Serve ``dev`` on a byte stream until EOF (host closed) or ``stop()`` is true.

    Parameters
    ----------
    fd : int
        Master side of the pty.
    dev : FireFaderDevice, HaplyDevice or HapkitSerialDevice
        The device (``feed(bytes, now) -> bytes``, ``idle(silent_s) -> bytes``,
        ``decoder.stats``). What a silent host does to the force is the device's own rule
        (``idle``): the FireFader ``.ino`` disables it after 0.1 s, the Haply board and the
        Hapkit sketch hold it (no watchdog).
    stop : callable, optional
        Polled; serving ends when it returns True.
    faults : dict, optional
        :class:`ByteFaults` spec (seeded byte loss and corruption, both directions); also
        the test hook ``slow`` / ``slow_s``: each answer, with that probability (its own
        seeded draw, so the bytes lost are the same), is written ``slow_s`` [s] late, as
        a mock process on a loaded host is.
    poll : float
        Wait for bytes before ``idle`` is called [s].
    handled : hapsim.spawn.HandledBytes, optional
        A lockstep mock's account of the bytes it has handled, published after each read
        is answered (the host tells a slow mock from a lost packet by it, not by time).

    Returns
    -------
    dict
        ``packets`` (force commands applied), ``decoder`` counters, ``faults`` (bytes
        dropped and corrupted per direction), ``held_at_end`` [N] (the force the device
        is left holding when the host is gone, its delay queue applied), and the keys of
        :class:`hapsim.emulated.mock.MockStats` the run report prints (``ticks`` = packets,
        ``late``, ``overruns`` and ``watchdog_trips`` 0: the device is paced by the packets
        and has no watchdog; ``clamped``; ``last_applied`` [N]; ``saw_stop``: the last
        packet commanded zero force, which is all a STOP is in these protocols).
    """
    os.set_blocking(fd, False)
    fl = ByteFaults(faults)
    slow_p = float((faults or {}).get("slow", 0.0))
    slow_s = float((faults or {}).get("slow_s", 0.0))
    if slow_p > 0:
        import numpy as np
        slow_rng = np.random.default_rng([int((faults or {}).get("seed", 0)), 1])
    n_read = n_written = 0
    t0 = last = t_idle = time.monotonic()
    streams = getattr(dev, "firmware", "") == "pde"
    while not (stop and stop()):
        r, _, _ = select.select([fd], [], [], poll)
        out = b""
        if streams and time.monotonic() - t_idle >= poll:
            t_idle = time.monotonic()           # a streaming firmware's pass, asked or not
            out = dev.idle(t_idle - last)
        if not r:
            if not streams and getattr(dev, "clock", "wall") == "wall":
                # (a lockstep device's time is the commands: a silence of the wall clock
                # is a slow host, not the device's; it counts silent ticks itself)
                out = dev.idle(time.monotonic() - last)
        else:
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError:
                break
            if not data:
                break
            n_read += len(data)
            now = time.monotonic()
            last = now
            split = getattr(dev, "host_writes", None)
            if split is not None and not streams:
                # the link's faults per host write: a write is one host tick whatever the
                # faults leave of it (the device's time goes on)
                ws = [fl.rx(w) for w in split(data)]
                got = dev.feed(b"".join(ws), now - t0, writes=ws)
            else:
                got = dev.feed(fl.rx(data), now - t0)
            if got and dev.reply_delay_s > 0:
                # the device's pass and its answer's wire time (the host's bytes that come
                # meanwhile wait for the next pass)
                wait = now + dev.reply_delay_s - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            if got and getattr(dev, "wall", None) is not None and hasattr(dev, "ready_at"):
                # a board on its own clock answers when its pass has run (after a set-up's
                # wait, later than the bytes came)
                wait = t0 + dev.ready_at - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            out += got
        out = fl.tx(out)
        if out and slow_p > 0 and slow_rng.random() < slow_p:
            time.sleep(slow_s)                  # the test hook: a slow mock process
        while out:
            try:
                k = os.write(fd, out)
            except BlockingIOError:             # the host reads later: wait for room
                if stop and stop():
                    out = None
                    break
                select.select([], [fd], [], poll)
                continue
            except OSError:
                out = None
                break
            n_written += k
            out = out[k:]
        if out is None:
            break
        if handled is not None:
            handled.publish(n_read, n_written)
    n = dev.commands()
    extra = {}
    for k in ("merged", "passes", "firmware", "host_ticks", "frame_walk", "tick_arrivals"):
        if hasattr(dev, k):
            extra[k] = getattr(dev, k)
    if getattr(dev, "enables", None):
        extra["enable"] = dev.enables[-1]       # at the last pass (not after the host left)
        extra["passes_at_full_enable"] = sum(e == 129 for e in dev.enables)
    return {"packets": n, "decoder": dict(dev.decoder.stats), "faults": dict(fl.counts),
            "watchdog_trips": 0, "watchdog_at": [], "held_at_end": dev.settles_on(),
            "clock": getattr(dev, "clock", "lockstep"),
            "true_excursion": (dev.wall.excursion if getattr(dev, "wall", None) is not None
                               else None),
            "ticks": n, "late": 0, "overruns": 0, "clamped": dev.clamped,
            "last_applied": dev.held, "saw_stop": bool(n and dev.last_command == 0), **extra}


def firefader_offline_loop(scene, n: int = 900, *, lost=(), silence_at=None,
                           silence: float = 0.2, rx_drop=None):
    """The FireFader THS closed offline through hapsim's engine and the firmware's own loop
    (:class:`FireFaderDevice` with ``clock="lockstep"``, by name): deterministic, no pty, no
    real time.

    The host loop's arithmetic: row ``k`` is the record answering command ``k``, the force
    computed from it goes out with command ``k + 1``; a record that never came is stepped
    through with the position extrapolated from the last two records (``FLAG_ESTIMATED``),
    as :meth:`hapsim.drivers.transport.DriverTransport.estimate` does.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A scene with a device (its rate, delay, force limit and excitation).
    n : int
        Rows [samples].
    lost : iterable of int
        Rows whose record never came (device -> host loss).
    silence_at : int, optional
        The host is silent ``silence`` [s] before the command that follows that row.
    silence : float
        [s].
    rx_drop : dict of int to int, optional
        ``{row: byte}``: the packet sent after that row loses that byte (0 the start, 1
        fader A's, 2 fader B's) on its way to the firmware, which parses what is left (a
        row whose record then never comes is estimated).

    Returns
    -------
    tuple
        ``(columns, driver, applied)``: telemetry columns (``time`` [s], ``position`` [m],
        ``force`` [N], ``seq``, ``flags``, ``late``, ``force_seq``, ``status``), shape
        (n,); the :class:`hapsim.drivers.firefader.FireFader` (its ``loop_delay`` set);
        the force the mock applied over each row's period [N], shape (n,).
    """
    import numpy as np

    from hapsim.drivers.base import FLAG_ESTIMATED
    from hapsim.drivers.firefader import CENTRE, FireFader, RecordDecoder
    from hapsim.engine import Engine
    sc = scene
    drv = FireFader()
    drv.loop_delay = int(sc.device.delay)       # whole passes (the fraction: the physics)
    dev = FireFaderDevice(sc.device, sc.rate_hz, sc.excitation, clock="lockstep")
    for _ in range(drv.arming_records):
        dev.feed(drv.encode_force(0.0))
    eng = Engine(sc)
    T = sc.period
    dec = RecordDecoder()

    def record(b):
        r = dec.feed(b)
        return (r[-1][0] - CENTRE) * drv.position_scale if r else None

    x = record(dev.feed(drv.encode_force(0.0)))
    n0 = len(dev.applied)
    cols = {k: np.zeros(n) for k in ("time", "position", "force")}
    flags = np.zeros(n, np.uint8)
    xs, ss = [x, x], [-1, 0]
    lost = set(lost)
    t = 0.0
    rx_drop = dict(rx_drop or {})
    for k in range(n):
        cols["time"][k] = t
        if k in lost or x is None:
            lost.add(k)
            flags[k] = FLAG_ESTIMATED
            x_k = xs[-1] + (xs[-1] - xs[-2]) / (ss[-1] - ss[-2]) * (k - ss[-1])
        else:
            x_k = x
            xs.append(x)
            ss.append(k)
        cols["position"][k] = x_k
        f = min(max(eng.port_step(x_k), -sc.device.force_limit), sc.device.force_limit)
        cols["force"][k] = drv.applied_force(f)
        t += T
        if k == silence_at:
            dev.idle(silence)
            t += silence
        pk = drv.encode_force(f)
        if k in rx_drop:
            j = rx_drop[k]
            pk = pk[:j] + pk[j + 1:]
        x = record(dev.feed(pk, writes=[b"", pk]))      # one host write, one tick
    cols.update(seq=np.arange(n), flags=flags, late=np.zeros(n, np.uint8),
                force_seq=np.arange(n) - int(sc.device.delay), status=np.zeros(n, np.uint16))
    # the pass of command k + 1 moves the fader over row k's period
    return cols, drv, np.array(dev.applied[n0:n0 + n])




def main(argv=None) -> int:
    """Child-process entry: ``python -m hapsim.emulated.driver_mock --fd N --spec JSON --rate R``."""
    import argparse
    import dataclasses

    from hapsim.scene import Device, Excitation
    p = argparse.ArgumentParser(prog="hapsim.emulated.driver_mock")
    p.add_argument("--fd", type=int, required=True)
    p.add_argument("--spec", required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--report")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--options", default="{}")
    p.add_argument("--faults", default="{}")
    p.add_argument("--handled")
    a = p.parse_args(argv)
    opt = json.loads(a.options)
    spec = json.loads(a.spec)
    d = spec["device"]
    if d.get("force_limit") is None:
        d["force_limit"] = math.inf
    device = Device(**d)
    exc = spec["excitation"]
    fields = {f.name for f in dataclasses.fields(Excitation)}
    if exc.get("impulse"):
        from hapsim.scene import Impulse
        exc["impulse"] = Impulse(**exc["impulse"])
    excitation = Excitation(**{k: v for k, v in exc.items() if k in fields})
    kind = spec.get("driver", "firefader")
    cls = {"haply": HaplyDevice, "hapkit-serial": HapkitSerialDevice}.get(kind, FireFaderDevice)
    dev = cls(device, a.rate, excitation, seed=a.seed, **opt)
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    from hapsim.spawn import HandledBytes
    rep = serve(a.fd, dev, stop=lambda: flag["stop"], faults=json.loads(a.faults),
                poll=0.02 if getattr(dev, "firmware", "") != "pde" else 1.0 / a.rate,
                handled=HandledBytes(a.handled) if a.handled else None)
    if a.report:
        with open(a.report + ".partial", "w") as fh:
            json.dump(rep, fh)
        os.replace(a.report + ".partial", a.report)
    return 0


class EmbeddedDriverMock(PtyChild):
    """A driver mock in a child process on the master side of a new pty.

    Parameters
    ----------
    driver : str
        Driver name (``"firefader"``).
    device, excitation
        What the mock models (:class:`hapsim.scene.Device`, :class:`~hapsim.scene.Excitation`).
    rate_hz : float
        Host rate [Hz] (one period per packet).
    seed : int
        Sensor-noise seed.
    options : dict, optional
        The mock device's own keywords (:class:`FireFaderDevice`: ``full_scale``,
        ``metres_per_count``, ``firmware``, ``touch``, ``boot_s``; :class:`HaplyDevice`:
        ``cpr``, ``motor_sign``): the hardware, which the host's driver may describe wrongly.
    faults : dict, optional
        :class:`ByteFaults` spec (and :func:`serve`'s ``slow`` hook).

    Attributes
    ----------
    port : str
        The slave path to open.
    handled : hapsim.spawn.HandledBytes or None
        A lockstep mock's account of the bytes it has handled
        (``options["clock"]`` ``"lockstep"``, the default): for
        :class:`hapsim.drivers.transport.DriverTransport`; None on the wall clock.
    """

    handled = None

    def __init__(self, driver: str, device, excitation, rate_hz: float, *, seed: int = 0,
                 options: dict | None = None, faults: dict | None = None) -> None:
        import dataclasses

        from hapsim.errors import ConfigError
        if driver not in ("firefader", "haply", "hapkit-serial"):
            raise ConfigError(f"no mock for driver {driver!r}; valid: firefader, haply, "
                              "hapkit-serial",
                              key="--driver")
        master = self.open_pty("hapsim-drvmock-")
        spec = {"device": dataclasses.asdict(device), "excitation": dataclasses.asdict(excitation),
                "driver": driver}
        if not math.isfinite(spec["device"]["force_limit"]):
            spec["device"]["force_limit"] = None
        extra = []
        if (options or {}).get("clock", "lockstep") == "lockstep":
            from hapsim.spawn import HandledBytes
            self.handled = HandledBytes.create()
            extra = ["--handled", self.handled.path]
        self.start([sys.executable, "-m", "hapsim.emulated.driver_mock", "--fd", str(master), "--spec",
                    json.dumps(spec), "--rate", repr(float(rate_hz)), "--report",
                    self.report_path, "--seed", str(seed), "--options",
                    json.dumps(options or {}), "--faults", json.dumps(faults or {})]
                   + extra, master)

    def close(self) -> None:
        """As :meth:`hapsim.spawn.PtyChild.close`, and the handled account removed."""
        super().close()
        if self.handled is not None:
            self.handled.close(unlink=True)


if __name__ == "__main__":
    sys.exit(main())

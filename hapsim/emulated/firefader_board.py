"""The FireFader's board, byte for byte: the firmware's loop (``haptics_firmware.ino``, its
parser, the enable gate, the 0.1 s silence rule; the older streaming ``.pde``) driving the
handle's physics (:class:`hapsim.emulated.actuated.Actuated`), served on a pty by
:func:`hapsim.emulated.driver_mock.serve`.
"""

from __future__ import annotations

import math

from hapsim.drivers.firefader import HAND_PASSES
from hapsim.emulated.actuated import Actuated
from hapsim.option_values import option_value

__all__ = ["FireFaderDevice"]


class FireFaderDevice(Actuated):
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
    (:attr:`hapsim.emulated.actuated.Actuated.extra_latency_s`), never less.

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

    Fader B (``device_b``): the ``.ino`` drives both faders alike, each with its own
    enable filter and touch sense (``setPWM`` for motor B, line 321; ``forceBEnableLPF``,
    lines 383-385; ``capSenseLPFB``, line 325), so fader B is a second handle
    (:class:`hapsim.emulated.actuated.Actuated`, its own mass and friction) whose force is
    each packet's byte B, set in the same pass as A's, and whose pot is read just before
    pot A's (lines 339-343: "channel A is sampled last so that the feedback control delay
    for it is slightly lower"), :data:`POT_S` earlier: on the wall clock fader B's own
    loop delay is ``1 - (adc_s - POT_S) / T`` periods (0.7625 at 250 Hz, A's 0.725). Its
    heat estimate adds fader A's PWM, not B's (line 371, ``heatB + (signedForceA >>
    5)``: the firmware's, kept). The silence rule zeroes both (lines 264-277). Without
    ``device_b`` fader B stays at rest and reads the centre, as before.

    The hand (``hand``, for a measurement of several records on one board): a list of
    starts ``(xA, xB, vA, vB)`` [m, m/s]. Each time the host has been silent
    :data:`HAND_SILENCE_S` (it paused between records; the silence rule has zeroed the
    forces by then) the hand takes both faders to the next start and holds them still
    there while the enable climbs back (:data:`HAND_PASSES` passes); at the
    :data:`HAND_PASSES`-th pass it lets go, the faders moving at ``(vA, vB)``: that
    pass's record is the record's first row. A shorter silence (a host late) leaves the
    faders where they are, and so does the silence before the host's first bytes (the
    hand waits for a measurement to begin: a host that opens the port later than
    :data:`HAND_SILENCE_S` after the board started would otherwise find the first start
    taken and its records one start late).

    End stops: with ``travel`` the fader's position is held within
    ``[stop_low, stop_low + travel]`` (an inelastic stop: the velocity is zeroed there);
    the pot reads ``CENTRE + x / metres_per_count`` clipped to 0..254.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`hapsim.emulated.actuated.Actuated`.
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
        The board's clock (above; :class:`hapsim.emulated.actuated.Actuated`).
    device_b : hapsim.scene.Device, optional
        Fader B's mass, friction, delay and force limit (None: fader B at rest).
    hand : sequence of 4-tuples of float, optional
        The hand's starts ``(xA, xB, vA, vB)`` [m, m/s], one per silence (above).

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
    fader_b : hapsim.emulated.actuated.Actuated or None
        Fader B's handle (with ``device_b``): its physics, its clock, its force held.
    enable_b, heat_b, cap_b, pwm_b : int
        Fader B's enable, heat and touch filters and its PWM (0 without ``device_b``).
    adc_b_s : float
        Wall clock, with ``device_b``: from the packet to pot B's read [s].

    Raises
    ------
    ConfigError
        An unknown firmware or clock, a travel, ``full_scale`` or ``metres_per_count``
        that is no finite number > 0, a ``boot_s`` < 0, an ``adc_s`` outside the period
        or a ``reply_s`` before the read.
    """

    #: From the packet to pot A's read on the board [s]: the issue's measured FireFader
    #: (the ``.ino``'s reads before pot A's last conversion sum to ~0.8 ms of the pass by
    #: its comments, lines 324-343; the pass starts when the packet's last byte is in).
    ADC_S = 1.1e-3
    #: Pot B's reading ends this long before pot A's [s]: pot A's eight conversions
    #: ("This takes about 150 microseconds", ``.ino`` lines 341-343) come after pot B's.
    POT_S = 150e-6
    #: Passes the hand holds the faders still after a silence before it lets go: the run's
    #: convention (:data:`hapsim.drivers.firefader.HAND_PASSES`).
    HAND_PASSES = HAND_PASSES
    #: The host's silence after which the hand takes the faders to its next start [s]:
    #: longer than the silence rule and its doubt band
    #: (:data:`hapsim.drivers.firefader.SILENCE_DOUBT_S`).
    HAND_SILENCE_S = 0.3
    #: From the packet to the record's last byte on the wire [s]: the issue's measured
    #: board (the read, pot A's remaining conversions and the 7-byte record's 1.22 ms at
    #: 57600 baud, which ``Serial.flush`` waits out, line 358).
    REPLY_S = 2.5e-3

    def __init__(self, device, rate_hz: float, excitation=None, *, full_scale: float = 0.39,
                 metres_per_count: float | None = None, firmware: str = "ino",
                 touch: bool = True, boot_s: float = 0.0, pass_time: bool = True,
                 travel: float | None = None, stop_low: float | None = None,
                 adc_s: float | None = None, reply_s: float | None = None,
                 clock: str = "wall", seed: int = 0, device_b=None, hand=None) -> None:
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
        self.full_scale = option_value("full_scale", full_scale, "N", low=0, low_ok=False)
        self.mpc = (ff.METRES_PER_COUNT if metres_per_count is None else
                    option_value("metres_per_count", metres_per_count, "m", low=0,
                                 low_ok=False))
        self.firmware = firmware
        self.touch = bool(touch)
        self.boot_s = option_value("boot_s", boot_s, "s", low=0)
        if stop_low is not None:
            option_value("stop_low", stop_low, "m")
        if travel is not None:
            travel = option_value("travel", travel, "m", low=0, low_ok=False)
        self.stops = (None if travel is None else
                      (float(-travel / 2 if stop_low is None else stop_low),
                       float((-travel / 2 if stop_low is None else stop_low) + travel)))
        self.adc_s = (None if adc_s is None
                      else option_value("adc_s", adc_s, "s", low=0, low_ok=False))
        T = 1.0 / float(rate_hz)
        if self.adc_s is not None:
            if not self.adc_s < T:
                raise ConfigError(f"must be a time inside the period (0, {T:g}) [s], got "
                                  f"{adc_s!r}", key="adc_s")
            # the board's own timing: no queue; over the time from one read to the next
            # the fader holds the old force for T - adc_s, the new one for adc_s: the
            # split hold of a delay 1 - adc_s / T (0 whole periods)
            device = dataclasses.replace(device, delay=1.0 - self.adc_s / T)
            if device_b is not None:
                device_b = dataclasses.replace(
                    device_b, delay=1.0 - max(self.adc_s - self.POT_S, 0.0) / T)
        elif wall:
            self.adc_s = self.ADC_S if firmware != "pde" else 0.0
        if wall:
            rs = (self.REPLY_S if reply_s is None
                  else option_value("reply_s", reply_s, "s", low=0)) \
                if pass_time else self.adc_s
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
        self.fader_b = None
        self.enable_b = self.heat_b = self.cap_b = self.pwm_b = 0
        self._hand = [tuple(float(v) for v in h) for h in (hand or ())]
        self._holding = None                  # (start, passes left) while the hand holds
        # the silence the hand last acted in: the one before the host's first bytes is
        # none it acts in (class notes)
        self._hand_quiet = self._quiet_from
        self._host_spoke = False
        if device_b is not None:
            self.fader_b = Actuated(device_b, rate_hz, None, math.inf, seed + 1, clock=clock)
            if wall:
                # pot B read POT_S before pot A: fader B's own loop delay is longer
                self.adc_b_s = max(self.adc_s - self.POT_S, 0.0)
                self.fader_b.extra_latency_s = max(
                    0.0, float(device_b.delay) - (1.0 - self.adc_b_s / T)) / float(rate_hz)

    def position_count(self, physics=None) -> int:
        """A fader's reading (fader A's by default, or that of ``physics``): the sampled
        position in counts from the centre, 0..254.

        Parameters
        ----------
        physics : hapsim.device_model.MockPhysics, optional
            A fader's plant (fader B's: ``fader_b.physics``); default fader A's.

        Returns
        -------
        int
            :data:`hapsim.drivers.firefader.CENTRE` plus the sampled position over
            ``metres_per_count``, rounded and clipped to 0..254 [counts].
        """
        ff = self._ff
        c = ff.CENTRE + round((physics or self.physics).sample() / self.mpc)
        return int(min(max(c, 0), ff.POSITION_MAX))

    @property
    def held_b_at_end(self):
        """The force fader B is left holding once its queue is applied [N] (None without
        fader B)."""
        return None if self.fader_b is None else self.fader_b.settles_on()

    def _force(self, pwm: int) -> float:
        return pwm / 254.0 * self.full_scale

    def _advance(self, force) -> None:
        """One period (:meth:`hapsim.emulated.actuated.Actuated.apply`), the end stops enforced."""
        self.apply(force)
        self._at_the_stops()

    def _at_the_stops(self, ph=None) -> None:
        """The end stops: a fader (A, or the one of physics ``ph``) at or beyond one is
        held there, at rest."""
        if self.stops is not None:
            ph = ph or self.physics
            lo, hi = self.stops
            if ph.x <= lo or ph.x >= hi:
                ph.x = min(max(ph.x, lo), hi)
                ph.v = 0.0

    def _run_to(self, t: float) -> None:
        """Wall clock: the fader integrated to the board's time ``t`` [s], the motor's
        force held, the end stops enforced at each period's end (and at ``t``)."""
        T = self.physics.period
        for a in (self, self.fader_b):
            if a is None:
                continue
            w = a.wall
            while w.t < t:
                w.run_to(min(t, w.t + T))
                self._at_the_stops(a.physics)
            a.held = w.held

    def _silence(self, now: float) -> None:
        """Wall clock: the ``.ino``'s silence rule up to the board's time ``now`` [s]: no
        byte waiting for :data:`hapsim.drivers.firefader.SILENCE_S` zeroes the enable and
        the motor at that instant (``waitForSerialInput``, lines 264-277)."""
        if self.firmware == "pde":
            return
        at = self._quiet_from + self._ff.SILENCE_S
        b = self.fader_b
        if now > at and (self.enable or self.pwm or self.wall.settles_on()
                         or (b is not None and (self.enable_b or self.pwm_b
                                                or b.wall.settles_on()))):
            self._run_to(at)
            self._silenced()
            self.silences.append(at)
        at = self._quiet_from + self.HAND_SILENCE_S
        if now > at and self._hand and self._hand_quiet != self._quiet_from:
            self._run_to(at)
            self._hand_quiet = self._quiet_from
            self._take()

    def _silenced(self) -> None:
        """``waitForSerialInput``'s 65000th poll (lines 264-277): both enables and both
        motors to 0."""
        self.enable = self.enable_b = 0
        self.pwm = self.pwm_b = 0
        self.apply_now(0.0)
        if self.fader_b is not None:
            self.fader_b.apply_now(0.0)

    def _take(self) -> None:
        """The hand takes the faders to its next start and holds them there."""
        self._holding = [self._hand.pop(0), self.HAND_PASSES]
        self._place(still=True)

    def _place(self, still: bool) -> None:
        """The hand puts the faders at its start: still (held) or let go at its velocities."""
        xa, xb, va, vb = self._holding[0]
        for ph, x, v in ((self.physics, xa, va),
                         (None if self.fader_b is None else self.fader_b.physics, xb, vb)):
            if ph is not None:
                ph.x, ph.v = x, (0.0 if still else v)

    def _pass(self, count_a: int, ticks: int, start: float | None = None,
              count_b: int = 0) -> bytes:
        """One pass of the firmware's loop for a packet whose force bytes A and B are
        ``count_a`` and ``count_b`` (signed): lockstep, over ``ticks`` host periods (the
        ones before its last held); wall clock, starting at the board's time ``start``
        [s]. Fader B moves only with ``device_b`` (class notes)."""
        ff = self._ff
        fb = self.fader_b
        scaled = self.firmware == "ino-scaled"
        if self.firmware == "pde":
            self.pwm, self.pwm_b = 2 * count_a, 2 * count_b
        else:
            self.pwm = ff.pass_pwm(count_a, self.enable, scaled)
            self.pwm_b = ff.pass_pwm(count_b, self.enable_b, scaled)
        f = self._force(self.pwm)
        hold = self._holding
        pot_b = ff.CENTRE
        if self.wall is not None:
            self._run_to(start)
            if hold is not None:              # the hand, at the pass's start
                self._hand_step()
            self.apply(f, now=start)          # setPWM (lines 320-321): the duties from
            if fb is not None:                # the pass's start
                fb.apply(self._force(self.pwm_b), now=start)
                self._run_to(start + self.adc_b_s)     # pot B read first (line 341)
                pot_b = self.position_count(fb.physics)
            self._run_to(start + self.adc_s)  # ... held to pot A's read (line 343)
            self._busy_until = self.ready_at = start + self.reply_s
            self._quiet_from = self.ready_at
        else:
            for _ in range(ticks - 1):        # host ticks merged into this pass
                self._advance(None)
                if fb is not None:
                    fb.apply(None)
                    self._at_the_stops(fb.physics)
            self._advance(f)
            if fb is not None:
                fb.apply(self._force(self.pwm_b))
                self._at_the_stops(fb.physics)
            if hold is not None:              # the hand, at the sample the pass reads
                self._hand_step()
            if fb is not None:
                pot_b = self.position_count(fb.physics)
        pot = self.position_count()
        self.enables.append(self.enable)
        cap_b = 0
        if self.firmware != "pde":
            self.cap = ((self.cap * 7) >> 3) + (10 if self.touch else 1)
            self.enable, heat = ff.enable_step(self.enable, self.heat, self.pwm, pot,
                                               self.cap > 30)
            if fb is not None:
                # lines 369-371 and 383-385: heat B adds fader A's PWM (the firmware's)
                self.cap_b = ((self.cap_b * 7) >> 3) + (10 if self.touch else 1)
                self.enable_b, self.heat_b = ff.enable_step(
                    self.enable_b, self.heat_b, self.pwm, pot_b, self.cap_b > 30)
                cap_b = min(self.cap_b, 254)
            self.heat = heat
            cap = min(self.cap, 254)
        else:
            cap = 0
        self.passes += 1
        return ff.encode_record(pot, pot_b, (0, 0, cap, cap_b))

    def _hand_step(self) -> None:
        """One pass of the hand after a silence: hold the faders still at its start, or
        let them go at its velocities once :data:`HAND_PASSES` passes have run."""
        self._holding[1] -= 1
        self._place(still=self._holding[1] > 0)
        if self._holding[1] <= 0:
            self._holding = None

    def step(self, count_a: int) -> bytes:
        """One packet: one pass of the firmware, one record.

        Parameters
        ----------
        count_a : int
            Fader A's force byte, signed (-128..127); fader B's is 0.

        Returns
        -------
        bytes
            The 7-byte record (:func:`hapsim.drivers.firefader.encode_record`).

        Notes
        -----
        Lockstep only: on the wall clock the pass needs its start time (:meth:`feed`).
        """
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
        counted (the first element, possibly empty).

        Parameters
        ----------
        data : bytes
            The bytes of one read.

        Returns
        -------
        list of bytes
            The writes, each but the first starting with its 127.
        """
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
        if data:
            self._host_spoke = True
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
                        and (self.enable or self.pwm or self.enable_b or self.pwm_b)):
                    self._silenced()
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
        return self._pass(done[0], n, count_b=done[1])

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
        return self._pass(end[0], 1, start=max(now, self._busy_until), count_b=end[1])

    def idle(self, silent_s: float) -> bytes:
        """The host has been silent for ``silent_s`` [s] since its last bytes: ``.ino``
        disables the force after 0.1 s (on the wall clock at the instant the firmware's
        polls ran out, :meth:`_silence`, once the emulator has seen the silence last that
        long: :func:`serve` calls this while no byte waits, every ``poll``); ``.pde``
        streams a record (one pass) on every call.

        Parameters
        ----------
        silent_s : float
            Time since the host's last bytes [s].

        Returns
        -------
        bytes
            ``.pde``: one 7-byte record; ``.ino``: ``b""``.
        """
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
        if silent_s > 0.1 and (self.enable or self.pwm or self.enable_b or self.pwm_b):
            self._silenced()
        if silent_s >= self.HAND_SILENCE_S and self._hand and self._host_spoke:
            self._take()
        return b""

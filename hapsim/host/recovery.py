"""A lost device and its recovery: silence, a port error or a reset (HELLO after arming)
ends a stretch of the loop with :class:`~hapsim.host.loop_types.LostDevice`; zero force
and STOP are sent, the port is re-opened, HELLO and CONFIG are asked again with backoff,
and the next stretch restarts the scene at rest under a force ramp.

The end of a run after a safety stop on the device's motion brakes it first, and so does
the end of a run (its duration, a signal) on a driver's board that keeps its own time
(:meth:`Recovery._brake`): zero force alone leaves a moving handle to its own friction,
which carries it ``v m / b`` further (a Hapkit paddle of 0.1 kg on 0.3 N s/m: 0.33 s
times its speed; a board without a watchdog holds the last force through a host stall,
and once in a loaded suite a paddle woke the host 0.23 m out, beyond its 0.2 m
workspace, still moving). The host instead answers each STATE with the damping
``f = -B v`` (clamped to the force limit) until the device is at rest, then sends zero;
a device that takes none of the host's FORCEs (a link that makes every answer late) is
sent the zero FORCE and STOP at once instead (:data:`hapsim.braking.IGNORED_TICKS`).
``B = g m / T`` with ``g = BRAKE_GAIN``: the velocity then obeys
``v(k+1) = v(k) - g v(k - d)`` (a mass, a zero-order hold and ``d`` periods of delay,
friction only helping), whose roots stay inside the unit circle for
``g < 2 sin(pi / (2 (2 d + 1)))`` (the delayed first-order difference equation's bound,
Levin & May 1976, *Theor. Popul. Biol.* 9, 178-187; Kuruklis 1994, *J. Math. Anal.
Appl.* 188, 719-731): 0.25 holds to ``d = 5``, so a host late by a few periods still
brakes. The speed then falls by about ``1 - g`` a period: the handle stops within about
``v T (d + 1/g)`` where friction alone took ``v m / b`` (``tests/test_brake.py``). The
law is :class:`hapsim.braking.Brake` with ``n = 1``, the one the 2-D and 3-D drivers brake
their joints with (:mod:`hapsim.braking`).

:class:`Recovery` is the part of :class:`hapsim.host.loop.HostLoop` that does it (with
its start and end: :meth:`Recovery._run_stretches`, :meth:`Recovery._shutdown`). It reads
the loop's ``transport``, ``config``, ``stop``, ``tel``, ``engine`` and ``result``, and
uses the handshake's HELLO and CONFIG (:class:`hapsim.host.handshake.Handshake`).
"""

from __future__ import annotations

import math

import firmware_protocol as fp
from hapsim.braking import BRAKE_GAIN, BRAKE_MAX_S, IGNORED_TICKS, Brake, brake_damping
from hapsim.host.loop_types import OPEN_ENDED, SEQ_HALF, SEQ_MASK, LostDevice, signame
from hapsim.kernels.ticks import named_delay
from hapsim.host.telemetry import FLAG_LOST
from hapsim.errors import DeviceError

# BRAKE_GAIN, BRAKE_MAX_S and brake_damping live in hapsim.braking (the law of every
# dimension, the n-D drivers' too); named here as before
__all__ = ["Recovery", "BRAKE_GAIN", "BRAKE_MAX_S", "brake_damping", "names_older"]


def _stored_energy(engine) -> float:
    """Energy the scene stores now [J] (:meth:`hapsim.engine.Engine.energy`); 0.0 for an
    engine without that method or a non-finite value (the observer's baseline, module notes)."""
    fn = getattr(engine, "energy", None)
    if fn is None:
        return 0.0
    e = float(fn())
    return e if math.isfinite(e) else 0.0


def names_older(state, seq0: int, d: int, applied: bool) -> bool:
    """Whether a STATE at least :data:`~hapsim.braking.IGNORED_TICKS` ticks past the tick
    FORCE ``seq0`` was due at (``seq0 + d``) still names an older FORCE as applied (or, on
    a device that flags what it applies, none): the device took none of the braking's
    FORCEs. The 1-D braking's test (:meth:`Recovery._brake`) and the n-D records'
    (:mod:`hapsim.pipeline.record_guard`).

    Parameters
    ----------
    state : firmware_protocol.State
        The STATE (``seq``, ``force_seq``, ``status``; u32 counters).
    seq0 : int
        The braking's first FORCE.
    d : int
        The delay [ticks].
    applied : bool
        The device has set ``STATUS_FORCE_APPLIED`` on this or an earlier STATE.

    Returns
    -------
    bool
        False before tick ``seq0 + d + IGNORED_TICKS`` (mod 2^32) or without a
        ``force_seq``.
    """
    past = (state.seq - seq0 - d) & SEQ_MASK
    if past >= SEQ_HALF or past < IGNORED_TICKS or state.force_seq < 0:
        return False
    if named_delay(state.seq, state.force_seq, state.status, applied) < 0:
        return applied
    return ((state.force_seq - seq0) & SEQ_MASK) >= SEQ_HALF


class Recovery:
    """Loss, recovery, the run's stretches and its end (a base of
    :class:`~hapsim.host.loop.HostLoop`)."""

    def _shutdown(self) -> None:
        tr = self.transport
        try:
            self._brake()
        except DeviceError:
            self.result.brake["ended"] = "port"
        try:
            tr.send(fp.Force((self._last_seq + 1) & SEQ_MASK, (0.0,)))
            tr.send(fp.Stop())
        except DeviceError:
            pass

    def _brake(self) -> None:
        """After a safety stop on the device's motion, brake it: answer each STATE with
        ``f = -B v`` (``B`` = ``config.brake_damping``, clamped to the force limit, ``v``
        the backward difference of the last two STATEs on the device's clock) until three
        speeds in a row are below ``config.brake_rest``, for at most
        :data:`BRAKE_MAX_S` (module notes). The same at the end of a run (its duration or
        a signal: ``stop_reason`` still ``"duration"`` here) on a driver's board that
        keeps its own time (its transport's ``driver.own_clock``: a real board, or an
        emulated one on the wall clock): a run's last force goes, and the handle goes on
        at its speed, ``v m / b`` (issue 29, the independent board models of
        ``tools/independent_boards``: the Haply M3's joint 1.0-2.0 rad past its last
        reading, the Hapkit's paddle to its end stops 6 cm out, after runs that ended on
        their duration). Nothing after a non-finite reading, a lost device or any other
        end. Nothing either, or no more, once the device is seen taking none of the host's
        FORCEs (:meth:`_ignoring` before the first, :func:`names_older` after): its
        braking would be as late as every other answer, and the zero FORCE and STOP that
        :meth:`_shutdown` sends next are what it applies at once (``ended``
        ``"ignored"``). What it did is :attr:`LoopResult.brake`.

        Raises
        ------
        DeviceError
            The port failed (the caller still sends zero force and STOP).
        """
        cfg, res = self.config, self.result
        B = float(cfg.brake_damping)
        reason = res.stop_reason or ""
        own = bool(getattr(getattr(self.transport, "driver", None), "own_clock", False))
        at_end = not res.safety_stop and reason == "duration" and own
        if (not (res.safety_stop or at_end) or not B > 0.0
                or reason.startswith("safety: non-finite")
                or self.state not in ("armed", "running")):
            return
        tr, clock, sleep = self.transport, self._clock, self._sleep
        T = 1.0 / cfg.rate_hz
        law = Brake(B, cfg.force_limit, cfg.brake_rest)        # n = 1 of hapsim.braking
        t0 = clock()
        end = t0 + max(BRAKE_MAX_S, 3.0 * T)
        seq = (self._last_seq + 1) & SEQ_MASK
        seq0 = seq                    # the braking's first FORCE
        prev_us = None                # device time [us] of the last STATE
        periods = late = 0
        ended = "time"
        last = t0
        d, applied = int(cfg.delay), self._applied_seen
        if self._ignoring(d, applied):
            res.brake = law.report(0, 0.0, "ignored", 0)
            return
        while clock() < end:
            f = float(law.command()[0])
            tr.send(fp.Force(seq, (f,)))
            self._last_seq = seq          # the zero FORCE follows the braking's last
            periods += 1
            deadline = clock() + T
            st = None
            for msg in tr.receive(2.0 * T):
                if type(msg) is fp.State and len(msg.position) == 1 \
                        and math.isfinite(msg.position[0]):
                    st = msg
            if st is not None:
                if names_older(st, seq0, d, applied):
                    ended = "ignored"
                    break
                seq = st.seq
                # the velocity on the device's clock: a repeated time restarts it
                law.observe(st.position, None if prev_us is None or st.time_us == prev_us
                            else (st.time_us - prev_us) * 1e-6)
                prev_us = st.time_us
                if law.at_rest:
                    ended = "rest"
                    break
            wait = deadline - clock()
            if wait > 0.0:
                sleep(wait)
            now = clock()
            if now - last > 2.0 * T:
                late += 1                 # the host itself late: a period held longer
            last = now
        res.brake = law.report(periods, clock() - t0, ended, late)

    def _ignoring(self, d: int, applied: bool) -> bool:
        """Whether the run's last STATE says the device applies none of the host's FORCEs:
        it names one more than ``d + IGNORED_TICKS`` ticks old (a link that makes every
        answer late: ``docs/reliability.md``, "A hold that never ends"). The braking's
        FORCEs would be as late: STOP is what the device takes at once."""
        n = self.tel.n
        kept = self.tel.rows_in_memory()
        if not kept or kept[-1][1] != n:
            return False
        sl = self.tel.slot(n - 1)
        lag = named_delay(int(self.tel.seq[sl]), int(self.tel.force_seq[sl]),
                          int(self.tel.status[sl]), applied)
        return lag > d + IGNORED_TICKS

    def _state_timeout(self) -> None:
        tr = self.transport
        raise DeviceError(f"no STATE from the device for {self.config.state_timeout:g} s "
                          f"(port {tr.info.get('port')}); last frames:\n"
                          f"{tr.last_frames() or '(none received)'}")

    # ------------------------------------------------------------------ recovery
    def _event(self, event: str, **kw) -> None:
        self.result.events.append({"event": event, "t": round(self._clock() - self._t0, 6),
                                   "sample": self.tel.n, "state": self.state, **kw})

    def _recover(self, lost: LostDevice) -> bool:
        """Zero force and STOP, then re-open / HELLO / CONFIG with backoff.

        Returns
        -------
        bool
            True when CONFIG was sent again (the loop resumes at the next armed STATE);
            False when the stop flag was set meanwhile.

        Raises
        ------
        DeviceError
            ``reconnect`` is off, or the attempts / time allowed for this loss are used up.
        ProtocolError
            The device that answered is not one hapsim can drive (version, axes).
        """
        cfg = self.config
        tr = self.transport
        res = self.result
        clock = self._clock
        reason = str(lost)
        frames = tr.last_frames() or "(none received)"      # docs/design.md, rule 11
        self._check_bad()
        self.state = "lost"
        if self._lost_since is None:
            self._lost_since = clock()
            self._attempts = 0
            res.lost += 1
            # where the handle was at the last STATE answered [m] (the report sets it
            # beside where the recovery finds it: a device holds its last force until its
            # watchdog, and the handle coasts on)
            tel = self.tel
            x_last = float(tel.position[tel.slot(tel.n - 1)]) if tel.n else None
            self._event("lost", reason=reason, last_frames=frames, x=x_last)
        else:
            self._event("lost again", reason=reason, last_frames=frames)
        try:                                   # the device's own watchdog zeroes it anyway
            tr.send(fp.Force((self._last_seq + 1) & SEQ_MASK, (0.0,)))
            tr.send(fp.Stop())
        except DeviceError:
            lost.port_error = True
        if not cfg.reconnect:
            if "no STATE" in reason:
                self._state_timeout()
            raise DeviceError(f"{reason} (port {tr.info.get('port')}); last frames:\n"
                              f"{tr.last_frames() or '(none received)'}")
        port_error = lost.port_error
        delay = cfg.backoff
        last_err = reason
        while not self.stop.set:
            spent = clock() - self._lost_since
            if self._attempts >= cfg.reconnect_attempts or spent > cfg.reconnect_time:
                raise DeviceError(
                    f"device lost ({reason}); {self._attempts} reconnect attempts in "
                    f"{spent:.3g} s failed (last: {last_err}); port {tr.info.get('port')}; "
                    f"last frames:\n{tr.last_frames() or '(none received)'}")
            self._attempts += 1
            res.reconnect_attempts += 1
            self.state = "recovering"
            self._event("attempt", n=self._attempts)
            try:
                if port_error and hasattr(tr, "reopen"):
                    tr.reopen()
                    port_error = False
                hello = self._ask_hello(cfg.attempt_timeout)
                if hello is not None:
                    self._check_hello(hello)
                    self._ask_sensors()        # a reset device forgot the request
                    # the device may still tick armed STATEs of the lost session
                    res.quiesced = self._quiesce()
                    self._check_applied = not res.quiesced
                    self._send_config()
                    self.state = "armed"
                    return True
                last_err = f"no HELLO within {cfg.attempt_timeout:g} s"
            except DeviceError as exc:        # ProtocolError (not a DeviceError) ends it
                last_err = str(exc).split("\n")[0]
                port_error = True
            if self.stop.set:
                break
            self._sleep(delay)
            delay = min(2 * delay, cfg.backoff_max)
        return False

    # ------------------------------------------------------------------ shared
    def _run_stretches(self, stretch) -> None:
        """Run ``stretch(n_max)`` until the end; after each loss, recover and run it again.

        Both loops (device- and host-clocked) go through here: a stretch runs from the next
        armed STATE after a CONFIG until the end, a stop, or a loss (:class:`LostDevice`); the loss
        is handled by :meth:`_recover` (zero FORCE, STOP, re-open, HELLO, CONFIG, backoff),
        and the next stretch restarts the scene through :meth:`_resume`.
        """
        res = self.result
        stop = self.stop
        n_max = self.config.n_samples if self.config.n_samples > 0 else OPEN_ENDED
        if self.tel.max_rows is not None:
            n_max = min(n_max, self.tel.max_rows)
        self._energy = 0.0
        while self.tel.n < n_max and not stop.set:
            try:
                stretch(n_max)
            except LostDevice as lost:
                if not self._recover(lost):
                    break
        if stop.set and res.stop_reason == "duration" and stop.signal is not None:
            res.stop_reason = f"signal {signame(stop.signal)}"

    def _silence(self) -> float:
        """Silence after which the device is lost [s]: ``lost_timeout`` (default: the
        watchdog, or longer for a transport that waits for a silent board itself,
        ``waits_silence_s``) when reconnecting, else ``state_timeout``.

        A board without a watchdog on its own clock (the Haply M3) is waited for by its
        driver transport, at zero torque after the hold bound, and declared lost there
        (:mod:`hapsim.drivers.resync`): a loss at the watchdog's 50 ms sent its STOP and
        CONFIG, whose set-ups set the board's angle to an estimate 50 ms old or more
        while the board held its torque, and the frame walked at each (issue 29: the
        joint 0.5-13 rad from its start in lossy runs beside CPU-bound processes)."""
        cfg = self.config
        if cfg.reconnect:
            if cfg.lost_timeout is not None:
                return cfg.lost_timeout
            waits = float(getattr(self.transport, "waits_silence_s", 0.0) or 0.0)
            return max(cfg.watchdog_us * 1e-6, waits)
        return cfg.state_timeout

    def _resume(self, x: float):
        """First armed STATE after a (re)CONFIG: restart the scene at rest at ``x`` [m].

        After a loss the engine is rebuilt from the scene (its initial state), the force
        ramp is armed and the recovery is recorded. The passivity observer restarts: ``E``
        from 0, its baseline ``E0`` the scene's stored energy now (module notes).

        Parameters
        ----------
        x : float
            Device position of the first armed STATE [m].

        Returns
        -------
        Engine
            The engine to step.
        """
        self._restart_flag = 0
        if self.first_state_at is None:
            self.first_state_at = self._clock()
        if self._lost_since is not None:
            self._restart_flag = FLAG_LOST          # telemetry: the scene restarts here
            self.engine = type(self.engine)(self.engine.scene)
            self._ramp = max(int(self.config.ramp_samples), 1)
            self.result.recovered += 1
            self._event("recovered", attempts=self._attempts,
                        after_s=round(self._clock() - self._lost_since, 6), x=x)
            self._lost_since = None
        self.engine.set_port_position(x, at_rest=True)
        # passivity observer: the scene (re)starts holding E0; E counts from 0 again
        self._e0 = _stored_energy(self.engine)
        self._energy = 0.0
        self.result.energy_stored = self._e0
        self._fresh = False
        self._check_applied = False
        return self.engine

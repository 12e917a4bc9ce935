"""The host loop: handshake, fixed-rate device- or host-clocked loop, safety.

:class:`HostLoop` is built from rooms with one job each: the run and the per-sample path
(:meth:`HostLoop._drive`) are here; the two clocks' sources of
STATEs are :class:`~hapsim.host.device_clock.DeviceClock` and
:class:`~hapsim.host.host_clock.HostClock`, the handshake
:class:`~hapsim.host.handshake.Handshake`, a loss and its recovery
:class:`~hapsim.host.recovery.Recovery`, the bad-frame records
:class:`~hapsim.host.bad_frames.BadFrames`, and what goes in and out (``LoopConfig``,
``LoopResult``, ``StopFlag``) :mod:`hapsim.host.loop_types` (re-exported here).

Hot path (docs/design.md, rule 4): per sample it decodes the STATE, steps the engine (numba), clamps,
encodes and writes the FORCE and writes one telemetry row *by index* into preallocated
arrays (a head kept whole, then a ring that a writer thread drains to the journal: the data
leaves through a ring buffer, and a run can be open-ended). A STATE the backlog policy skips
steps the scene and is written by index into the telemetry's preallocated skipped STATEs'
record (the row it precedes, its position; bounded, then only counted), so that the contact
replay knows the scene's state through a backlog (:mod:`hapsim.host.telemetry`). No logging, no file I/O, no
allocation beyond the protocol's message objects and byte strings (unavoidable in Python).
Counters (late, missed, clamped, overruns) are kept as integers and reported at the end.

Timing convention: STATE ``n`` (``x(nT)``) is answered by FORCE ``seq = n`` computed from
``x[n]`` and ``x[n-1]``; the device applies it over ``[(n+d)T, (n+d+1)T)``.

Safety (from the first version): host-side clamp at the force limit; a non-finite position
or force sends zero force and stops; a stop flag (set by SIGINT/SIGTERM handlers) ends the
loop; safety stops end it with zero force: force at the limit in at least ``clamp_max`` of the
last ``clamp_window`` samples, ``|x|`` beyond ``position_bound``, ``|v|`` beyond
``velocity_limit``, the energy the virtual environment gave the hand beyond
``energy_limit``, or (``late_growth``, the lateness guard) the forces the device held over
the host's lateness having grown the scene's loop by the guard's bound, the handle moving
(:mod:`hapsim.kernels.late_growth`). Every end sends a zero FORCE then STOP.

Reliability (both loops): bad frames are dropped by the decoder and never acted on, and
each is recorded (docs/design.md, rule 11: sample, time, what the decoder found, its bytes and the
frames before it; the last ``BAD_FRAME_RECORDS``): the loop compares the decoder's bad-frame
count after each read (five integer reads) and only when it changed copies the references
of the decoder's last frames, formatted at the end of the run;
a STATE older than the last one (duplicated, reordered) is ignored (``stale``), one with the
wrong number of axes too (``bad_axes``); silence for ``lost_timeout`` (default: the
watchdog period, so the host sends zero force and STOP when the device's own watchdog
zeroes it), a port error, an unarmed STATE after arming, or a HELLO after the first armed
STATE (the device reset: it says HELLO when it restarts) make the device *lost* at once:
zero FORCE and STOP are sent (best effort), then, when ``reconnect`` is on, the host re-opens
the port if it failed, asks for HELLO and sends CONFIG again, with exponential backoff, at
most ``reconnect_attempts`` times and ``reconnect_time`` seconds per loss; the scene restarts
from its initial state with the port at the device's position at rest, the force ramped up
over ``ramp_samples``. A recovery's CONFIG follows a STOP and the PONG of a PING sent
after it (:meth:`HostLoop._quiesce`; without that PONG, the first armed STATE after the
CONFIG must not report a FORCE applied, as the host sent none yet): the scene restarts at
the handle of the new session, never at a STATE the device sent before it took the CONFIG. The loop's state (:attr:`HostLoop.state`: ``idle``, ``handshake``,
``armed``, ``lost``, ``recovering``, ``stopped``) is kept and reported. Non-latched device
FAULTs (WATCHDOG, RX_ERRORS, OVERRUN, AXES_MISMATCH) are counted; latched ones end the
run. The host-clocked loop uses the same machinery (one driver,
:meth:`HostLoop._run_stretches`, runs either loop's stretch and recovers its losses;
:meth:`HostLoop._resume` restarts the scene) and the same per-sample work
(:meth:`HostLoop._drive`, fed by either clock's source of STATEs): it answers the latest
STATE at each host deadline, and silence longer than ``lost_timeout`` is a loss like in the
device-clocked loop. Without ``reconnect`` a loss raises :class:`DeviceError`.

Passivity observer (Hannaford & Ryu, "Time-domain passivity control of haptic interfaces",
IEEE Trans. Robot. Autom. 18(1), 2002): ``E(n) = sum_k f_held(k) (x(k+1) - x(k))`` [J], i.e.
``T sum f v`` with ``v`` the backward-difference velocity, where ``f_held(k)`` is the force
the device held over ``[kT, (k+1)T)``: the FORCE its STATE ``k`` names as applied (the FORCE
answering STATE ``k - d`` when it came in time, an older one it held when it came late, zero
under its watchdog), at the value the host sent (:func:`hapsim.kernels.ticks.held_force`),
over every STATE, a skipped one's too. Sign convention: ``E`` is the energy that flowed
**out of the virtual environment into the hand** (work done by the actuator on the hand);
Hannaford & Ryu's ``E_obs`` (energy *into* the one-port) is ``-E``. A passive environment
holding the energy ``E0`` when it starts can give at most ``E0`` (their condition
``E_obs(n) + E0 >= 0``), so the observer's baseline is ``E0``, the scene's stored energy
(:meth:`hapsim.engine.Engine.energy`) at each (re)start, with the port at rest at the
device's position; ``E`` restarts from 0 at each (re)start (a recovery restarts the scene,
whose stored energy is ``E0`` again). What the scene gave **beyond** it, the *excess*
``E - E0``, is what the energy safety stop (``excess > energy_limit``) and the optional
passivity controller act on: the controller adds the damping ``alpha = (E - E0) / (T v^2)``
(their ``alpha = -(E_obs + E0) / (T v^2)``) while the excess is positive, capped at
``max_damping``: ``f <- f - alpha v``. With d samples of delay the damping acts d samples
late, or not at all when the device ignored it as late; the observer still measures the work
really done (the force held, not the force sent: before 2026-11-29 it took FORCE ``k - d``
as held, and a link that made answers late gave it the wrong sign: -0.06 J where the device
gave the hand +0.29 J). A sampled wall is not exactly passive (the hold and the delay lag
its spring, Colgate & Schenkel 1997): when its damping B does not cover that lag the excess
grows a little above 0 even though the loop is stable, and the controller acts.
"""

from __future__ import annotations

import gc
import math
import time
from collections import deque
from itertools import chain

import firmware_protocol as fp
from hapsim.host.bad_frames import BadFrames, bad_count
from hapsim.host.device_clock import DeviceClock
from hapsim.host.handshake import Handshake
from hapsim.host.host_clock import HostClock
from hapsim.host.link_verdict import CLAMP_STOP
from hapsim.host.loop_types import (BAD_FRAME_CONTEXT, BAD_FRAME_RECORDS, LATCHED_FAULTS,
                                      SENSORS_TRIES, SENSORS_WAIT, LoopConfig,
                                      LoopResult, LostDevice, MeasuredVelocity, StopFlag,
                                      percentiles_us, signame)
from hapsim.host.recovery import Recovery
from hapsim.host.telemetry import FLAG_CLAMPED, FLAG_RAMP
from hapsim.errors import DeviceError
from hapsim.kernels.late_growth import (LATE_GROWTH_STOP, late_growth_reason,
                                        late_growth_step, open_hold_growth)
from hapsim.kernels.ticks import held_force, named_delay, sent_ring_size, tick_late

__all__ = ["LoopConfig", "LoopResult", "StopFlag", "HostLoop", "MeasuredVelocity",
           "LostDevice", "percentiles_us", "safety_reason", "LATCHED_FAULTS",
           "BAD_FRAME_RECORDS", "BAD_FRAME_CONTEXT", "SENSORS_TRIES", "SENSORS_WAIT"]

_Lost = LostDevice          # the name this module's loop code uses


class HostLoop(Handshake, Recovery, BadFrames, DeviceClock, HostClock):
    """The fixed-rate host loop between an engine and a device transport.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        The scene (warmed up: its kernel already compiled/loaded).
    transport : object
        A transport of :mod:`hapsim.host.transport`. When it has ``clock()`` and
        ``sleep(s)`` (the virtual-clock :class:`~hapsim.emulated.links.SimTransport`) the
        loop's timeouts use them; ``reopen()`` is used to recover a failed port.
    config : LoopConfig
        Run parameters.
    telemetry : Telemetry
        Preallocated buffer: its head rows, then its ring (the loop writes row ``i`` in
        slot ``i`` or ``head + (i - head) % ring``, then raises ``n``; a writer thread may
        drain it); without a ring, at most ``head`` samples are run.
    stop : StopFlag, optional
        Polled every sample.
    measured : MeasuredVelocity, optional
        Ask the device for its velocity sensor (SENSORS_REQUEST before CONFIG, refused with
        :class:`~hapsim.errors.ConfigError` when it offers none) and keep each STATE's
        VELOCITY there, for an engine that reads it.

    Attributes
    ----------
    state : str
        ``"idle"`` (not started), ``"handshake"`` (asking HELLO, sending CONFIG),
        ``"armed"`` (CONFIG sent: driving the device, or waiting for its first STATE),
        ``"lost"`` (silence, port error or reset seen: zero force and STOP sent),
        ``"recovering"`` (re-opening, HELLO, CONFIG with backoff), ``"stopped"`` (zero
        force and STOP sent at the end).
    """

    def __init__(self, engine, transport, config: LoopConfig, telemetry,
                 stop: StopFlag | None = None, measured: MeasuredVelocity | None = None):
        self.engine = engine
        self.measured = measured
        #: Called between two samples, before the engine steps (live changes: the
        #: mailbox of :class:`hapsim.audio.control.Controller`); None: nothing.
        self.poll = None
        #: Called once the device's HELLO is checked, before PING and CONFIG (``hapsim
        #: run``: waits for the numba warm-up that ran while the device started); None:
        #: nothing.
        self.before_arm = None
        #: :attr:`_clock` time of the first armed STATE (start-up figure); None before.
        self.first_state_at = None
        self.transport = transport
        self.config = config
        self.tel = telemetry
        self.stop = stop or StopFlag()
        self.result = LoopResult()
        self._last_seq = -1
        self._clock = getattr(transport, "clock", time.monotonic)
        self._sleep = getattr(transport, "sleep", time.sleep)
        self._fresh = True          # next armed STATE (re)starts the scene at rest
        self._ramp = 0              # samples left in the force ramp after a recovery
        self._restart_flag = 0      # FLAG_LOST for the first row after a recovery
        self._skip_flag = 0         # FLAG_SKIPPED for the next row (older STATEs skipped)
        # a driver's host tick that went out a period or more late: its row is marked
        # late (the device held the force before over it, and read the position late),
        # so that a measurement cuts there as at a late tick it cannot account
        self._host_late = 0
        self._expect = -1           # next STATE seq expected (device-clocked source)
        self._last_rx = 0.0         # clock time of the last STATE used [s]
        self._lost_since = None     # clock time of the current loss, None when healthy
        self._attempts = 0
        self._t0 = 0.0
        self._energy = 0.0          # passivity observer E since the last (re)start [J]
        self._e0 = 0.0              # its baseline: stored energy at that (re)start [J]
        self._applied_seen = False  # the device sets STATUS_FORCE_APPLIED (PROTOCOL.md §4)
        self._check_applied = False  # skip STATEs with FORCE_APPLIED until the scene resumes
        self.force_limit = math.inf
        self.state = "idle"
        dec = getattr(transport, "decoder", None)
        self._dstats = dec.stats if dec is not None else None
        self._nbad = bad_count(self._dstats) if dec is not None else 0
        self._nbad0 = self._nbad
        self._bad_snaps: deque = deque(maxlen=BAD_FRAME_RECORDS)

    # ------------------------------------------------------------------ run
    def run(self) -> LoopResult:
        """Handshake, run the loop, then always send zero force and STOP.

        Returns
        -------
        LoopResult

        Raises
        ------
        DeviceError
            Device silent or lost beyond recovery, port failure, or no HELLO (zero force +
            STOP are still attempted).
        ProtocolError
            The device (at the handshake or when it came back after a loss) speaks another
            protocol version or has another number of axes than 1 (zero force + STOP are
            still attempted).
        """
        gc_was = gc.isenabled()
        if getattr(self.transport, "info", {}).get("kind") not in ("in-process", "sim"):
            # before CONFIG arms the device: a device on the wall clock ticks from then
            # on (an in-process lockstep or virtual-clock mock waits for the host: no
            # collection needed, ~0.07 s a run in a large process)
            gc.collect()
        gc.disable()             # from then on; no collector pauses in the hot loop (§4)
        try:
            hello = self.handshake()
        except BaseException:
            if gc_was:
                gc.enable()
            raise
        try:
            if hello is None:
                pass
            elif self.config.host_clocked:
                self._run_stretches(self._host_clocked_stretch)
            else:
                self._run_stretches(self._device_clocked_stretch)
        finally:
            self.result.state = self.state
            self._shutdown()
            self.state = "stopped"
            if gc_was:
                gc.enable()
        return self.finish()

    def finish(self) -> LoopResult:
        """Fill the result from what was recorded: samples, turnaround, decoder counters.

        :meth:`run` ends with it; a caller that caught :meth:`run`'s DeviceError or
        ProtocolError calls it to report the run up to the loss.

        Returns
        -------
        LoopResult
            :attr:`result`, completed.
        """
        res = self.result
        if self.stop.set and res.stop_reason == "duration" and self.stop.signal is not None:
            res.stop_reason = f"signal {signame(self.stop.signal)}"
        elif self.stop.set and res.stop_reason == "duration" and getattr(self.stop, "reason",
                                                                          None):
            res.stop_reason = self.stop.reason
        res.samples = self.tel.n
        if self.measured is not None and res.velocity:
            res.velocity = self.measured.as_dict()
        ta = self.tel.columns()["turnaround_us"]       # the rows still in memory
        res.turnaround_us = percentiles_us(ta)
        res.turnaround_us["samples"] = int(ta.size)
        dec = getattr(self.transport, "decoder", None)
        if dec is not None:
            res.decoder = dec.stats.as_dict()
            self._check_bad()
            res.bad_frames_seen = self._nbad - self._nbad0
            res.bad_frames = self._bad_frame_records()
        return res

    def _note_other(self, msg) -> bool:
        """A message other than STATE during the loop: count non-latched FAULTs and HELLOs.

        A latched FAULT ends the run (returns True, stop flag set). A HELLO after the first
        armed STATE since the last CONFIG means the device reset (it says HELLO when it
        restarts): the device is lost at once (:class:`_Lost`) rather than after
        ``lost_timeout`` of silence. Before that STATE a HELLO may answer one of the
        handshake's HELLO requests and is only counted.

        Raises
        ------
        _Lost
            On a HELLO after arming.
        """
        res = self.result
        tm = type(msg)
        if tm is fp.Fault:
            name = fp.FAULT_NAMES.get(msg.code, f"0x{msg.code:04X}")
            if msg.code in LATCHED_FAULTS:
                res.faults.append(name)
                res.stop_reason = f"device: FAULT {name} (detail {msg.detail})"
                self.stop.set = True
                return True
            res.device_faults[name] = res.device_faults.get(name, 0) + 1
        elif tm is fp.Velocity:
            if self.measured is not None:
                self.measured.put(msg)
        elif tm is fp.Hello:
            res.hello_mid_run += 1
            if not self._fresh:
                raise _Lost("device reset: HELLO after arming")
        return False

    # ------------------------------------------------------------------ per sample (both)
    def _non_finite_stop(self, seq: int) -> None:
        """Safety stop on a non-finite position or force: zero force for ``seq``, then stop."""
        self.transport.send(fp.Force(seq, (0.0,)))
        self._last_seq = seq
        self.result.stop_reason = "safety: non-finite position or force"
        self.result.safety_stop = True
        self.stop.set = True

    def _drive(self, n_max: int, states) -> None:
        """The hot loop of both clocks: answer each sample ``states`` yields, until it ends,
        a stop, or a loss.

        The per-sample work exists here only: late check, engine step (non-finite stop),
        passivity observer and controller, force ramp after a recovery, clamp, FORCE,
        clamp window, telemetry row (head + ring, drained at half laps), maxima, safety
        bounds. The clocks differ only in which STATE is answered when, and that is the
        source's business (:meth:`_device_states`, :meth:`_host_states`); the source is a
        generator, so this loop keeps its state in local variables (no attribute access
        per sample beyond what the two loops did before).

        Parameters
        ----------
        n_max : int
            Rows to reach (the sources stop there).
        states : generator
            Yields ``(msg, x, t_rx)`` per sample to answer: the STATE, its position [m]
            and ``perf_counter_ns()`` when it was read; ``t_rx = -1`` for a STATE the
            backlog policy skips (the engine steps with it, nothing is sent; its row-to-be
            and position go to the telemetry's skipped STATEs' record,
            :meth:`~hapsim.host.telemetry.Telemetry.skipped`). It (re)starts the scene
            (:meth:`_resume`) at its first usable STATE, before yielding anything; it ends
            at ``n_max`` rows, on a stop, and raises :class:`_Lost` on a loss.
        """
        cfg = self.config
        tel = self.tel
        stop = self.stop
        res = self.result
        lim = self.force_limit
        d = cfg.delay
        T = 1.0 / cfg.rate_hz
        rate = float(cfg.rate_hz)
        pos_bound = cfg.position_bound
        vlim = cfg.velocity_limit
        elim = cfg.energy_limit
        pc_on = bool(cfg.passivity_controller)
        bmax = float(cfg.max_damping)
        # the clamp window as Python ints (0/1): a numpy int8 element costs ~0.2 us a read
        # or write and makes the sum a numpy scalar; the same counts
        win = [0] * max(cfg.clamp_window, 1)
        wlen = len(win)
        wsum = 0
        clamp_max = cfg.clamp_max
        # the FORCEs sent this stretch, by seq, and the force held the last STATE named,
        # and which FORCE: the passivity observer's (hapsim.kernels.ticks.held_force)
        ring_n = sent_ring_size(cfg.watchdog_us, cfg.rate_hz, d)
        ring = [[-1.0] * ring_n, [0.0] * ring_n]
        held = [0.0, -1.0]
        Force = fp.Force
        applied_bit = fp.STATUS_FORCE_APPLIED
        flags_applied = self._applied_seen
        isfinite = math.isfinite
        perf = time.perf_counter_ns
        send = self.transport.send
        ramp_n = max(int(cfg.ramp_samples), 1)
        e_max = res.energy_max
        x_max = res.energy_excess_max
        v_max = res.v_max
        f_max = res.f_max
        # the lateness guard (hapsim.kernels.late_growth): the growth the device's holds
        # put in, since this stretch (re)started, and the FORCE it named last
        guard = cfg.late_growth
        g_on = guard is not None
        g_tables = guard.lists() if g_on else None
        g_step = guard.step if g_on else 1.0
        g_acc = [0.0] * len(g_tables) if g_on else [0.0]    # per mode [nepers]
        g_worst = 0.0
        g_prev = -1
        # a handle slower than the braking's rest speed is at rest: the guard does not stop
        # it (a growth from rest is the guard's once the handle moves, or the bounds')
        g_rest = float(cfg.brake_rest)
        first = None
        try:
            # the source (re)starts the scene (engine, observer baseline, restart flag)
            # at its first usable STATE, before its first yield: device-clocked, that
            # STATE is the one it yields; host-clocked, the latest STATE at its first
            # deadline. Read what the restart set only now.
            first = next(states, None)
            if first is None:
                return
            eng = self.engine
            restart = self._restart_flag
            energy = self._energy
            e0 = self._e0
            t_arr, x_arr, f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr = (
                tel.time, tel.position, tel.force, tel.seq, tel.turnaround_us, tel.late,
                tel.flags, tel.force_seq, tel.status)
            hl, rl = tel.head, tel.ring      # row i is in slot i, or hl + (i - hl) % rl
            # a loop that is not real-time lets the journal writer catch up each half lap
            drain = tel.drain if rl else None
            lap_a, lap_b = (hl, hl + rl // 2) if drain is not None else (-1, -1)
            # the scene restarts at rest at the first sample: dx = 0 there, for both clocks
            # (device-clocked: at the STATE it resumed at; host-clocked: at the latest
            # STATE at its first deadline, maybe newer than the one it resumed at)
            x_prev = first[1]
            poll = self.poll
            sk_row, sk_x, sk_meta = tel.skip_row, tel.skip_x, tel.skip_meta  # skips' record
            sk_cap = sk_row.size
            i = tel.n
            for msg, x, t_rx in chain((first,), states):
                if t_rx < 0:
                    # a skipped STATE (backlog policy): not answered, but the scene takes
                    # its position, so that the next velocity spans one period; the step
                    # is recorded (the row it precedes, its position) for the replay
                    if isfinite(x):
                        eng.port_step(x)
                        # the work of the force held over its period (as a row's below)
                        energy += held_force(ring, msg.seq, msg.force_seq, msg.status, d,
                                             flags_applied, held) * (x - x_prev)
                        x_prev = x
                        sn = tel.skip_n
                        if sn < sk_cap:
                            sk_row[sn] = i
                            sk_x[sn] = x
                            sk_meta[sn, 0] = msg.seq
                            sk_meta[sn, 1] = msg.force_seq
                            sk_meta[sn, 2] = msg.status
                            sk_meta[sn, 3] = msg.time_us
                        tel.skip_n = sn + 1
                    continue
                seq = msg.seq
                lt = 0
                st = msg.status
                if st & applied_bit and not flags_applied:
                    flags_applied = self._applied_seen = True
                # the late-tick rule (hapsim.kernels.ticks), as the compiled loop and the
                # record's account read it
                host_late = self._host_late
                if host_late:
                    self._host_late = 0
                if tick_late(seq, msg.force_seq, st, d, flags_applied):
                    lt = 1
                    res.late += 1
                elif host_late:
                    lt = 1
                if g_on:
                    lag = named_delay(seq, msg.force_seq, st, flags_applied)
                    g_prev = late_growth_step(g_acc, g_prev, msg.force_seq, lag, g_tables,
                                              g_step)
                    g_worst = open_hold_growth(g_acc, g_prev, seq, lag, d, g_tables, g_step)
                if poll is not None:
                    poll()
                f = eng.port_step(x) if isfinite(x) else math.nan
                if not isfinite(f):
                    self._non_finite_stop(seq)
                    break
                # passivity observer: work of the force held over the last period, the one
                # the last STATE named (this one with d = 0): hapsim.kernels.ticks.held_force
                dx = x - x_prev
                x_prev = x
                v = dx * rate
                energy += held_force(ring, seq, msg.force_seq, st, d, flags_applied, held) * dx
                excess = energy - e0
                if pc_on and excess > 0.0:
                    tvv = T * v * v
                    if tvv > 0.0:
                        # alpha = (E - E0) / (T v^2), capped (compared without dividing:
                        # no overflow for a tiny v)
                        alpha = excess / tvv if excess < bmax * tvv else bmax
                        f -= alpha * v
                        res.passivity_samples += 1
                rf = 0
                if self._ramp > 0:
                    f *= (ramp_n - self._ramp + 1) / ramp_n
                    self._ramp -= 1
                    rf = FLAG_RAMP
                c = 0
                if f > lim:
                    f = lim
                    c = 1
                elif f < -lim:
                    f = -lim
                    c = 1
                send(Force(seq, (f,)))
                t_tx = perf()
                self._last_seq = seq
                j = seq % ring_n
                ring[0][j] = seq
                ring[1][j] = f
                j = i % wlen
                wsum += c - win[j]
                win[j] = c
                if c:
                    res.clamped += 1
                sl = i if i < hl else hl + (i - hl) % rl
                t_arr[sl] = msg.time_us * 1e-6
                x_arr[sl] = x
                f_arr[sl] = f
                s_arr[sl] = seq
                ta_arr[sl] = (t_tx - t_rx) * 1e-3
                late_arr[sl] = lt
                fs_arr[sl] = msg.force_seq
                st_arr[sl] = st
                skip = self._skip_flag
                if skip:
                    self._skip_flag = 0
                fl_arr[sl] = lt | rf | restart | (FLAG_CLAMPED if c else 0) | skip
                restart = 0
                i += 1
                tel.n = i
                if sl == lap_a or sl == lap_b:
                    drain()
                if energy > e_max:
                    e_max = energy
                if excess > x_max:
                    x_max = excess
                av = v if v >= 0.0 else -v
                if av > v_max:
                    v_max = av
                af = f if f >= 0.0 else -f
                if af > f_max:
                    f_max = af
                if (wsum >= clamp_max or x > pos_bound or x < -pos_bound or av > vlim
                        or excess > elim or (g_worst > LATE_GROWTH_STOP and av > g_rest)):
                    res.stop_reason = safety_reason(wsum, clamp_max, wlen, lim, x, pos_bound,
                                                     v, vlim, excess, elim, e0, g_worst, guard,
                                                     T)
                    res.safety_stop = True
                    stop.set = True
                    break
        except DeviceError as exc:        # a read or write failed: the port is gone
            raise _Lost(f"port failed: {str(exc).splitlines()[0]}", True) from None
        finally:
            if first is not None:
                self._energy = energy
                res.energy_max = e_max
                res.energy_excess_max = x_max
                res.v_max = v_max
                res.f_max = f_max
            # without a sample, E is what the source left: 0 when it (re)started the scene
            res.energy = self._energy


def safety_reason(wsum: int, clamp_max: int, wlen: int, limit: float, x: float,
                   position_bound: float, v: float, velocity_limit: float, excess: float,
                   energy_limit: float, stored: float = 0.0, growth: float = 0.0,
                   guard=None, period: float = 0.0) -> str:
    """Why a safety stop is due (called only once a bound is breached, off the fast path).

    Parameters
    ----------
    wsum, clamp_max, wlen : int
        Samples at the force limit in the last ``wlen``, and how many stop the run.
    limit : float
        Force limit [N].
    x, position_bound : float
        Device position and its bound [m].
    v, velocity_limit : float
        Device velocity and its bound [m/s].
    excess, energy_limit : float
        Energy given to the hand by the scene beyond what it stored at its (re)start, and
        its bound [J] (passivity observer, Hannaford & Ryu 2002).
    stored : float
        The scene's stored energy at that (re)start, the observer's baseline [J].
    growth : float
        The lateness guard's largest cumulative growth of a mode [nepers]
        (:mod:`hapsim.kernels.late_growth`).
    guard : hapsim.kernels.late_growth.LateGrowth or None
        Its table (the delays its reason names); None: no guard.
    period : float
        The sample period [s].

    Returns
    -------
    str
        The stop reason for the report, the first breached bound first.
    """
    if wsum >= clamp_max:
        return f"{CLAMP_STOP} {limit:g} N in {wsum} of the last {wlen} samples"
    if x > position_bound or x < -position_bound:
        return f"safety: position {x:.6g} m beyond +-{position_bound:g} m"
    if abs(v) > velocity_limit:
        return f"safety: velocity {v:.6g} m/s beyond +-{velocity_limit:g} m/s"
    if guard is not None and growth > LATE_GROWTH_STOP and not excess > energy_limit:
        return late_growth_reason(growth, guard, period)
    return (f"safety: the scene gave the hand {excess:.6g} J more than the {stored:.6g} J "
            f"it stored at its start, beyond the energy limit {energy_limit:g} J")

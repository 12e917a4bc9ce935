"""The host-clocked source of STATEs: the latest STATE answered at each host deadline.

:class:`HostClock` is the part of :class:`hapsim.host.loop.HostLoop` that ticks on the
host's clock (or a virtual-clock transport's): at each deadline it takes the newest armed
STATE, skips or estimates a tick without one (a request-reply driver's overdue answer),
counts overruns and stalls, stops a host that is late too often, and declares the device
lost on silence. It reads the loop's ``config``, ``tel``, ``stop``, ``result``,
``transport`` and ``measured`` (the notes of :mod:`hapsim.host.loop`).
"""

from __future__ import annotations

import time

import firmware_protocol as fp
from hapsim.drivers.base import LATE_STOP, LATE_WINDOW
from hapsim.host.bad_frames import bad_count
from hapsim.host.loop_types import EstimatedState
from hapsim.host.loop_types import LostDevice as _Lost
from hapsim.host.loop_types import SEQ_HALF as _HALF
from hapsim.host.loop_types import SEQ_MASK as _U32
from hapsim.host.realtime import sleep_until_ns
from hapsim.host.telemetry import FLAG_ESTIMATED

__all__ = ["HostClock", "ESTIMATED_MAX", "STALL_TICKS"]

#: Missing samples in a row a driver's loop steps the scene through with an extrapolated
#: position (beyond, ticks are skipped): :meth:`HostLoop._host_states`.
ESTIMATED_MAX = 2


class HostClock:
    """The host-clocked loop's source of STATEs (a base of
    :class:`~hapsim.host.loop.HostLoop`)."""

    # ------------------------------------------------------------------ host-clocked
    def _host_clocked_stretch(self, n_max: int) -> None:
        """Host-clocked loop from the next armed STATE until the end, a stop, or a loss:
        at each host deadline the latest STATE is answered (:meth:`_host_states`,
        :meth:`_drive`)."""
        self._drive(n_max, self._host_states(n_max))

    def _host_states(self, n_max: int):
        """The host-clocked source of :meth:`_drive`: the latest STATE at each deadline.

        Ticks without a new STATE are skipped (``missed``). Silence longer than
        :meth:`_silence`, or a disarmed STATE after arming, raise :class:`_Lost`
        (recovered by :meth:`_run_stretches`, as in the device-clocked loop). On a
        virtual-clock transport (``clock()``/``sleep()``) the deadlines are on that clock;
        deadlines missed by more than a period are counted (``overruns``).

        Yields
        ------
        (State, float, int)
            The STATE, its position [m], and ``perf_counter_ns()`` at the deadline.
        """
        cfg = self.config
        tr = self.transport
        tel = self.tel
        stop = self.stop
        res = self.result
        rate = float(cfg.rate_hz)
        silence = self._silence()
        State = fp.State
        armed_bit = fp.STATUS_ARMED
        applied_bit = fp.STATUS_FORCE_APPLIED
        perf = time.perf_counter_ns
        clock = self._clock
        sleep = self._sleep
        virtual = hasattr(tr, "clock")
        if virtual:
            def mono_ns() -> int:
                return int(round(clock() * 1e9))
        else:
            mono_ns = time.monotonic_ns
        receive = tr.receive
        # a request-reply device (a driver's) answers only what it is asked. A tick whose
        # answer is overdue (the transport's deadline) is a missing sample, not a silence
        # that grows into a loss: the scene steps with the position extrapolated from the
        # two before and its FORCE goes out (asking the device again), so the scene's clock
        # stays the device's (row flagged FLAG_ESTIMATED); more than ESTIMATED_MAX in a row,
        # the tick is skipped and the last force asked again (hold)
        # the driver declares it (Driver.request_reply): its transport then offers
        # overdue(), hold() and estimate()
        replies = getattr(getattr(tr, "driver", None), "request_reply", False)
        hold = tr.hold if replies else None
        overdue = tr.overdue if replies else None
        estimate = tr.estimate if replies else None
        est_state = EstimatedState()
        run_est = 0
        # a driver's transport on the wall clock is told of the host's stalls (no catch-up
        # burst of commands after one); a lockstep or virtual-clock run has none
        stalled = (getattr(tr, "host_stalled", None)
                   if replies and not cfg.lockstep and not virtual else None)
        # a lockstep mock with its account of the bytes it handled (a driver's): its
        # record is the commands', whatever the clock did (DriverTransport._clock), so a
        # tick is taken once it has answered everything written to it, the deadline only
        # the wait's bound: a 1,000-sample run in ~0.5 s, not 4 s of waiting for deadlines
        settled = (tr.settled if cfg.lockstep and not virtual and getattr(tr, "settles", False)
                   else None)
        late_ring = [0] * LATE_WINDOW           # 1 per late tick, the last LATE_WINDOW
        late_i = late_n = late_old = 0
        period_ns = int(round(1e9 / cfg.rate_hz))
        latest = None
        t_latest = 0.0              # clock time the latest STATE was taken [s]

        ds = self._dstats
        mv = self.measured

        def take(msgs) -> None:
            """Keep the newest armed 1-axis STATE; count the others; FAULT/HELLO noted;
            a change of the decoder's bad-frame count is recorded."""
            nonlocal latest, t_latest
            if ds is not None and (ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed
                                   + ds.unknown_type) != self._nbad:
                self._snap_bad(bad_count(ds))
            for msg in msgs:
                if type(msg) is not State:
                    self._note_other(msg)
                    continue
                if len(msg.position) != 1:
                    res.bad_axes += 1
                    continue
                if not msg.status & armed_bit:
                    if latest is None:
                        res.unarmed += 1
                        continue
                    raise _Lost("the device reports itself disarmed (reset?)")
                if latest is None and self._check_applied and msg.status & applied_bit:
                    res.earlier_session += 1      # a FORCE applied since CONFIG: none sent
                    continue
                if latest is not None:
                    ahead = (msg.seq - latest.seq) & _U32
                    if ahead >= _HALF:
                        res.stale += 1            # duplicated or reordered: older
                        continue
                    if ahead > 1 and ahead > (clock() - t_latest + silence) * rate + 2.0:
                        res.implausible += 1      # further ahead than time allows
                        continue
                latest = msg
                t_latest = clock()
                if mv is not None:
                    mv.take(msg.seq)              # its VELOCITY came just before it

        # wait for the first armed STATE (a device (re)starting gets state_timeout)
        end = clock() + cfg.state_timeout
        while latest is None and not stop.set:
            take(receive(0.05))
            if latest is None and clock() > end:
                raise _Lost(f"no STATE from the device for {cfg.state_timeout:g} s")
        if latest is None or stop.set:
            return
        self._resume(latest.position[0])
        used_seq = -1
        last_new = clock()
        # a real-time device ticks on the same clock: tick a third of a period after its
        # STATE arrives, so the STATE is in and the FORCE is back before its next tick
        # (ticking in phase with the device would race it every period)
        deadline = mono_ns() + (0 if cfg.lockstep else period_ns // 3)
        # a board that takes commands on its own tick: the deadlines put where a write
        # lands mid-tick, so its answer has the whole period to come before the next
        # deadline (delaying the writes alone left it the period less that delay, up to a
        # tick: the Hapkit sketch's answer, 3.5-4.3 ms after a write at 4 ticks a period,
        # came after the next deadline and was read as the next command's)
        align = (getattr(tr, "align_deadline", None)
                 if not cfg.lockstep and not virtual else None)
        if align is not None:
            deadline = align(deadline)
        while tel.n < n_max and not stop.set:
            remaining = deadline - mono_ns()
            if virtual:
                while remaining > 0:
                    sleep(max(remaining, 1000) * 1e-9)
                    remaining = deadline - mono_ns()
            elif remaining > 0 and settled is not None:
                while True:                 # (its answers read, then asked whether settled)
                    take(receive(0.0))
                    if settled() or mono_ns() >= deadline:
                        break
                    sleep_until_ns(min(deadline, mono_ns() + 100_000))
                deadline = min(deadline, mono_ns())     # (the next one a period on)
            elif remaining > 0:
                # an absolute-deadline sleep, no spin: a SCHED_FIFO thread spinning to each
                # deadline is throttled by the kernel (sched_rt_runtime_us) under load
                sleep_until_ns(deadline)
            take(receive(0.0))
            if stop.set:
                break
            if stalled is not None:
                behind = mono_ns() - deadline
                late_ring[late_i] = behind if behind > period_ns else 0
                late_n += late_ring[late_i] - late_old
                late_i = (late_i + 1) % LATE_WINDOW
                late_old = late_ring[late_i]
                if late_n > LATE_STOP * LATE_WINDOW * period_ns:
                    # a board without a watchdog holds each torque as long as the host is
                    # late: a host that is late by half the time feeds the loop energy
                    # through the varying delay; stop before the device runs away
                    res.stop_reason = (f"safety: the host was {late_n / 1e6:.0f} ms late "
                                       f"over its last {LATE_WINDOW} ticks: it cannot hold "
                                       f"{rate:g} Hz here (a loaded machine without real-time "
                                       f"priority?); zero torque sent")
                    res.safety_stop = True
                    stop.set = True
                    break
                if behind > period_ns:
                    # the host is late (a descheduled process, a collection): the ticks it
                    # missed are not sent now in a burst -- the device held its force over
                    # them, a known input; a stall of STALL_TICKS or more is a gap in seq
                    # (the transport), so a measurement does not run across it
                    res.overruns += 1
                    self._host_late = 1
                    if behind >= STALL_TICKS * period_ns:
                        stalled(int(behind // period_ns))
                    deadline = mono_ns() if align is None else align(mono_ns())
            t_rx = perf()
            if (latest.seq - used_seq) & _U32 >= _HALF or latest.seq == used_seq:
                # no new sample since the last tick (or only one older than an estimated
                # tick already stepped through): stepping the engine with a stale
                # position would corrupt its velocity; skip this tick (counted), or, for a
                # driver whose answer is overdue, step it with an estimate (notes above)
                res.missed += 1
                if clock() - last_new >= silence - 1e-6:
                    raise _Lost(f"no STATE from the device for {silence:g} s")
                if overdue is not None and run_est < ESTIMATED_MAX and overdue():
                    # the position extrapolated from the last two records to this tick
                    # (NaN before two came), the STATE fields filled in place
                    x_e = estimate(est_state, (used_seq + 1) & _U32, cfg.delay)
                    if x_e == x_e:
                        run_est += 1
                        res.estimated += 1
                        used_seq = est_state.seq
                        self._skip_flag |= FLAG_ESTIMATED
                        yield est_state, x_e, t_rx
                        deadline += period_ns
                        continue
                if hold is not None:
                    hold()
                deadline += period_ns
                continue
            last_new = clock()
            used_seq = latest.seq
            run_est = 0
            yield latest, latest.position[0], t_rx   # _drive answers it (or stops)
            deadline += period_ns
            now = mono_ns()
            if now - deadline > period_ns:
                res.overruns += 1
                if stalled is not None:
                    # (answering took the host past the next deadline: a stall as above)
                    self._host_late = 1
                    if now - deadline >= STALL_TICKS * period_ns:
                        stalled(int((now - deadline) // period_ns))
                deadline = now


#: Host deadlines missed at once that a driver's run marks as a gap in seq (a host stall:
#: the device held its force over them): one. At 3 (before), a tick one or two periods late
#: went into the measurement as on time: the Haply M3 said "differs" (k +0.36 %) after one
#: such tick, unloaded; the row is also marked late (``_host_late``) where the transport
#: cannot skip seq (a command still unanswered).
STALL_TICKS = 1

"""A board that takes commands on its own tick (the Hapkit sketch's 0.992 ms): where the host's
writes fall in that tick, measured at the first arming, and the writes delayed into its
middle from then on (:class:`TickAligned`, a base of
:class:`hapsim.drivers.transport.DriverTransport`).

A write near the tick's boundary is taken at one tick or the next by the host's jitter:
sample intervals of 3 and 5 ms in a loop modelled at 4 ms, which no reply says. The probe
writes :data:`TICK_PROBES` zero-force commands a fraction of a tick apart and times their
replies: the write-to-reply time jumps by one tick at the board's boundary, whatever the
link's latency (docs/drivers.md, "Hapkit-serial: the sketch's tick").
"""

from __future__ import annotations

import math
import time

from hapsim.errors import DeviceError

__all__ = ["TickAligned", "TICK_PROBES", "PROBE_WAIT_S", "PROBE_QUIET_S", "PROBES_NEEDED",
           "PROBE_TRIES", "REARM_INTERVAL"]

#: Wait for the first record before the arming command is sent again [s].
REARM_INTERVAL = 0.1
#: Zero-force probes at an arming that measure where the host's writes fall in a board's
#: tick (a driver with ``tick_s``: :meth:`TickAligned.tick_phase`), spread over one
#: tick: the boundary is found to a sixteenth of a tick.
TICK_PROBES = 16
#: Longest wait for a ticking board's first answer before its tick is probed [s].
PROBE_WAIT_S = 2.0
#: The silence [s] after which a ticking board's backlog is taken as answered, before
#: its tick is probed (the Hapkit: a round trip of 3.3 ms and a tick, many times over).
PROBE_QUIET_S = 0.02
#: Probes (of :data:`TICK_PROBES`) that must be answered in time for a phase to be found.
PROBES_NEEDED = 12
#: Probes of a ticking board's phase tried at an arming before its writes go unaligned.
PROBE_TRIES = 3


class TickAligned:
    """The tick probe and the aligned writes of a driver transport whose board takes
    commands on its own tick (``driver.tick_s``): :meth:`tick_phase` at the first arming,
    :meth:`_wait_for_band` before each write. A base of
    :class:`hapsim.drivers.transport.DriverTransport`, whose port, clock and counters it
    uses (``_ser``, ``_write``, ``_drain``, ``driver``, ``info``, ``tick_probe``).
    """

    #: The band a write to a ticking board is kept in: from this fraction of a tick after
    #: the board's boundary (where a command arriving later is taken a tick later) to as
    #: much before the next. Leaving it re-centres the writes (a change of up to a tick
    #: once: one sample interval a tick long or short), so it is wide: the running means
    #: wander by a tenth of a tick on a loaded host, and a band of 0.3 re-centred often
    #: enough to make two runs in 12 say "differs".
    BAND = 0.15

    def _wait_for_band(self) -> None:
        """Delay a write to a ticking board by a constant (less than a tick) that puts the
        host's writes in the middle of the board's tick (:meth:`tick_phase`).

        The delay is not chosen per write (a rule "wait for the next middle unless in
        the band" has its own jump: writes near its edge are taken a tick apart by the
        jitter). The phase the host's writes come at by themselves (the loop's deadlines
        are whole ticks apart) is followed by a running circular mean, and how late the
        delay's sleep wakes by a running mean; the delay is changed only when the phase
        the writes then fall at leaves the band (:data:`BAND`: after a host stall moved
        the deadlines), to the one that puts them in the middle. It is added to every
        write, so the host's period is unchanged (a reply still has the rest of the
        period: 4 ms less the delay, at most a tick, for its tick and 1.56 ms of wire).
        """
        import cmath
        tk = self._tick_ns
        t = time.monotonic_ns()
        ph = (t - self._write_at) % tk               # 0 at the board's boundary
        u = cmath.exp(2j * math.pi * ph / tk)
        z = u if self._phase_z is None else 0.9 * self._phase_z + 0.1 * u
        self._phase_z = z
        mean = (cmath.phase(z) / (2 * math.pi) * tk) % tk
        # where the write will fall: the writes' own phase, the delay, and how late the
        # sleep for it wakes (a running mean too)
        lands = (mean + self._delay_ns + self._over_ns) % tk
        if not self.BAND * tk <= lands <= (1 - self.BAND) * tk:
            self._delay_ns = int((tk // 2 - mean - self._over_ns) % tk)
        if self._delay_ns > 0:
            due = t + self._delay_ns
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            over = min(max(time.monotonic_ns() - due, 0), tk // 2)
            self._over_ns = int(0.9 * self._over_ns + 0.1 * over)
        self._note_tick(time.monotonic_ns())

    def _note_tick(self, t_ns: int) -> None:
        """Where a write at ``t_ns`` falls on the board's tick grid: ``_write_tick`` =
        ``(tick index, near)``, the index counted from the probed boundary and ``near``
        whether it is within :data:`BAND` of a tick of a boundary (the probe places the
        boundary to a sixteenth of a tick; the link's latency varies too), where the board
        may take it at one tick or the other."""
        tk = self._tick_ns
        n, ph = divmod(t_ns - self._write_at, tk)
        self._write_tick = (int(n), min(ph, tk - ph) < self.BAND * tk)

    def tick_phase(self) -> dict | None:
        """Measure where the host's writes fall in the board's tick, and write in its
        middle from then on (a driver whose board takes commands on its own tick:
        ``driver.tick_s``).

        The board takes a command at its first tick after the command has come and its
        reply leaves then, so the time from a write to its reply, plus the write's phase
        within a tick, is one constant for writes before the board's boundary (the phase
        where a command comes just too late for a tick) and that constant plus one tick
        after it, whatever the link's latency in either direction: a step, located by
        :data:`TICK_PROBES` zero-force commands written at phases a sixteenth of a tick
        apart, their replies timed (the step fitted with the least sum of absolute
        deviations, each clipped at half a tick: a late reply moves no boundary). A
        write near the boundary is taken at one tick or the next by the jitter of the
        host and the link: a sample interval a tick short or long, another loop than the
        one modelled. The host's phase came from its latency at the arming (its first
        deadline is a third of a period after the arming's reply) and so could sit
        anywhere in the tick: on the Hapkit mock beside two CPU-bound processes one run
        of 20 had 77 % of its commands within a tenth of a tick of the boundary and 80 of
        its 375 sample intervals 3 or 5 ms instead of 4. From now on :meth:`_command`
        delays each write by a constant less than a tick that keeps the host's writes at
        least :data:`BAND` of a tick from the boundary (:meth:`_wait_for_band`). The
        board must answer first (zero-force commands, for at most :data:`PROBE_WAIT_S`,
        its backlog then dropped); a probe whose reply does not come within its spacing
        is left out, and at least :data:`PROBES_NEEDED` must be answered.

        Returns
        -------
        dict or None
            ``boundary_us`` (the jump's phase after the first probe's write, [us]),
            ``spread_us`` (the median distance of the probes from the fitted sawtooth),
            ``outliers`` (probes more than a quarter tick off it), ``probes``; None when
            the probe could not place the jump (no alignment). Also kept in
            :attr:`tick_probe`.

        Raises
        ------
        DeviceError
            The port failed.
        """
        import numpy as np
        dr = self.driver
        tk = self._tick_ns
        self._write_at = None
        self._phase_z = None
        self._delay_ns = 0
        self._over_ns = 0
        self.tick_probe = None
        k = TICK_PROBES
        # a probe's reply comes within the round trip and a tick; spaced whole ticks and
        # a sixteenth apart, the probes' phases sweep the tick once
        whole = int(math.ceil((dr.round_trip_s() * 1e9 + 2 * tk) / tk)) * tk
        step = whole + tk // k
        dec = dr.probe_decoder()
        ser = self._ser
        cmd = dr.encode_force(0.0)
        q, e = [], []
        try:
            # the board answering at all first (a board, or a mock process, still
            # starting drops what comes): a zero-force command each REARM_INTERVAL, for
            # at most PROBE_WAIT_S
            until = time.monotonic() + PROBE_WAIT_S
            up = False
            while not up and time.monotonic() < until:
                self._n_written += len(cmd)
                ser.write(cmd)
                end = time.monotonic() + REARM_INTERVAL
                while not up and time.monotonic() < end:
                    data = ser.read(max(ser.in_waiting, 1))
                    if data:
                        self._n_read += len(data)
                        up = bool(dec.feed(data))
            if not up:
                return None
            # the answers to the commands a board still starting took late, one a tick,
            # let come and dropped: a probe's reply is its own
            self._drain(PROBE_QUIET_S)
            dec = dr.probe_decoder()            # no partial frame left in it
            start = time.monotonic_ns() + tk
            for j in range(k):
                at = start + j * step
                wait = at - time.monotonic_ns()
                if wait > 0:
                    time.sleep(wait * 1e-9)
                if ser.in_waiting:
                    # a late reply to an earlier probe: this one would be timed by it
                    self._drain(PROBE_QUIET_S)
                    dec = dr.probe_decoder()
                    continue
                s = time.monotonic_ns()
                self._n_written += len(cmd)
                ser.write(cmd)
                got = None
                end = s + step - tk // k
                while got is None and time.monotonic_ns() < end:
                    data = ser.read(max(ser.in_waiting, 1))
                    if data:
                        self._n_read += len(data)
                        if dec.feed(data):
                            got = time.monotonic_ns()
                if got is None:
                    continue                # no reply in time: left out
                q.append((s - start) % tk)
                e.append(got - s)
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"probe of {self.info['port']} failed: {exc}") from None
        self._t_write = time.monotonic()
        n = len(q)
        if n < PROBES_NEEDED:
            self.tick_probe = {"probes": n}
            return None
        order = np.argsort(q)
        q = np.asarray(q, float)[order]
        v = np.asarray(e, float)[order] + q
        best = None
        for b in range(n):
            # writes at phases from the b-th (in phase order) on come too late for the
            # tick the ones before it are taken at: one tick more from write to reply
            w = v - tk * (np.arange(n) >= b)
            r = np.abs(w - np.median(w))
            cost = float(np.sum(np.minimum(r, tk / 2)))
            if best is None or cost < best[0]:
                best = (cost, b, r)
        _, b, r = best
        # the jump: midway between the last write before it and the first after it
        jump = 0.5 * ((q[b - 1] if b > 0 else q[-1] - tk) + q[b]) % tk
        spread = float(np.median(r))
        outliers = int(np.count_nonzero(r > tk / 4))
        found = {"boundary_us": float(jump) / 1e3, "spread_us": spread / 1e3,
                 "outliers": outliers, "probes": n}
        self.tick_probe = found
        if spread > tk / 8 or outliers > n // 4:
            return None                     # no clean sawtooth: the phase is not known
        self._write_at = start + int(jump)
        return found

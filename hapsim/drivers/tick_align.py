"""A board that takes commands on its own tick (the Hapkit sketch's 0.992 ms): where the host's
writes fall in that tick, measured at the first arming, and the writes delayed into its
middle from then on (:class:`TickAligned`, a base of
:class:`hapsim.drivers.transport.DriverTransport`).

A write near the tick's boundary is taken at one tick or the next by the host's jitter:
sample intervals of 3 and 5 ms in a loop modelled at 4 ms, which no reply says. The probe
writes :data:`TICK_PROBES` zero-force commands a fraction of a tick apart and times their
replies: the write-to-reply time jumps at the board's boundary, whatever the link's
latency (:func:`fit_tick_jump`; docs/drivers.md, "Hapkit-serial: the sketch's tick").
"""

from __future__ import annotations

import math
import time

from hapsim.errors import DeviceError

__all__ = ["TickAligned", "fit_tick_jump", "walk_from_placements", "agreeing_placement",
           "TICK_PROBES", "PROBE_WAIT_S", "PROBE_QUIET_S", "PROBES_NEEDED", "PROBE_TRIES",
           "ARM_AGREE", "END_PROBES",
           "END_FIRST", "END_GAP_S", "END_GAP_FRACTION", "END_GAP_MAX_S", "REARM_INTERVAL",
           "JUMP_STEPS", "FLAT_STEPS", "LANDED_BINS", "WRITE_LEAD", "SPIN"]

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
#: Sweeps of the probes made for ``k`` placements of a ticking board's boundary are at
#: most ``k + PROBE_TRIES - 1`` (a sweep with no clean fit places nothing): at a stop
#: (:meth:`TickAligned._placements`) and at the first arming, which needs two placements
#: that agree (:data:`ARM_AGREE`), before its writes go unaligned.
PROBE_TRIES = 3
#: Two placements of the boundary at the first arming must agree within this fraction
#: of a tick (:meth:`TickAligned.tick_phase`); the writes are aligned on the later one
#: (the nearest the writes in time: a board whose oscillator is off the host's walks
#: between the two). One sweep of the probes whose replies a loaded host read late in a
#: burst (3-6 probes in a row, 0.2-0.45 of a tick) still fits cleanly, its jump placed up
#: to half a tick off (29 of 1,000 seeded bursts more than 0.275 off in the in-process
#: model, tests/test_tick_arming.py), and the writes are never re-timed: beside two
#: CPU-bound processes and two other real-time test modules two runs in 59 placed it
#: 0.37 and 0.41 of a tick off (the stop's 8 placements agreeing on it), their commands
#: 282 of 478 at 0.1-0.2 of a tick from the boundary and 283 of 478 within a tenth of
#: it (none in 24 runs with the agreement). Measured between consecutive
#: placements of a board on the host's clock in those runs: 0.025 of a tick at the
#: median, 0.122 at the 99th percentile, 0.207 at most (406 pairs, 3 over 0.125: a pair
#: further apart costs a third sweep, ~0.1 s, not a wrong alignment). The placement
#: taken is within this and the other's error of the boundary (0.158 at worst over the
#: model's 1,000 seeds, all aligned; 0.2 let 0.206 through). A board whose oscillator is
#: more than ~1,400 ppm off the host's walks 0.15 of a tick between two placements (0.11
#: s apart) and is not aligned (a single sweep of it is smeared by as much).
ARM_AGREE = 0.15
#: Placements of a ticking board's boundary at each stop whose median says how far its
#: tick moved over the run (:meth:`TickAligned.end_probe`).
END_PROBES = 3
#: Placements in the first group at each stop: its own slope (the median of its pairs')
#: unwraps the whole ticks between the two groups (:func:`walk_from_placements`).
END_FIRST = 5
#: The wait at each stop between the first group of :data:`END_FIRST` placements and a
#: second [s]: the two groups' difference is the board's rate against the host's clock
#: (:func:`walk_from_placements`), which tells a walk of whole ticks over the run from
#: none (the placements alone see the walk only to the nearest whole tick). Over 0.4 s
#: a placement's error of a sixteenth of a tick is 160 ppm, 0.2 of a tick over a 1.3 s
#: run (the wait is from the first group's median).
END_GAP_S = 0.4
#: The second group's least distance from the first's median, as a share of the time
#: since the arming (:data:`END_GAP_S` for short runs), at most :data:`END_GAP_MAX_S`: the
#: rate's error is carried over the run, so the walk's deviation is the placements'
#: times the run over the distance. At a quarter, beside two CPU-bound processes, the
#: walk's deviation on a board on the host's clock was 0.19-0.26 of a tick and three of
#: them told a whole tick from none in 3 runs of 6; at a third, 2.9 times the
#: placements' 0.05.
END_GAP_FRACTION = 1 / 3
#: The longest wait [s] (a longer run's "differs" stands only where its rate's walk is
#: told from a whole tick).
END_GAP_MAX_S = 3.0
#: The writes' phases counted per write in this many bins of a tick (a histogram: the
#: loop appends nothing, :meth:`TickAligned.tick_landed_median`).
LANDED_BINS = 128
#: The fit's grids (:func:`fit_tick_jump`): the jump's phase to 1/128 of a tick, the flat
#: part's width to 1/16.
JUMP_STEPS = 128
FLAT_STEPS = 16
#: Where a write is made after the host loop's deadline once the deadlines are aligned
#: (:meth:`TickAligned.align_deadline`) [fraction of a tick]: the deadline is put this much
#: before the middle of the board's tick and the write is made at the middle itself,
#: whenever the host's wake-up and its tick's work took less (:meth:`TickAligned.
#: _write_on_grid`). A write made as soon as the tick's work was done came at the
#: deadline plus that work and the wake-up's latency, both varying: on the CI machine kind
#: (a virtual machine waking its halted CPUs 0.1-1 ms late) the writes' phases spread
#: with a standard deviation of 0.15-0.2 of a tick and a third of the rows were marked
#: mistimed, the Hapkit scene "not measurable" in 8 runs of 8.
WRITE_LEAD = 0.35
#: The last part of the wait for a write's time spent polling the clock instead of
#: sleeping [fraction of a tick]: a sleep's wake-up comes 0.07-0.3 ms late on such a
#: machine (a tick is 0.992 ms); at most this much CPU per write.
SPIN = 0.25


def fit_tick_jump(q, e, tick) -> dict:
    """Where a board that samples on its own tick changes the tick it takes a command at:
    the jump in the write-to-reply time over the write's phase, fitted.

    The Hapkit sketch (haphub/WHC2017 ``Hapkit_arduino.ino:96-135``, ``loop``) reads a
    command on the first tick of its Timer1 flag with a byte waiting (the header byte
    complete), waits in ``readBytes`` for the other 9, and samples the handle, renders and
    replies on the next flag: the tick after the read began, or at once when a tick passed
    during the read (the flag is one bit). With the command's last byte ``W`` after the
    first byte's end (9 bytes at 57600 baud: 1.5625 ms, more than a tick ``T``), the sample
    is ``max(c + W, k + T)`` for the first byte's end ``c`` and the read's tick ``k``: on the
    tick for ``x = c - (k - T)`` below ``L = 2 T - W`` (0.42 ms), ``W`` after ``c`` above it,
    and a jump of ``L`` where ``c`` crosses a tick. So the write-to-reply time ``e`` plus the
    write's phase ``q`` is, with ``x = (q - J) mod T`` the phase after the jump ``J``::

        e + q = C + max(x, L) - T [q < J]

    ``L = T`` is a board that samples on the tick after the whole command (a step of a
    tick, the model of this probe before); ``L = 0`` one that samples at the command's end
    (no jump: any phase will do). ``C`` (the link's latency, unknown) is the median, ``J``
    and ``L`` are searched on grids (:data:`JUMP_STEPS`, :data:`FLAT_STEPS`) for the least
    sum of absolute deviations, each clipped at half a tick (a late reply moves no jump).
    Measured on the independent sketch model (docs/drivers.md): 4 of 16 probes more than a
    quarter tick off the step alone (``L = T``), which is the refusal's threshold; the
    shape is the firmware's, not a tuning.

    Parameters
    ----------
    q : array_like, shape (n,)
        The writes' phases within a tick, in ``[0, tick)``, any time unit.
    e : array_like, shape (n,)
        Their write-to-reply times, the same unit.
    tick : float
        The board's tick, the same unit, > 0.

    Returns
    -------
    dict
        ``boundary_us`` (``J``: the jump's phase, in the unit / 1e3: microseconds for
        nanoseconds given), ``flat_us`` (``L``), ``spread_us`` (the median distance of the
        probes from the fit), ``outliers`` (probes more than a quarter tick off it),
        ``probes`` (``n``).

    Raises
    ------
    ValueError
        ``q`` and ``e`` of other lengths, or empty.
    """
    import numpy as np
    q = np.asarray(q, float)
    e = np.asarray(e, float)
    if q.shape != e.shape or q.ndim != 1 or q.size == 0:
        raise ValueError(f"q and e must be two equal non-empty vectors, got {q.shape}, "
                         f"{e.shape}")
    v = e + q
    tk = float(tick)
    J = np.arange(JUMP_STEPS)[:, None, None] * (tk / JUMP_STEPS)
    L = np.arange(FLAT_STEPS + 1)[None, :, None] * (tk / FLAT_STEPS)
    x = (q[None, None, :] - J) % tk
    m = np.maximum(x, L) - tk * (q[None, None, :] < J)
    w = v[None, None, :] - m
    r = np.abs(w - np.median(w, axis=2, keepdims=True))
    cost = np.minimum(r, tk / 2).sum(axis=2)
    # the least cost; on a tie the wider flat part (the step), and the middle of the run
    # of jumps between the same two probes (every jump there fits them alike: a step's
    # jump lies anywhere between the last probe before it and the first after it)
    rev = cost[:, ::-1]
    i, j = np.unravel_index(int(np.argmin(rev)), rev.shape)
    j = FLAT_STEPS - j
    tie = cost[:, j] == cost[i, j]
    lo = hi = 0
    while lo < JUMP_STEPS - 1 and tie[(i - lo - 1) % JUMP_STEPS]:
        lo += 1
    while hi < JUMP_STEPS - 1 - lo and tie[(i + hi + 1) % JUMP_STEPS]:
        hi += 1
    jump = ((i + 0.5 * (hi - lo)) % JUMP_STEPS) * (tk / JUMP_STEPS)
    rb = r[i, j]
    return {"boundary_us": jump / 1e3, "flat_us": float(L[0, j, 0]) / 1e3,
            "spread_us": float(np.median(rb)) / 1e3,
            "outliers": int(np.count_nonzero(rb > tk / 4)), "probes": int(q.size)}


def walk_from_placements(j0, tick_ns: int, first, second) -> dict:
    """How far a board's tick walked against the host's nominal grid since an arming,
    whole ticks counted, from two groups of placements of its boundary at a stop.

    A placement ``(b, t)`` is a boundary time ``b`` found by a probe that met it at ``t``
    [monotonic ns] (the probes sweep the tick over 0.1 s: a walking tick is placed where
    they met it). Its phase against the arming's boundary carried on at the nominal tick
    is ``p = fold((b - b0) / tick)``: the walk to the nearest whole tick; ``p_A`` (at
    ``t_A``) is the first group's median, its placements unwrapped one from the next (a
    tenth of a second apart). The rate ``r`` is the median of the slopes between each
    placement of the first group and each of the second (Theil-Sen: a placement a loaded
    host timed badly, an eighth of a tick off, moves it nothing), each pair's whole ticks
    unwrapped by the first group's own slope (the median of its pairs') where that says
    half a tick or more over the groups' distance. The walk over the run is ``p_A`` plus
    the whole number of ticks nearest ``r (t_A - t0) - p_A``. The rate's deviation is the
    pairs' (1.4826 times their median absolute deviation) scaled to the groups' medians'
    difference, ``1.25 sqrt((1/n_A + 1/n_B) / 2)`` (a median of ``n`` normal errors
    deviates 1.25 theirs over ``sqrt(n)``), and at least the probes' own (a placement
    uniform within a thirty-second of a tick, half their spacing, over the groups'
    distance); the walk's is the rate's times ``t_A - t0``.

    Parameters
    ----------
    j0 : tuple of int
        The arming's placement ``(b0, t0)`` [monotonic ns].
    tick_ns : int
        The board's nominal tick [ns], > 0.
    first, second : sequence of tuple of int
        Placements ``(b, t)`` [monotonic ns], each group a few a probe apart; ``second``
        may be empty.

    Returns
    -------
    dict
        ``moved`` (``p_A`` [ticks]), ``seconds`` (``t_A - t0`` [s]); with a ``second``
        group, ``walk`` (the run's walk [ticks], positive: the board slow), ``walk_rate``
        (``r (t_A - t0)`` [ticks]: the walk the rate alone says), ``walk_sd`` [ticks],
        ``rate_ppm`` (the walk per nominal tick, 1e6 times) and ``placements`` (each
        placement's time since the arming's [s] and phase [ticks], unwrapped in its
        group).

    Raises
    ------
    ValueError
        ``first`` empty.
    """
    if not len(first):
        raise ValueError("walk_from_placements needs at least one placement")
    tk = int(tick_ns)
    b0, t0 = (int(v) for v in j0)

    def fold(v: float) -> float:
        return (v + 0.5) % 1.0 - 0.5

    def group(g):
        """The placements' phases unwrapped in time order (each from the one before: a
        tenth of a second apart), and the median one's."""
        g = sorted((int(t), fold((int(b) - b0) / tk)) for b, t in g)
        out = [g[0]]
        for t, p in g[1:]:
            out.append((t, out[-1][1] + fold(p - out[-1][1])))
        tm, pm = out[len(out) // 2]
        shift = pm - fold(pm)                    # (the median's phase folded)
        return [(t, p - shift) for t, p in out], tm, pm - shift

    ga, t_a, p_a = group(first)
    out = {"moved": p_a, "seconds": (t_a - t0) * 1e-9}
    if not len(second):
        return out
    # the first group's own slope [ticks/ns]: the median of its pairs' (Theil-Sen; a
    # least-squares line through three placements a loaded host scattered by a fifth of a
    # tick unwrapped the groups' difference by a whole tick: a board on the host's clock
    # read -1,265 ppm)
    pair = sorted((pj - pi) / (tj - ti) for i, (ti, pi) in enumerate(ga)
                  for tj, pj in ga[i + 1:] if tj > ti)
    slope = pair[len(pair) // 2] if pair else 0.0
    gb, t_b, p_b = group(second)
    # the groups' whole ticks apart: the first group's slope carried over their distance,
    # where it says half a tick or more (a slope within its noise, a few tenths of a tick
    # a second on a loaded host, unwrapped a board on the host's clock by a whole tick)
    dt = t_b - t_a
    guess = slope * dt if abs(slope * dt) >= 0.5 else 0.0
    # the rate: the median of the slopes between each placement of the first group and
    # each of the second (Theil-Sen: a placement a loaded host timed badly moves it
    # nothing), each pair unwrapped by the guess
    rates = sorted((guess * (tb - ta) / dt + fold(pb - pa - guess * (tb - ta) / dt))
                   / (tb - ta) for ta, pa in ga for tb, pb in gb)
    r = rates[len(rates) // 2]
    mad = sorted(abs(v - r) for v in rates)[len(rates) // 2]
    # a pair's deviation is sqrt(2) placements' over the distance; the median of the
    # pairs is about the groups' medians' difference, whose deviation is
    # 1.25 sqrt(1/n_A + 1/n_B) placements' (a median's efficiency for normal errors)
    scale = 1.25 * math.sqrt((1.0 / len(ga) + 1.0 / len(gb)) / 2.0)
    # at least the probes' own: a placement to within half their spacing (a
    # thirty-second of a tick), uniformly: 1/32/sqrt(3) a placement
    sd_r = scale * max(1.4826 * mad, math.sqrt(2.0 / 3.0) / 32 / dt)
    w_rate = r * (t_a - t0)
    out.update(walk=p_a + round(w_rate - p_a), walk_rate=w_rate,
               walk_sd=sd_r * (t_a - t0), rate_ppm=r * tk * 1e6,
               placements=[[round((t - t0) * 1e-9, 4), round(p, 4)] for t, p in ga + gb])
    return out


def agreeing_placement(placed, new, tick_ns: int):
    """The boundary the writes are aligned on at an arming: ``new``, when one of the
    earlier placements ``placed`` agrees with it within :data:`ARM_AGREE` of a tick
    (whole ticks apart or not); None when none does.

    A placement is one sweep of the probes (:meth:`TickAligned._probe_boundary`), to about
    a sixteenth of a tick; one whose replies a loaded host read late in a burst fits
    cleanly with its jump up to half a tick off (:data:`ARM_AGREE`). Two sweeps a burst
    left alone agree; one it moved agrees with neither. The later of the two is taken,
    the nearest the writes in time (a board whose oscillator is off the host's walks
    its tick between them: 0.09 of a tick at 790 ppm).

    Parameters
    ----------
    placed : sequence of tuple of int
        Earlier placements ``(boundary, t)`` [monotonic ns]: a boundary's time and when
        the sweep met it.
    new : tuple of int
        The latest placement, the same form.
    tick_ns : int
        The board's tick [ns], > 0.

    Returns
    -------
    tuple of int or None
        ``new`` as ``(boundary, t)`` [monotonic ns] when a placement agrees, else None.
    """
    tk = int(tick_ns)
    b1, t1 = (int(v) for v in new)
    for b0, _ in placed:
        d = ((b1 - int(b0)) / tk + 0.5) % 1.0 - 0.5          # [ticks], folded
        if abs(d) <= ARM_AGREE:
            return b1, t1
    return None


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
        if self._grid_ns and t >= self._aligned_ns:
            self._write_on_grid(t)
            return
        if t < self._aligned_ns:
            # a write before the deadline the host loop was just put on (the one it makes
            # when it wakes from a stall, :meth:`align_deadline`) is on no grid of the
            # writes: taken for their phase, it set a delay that put the aligned writes
            # after it near the boundary, each marked and cut, until the running mean
            # forgot it (15-20 writes after each stall on a host stopped 10 ms in 100)
            self._note_tick(t)
            return
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

    def align_deadline(self, deadline_ns: int) -> int:
        """The host loop's deadline ``deadline_ns`` [monotonic ns] moved on (by less than
        a tick) to where a write made at it lands in the middle of the board's tick (the
        aim of :meth:`_wait_for_band`, less how late its sleeps wake): the loop's reads
        then come a whole period after its writes, the answer's time (a write delayed
        after its deadline leaves the answer the period less that delay). Unchanged before
        a probe found the tick (:meth:`tick_phase`).

        Parameters
        ----------
        deadline_ns : int
            The loop's next deadline [monotonic ns].

        Returns
        -------
        int
            The aligned deadline [monotonic ns], less than a tick after ``deadline_ns``.
        """
        if self._write_at is None:
            return int(deadline_ns)
        tk = self._tick_ns
        lead = self._over_ns
        if self._period_ticks:
            # the writes on the deadlines' grid, each at the middle of its tick
            # (_write_on_grid): the deadline WRITE_LEAD of a tick before it
            self._grid_ns = int(getattr(self, "_grid_period_ns", 0)
                                or int(self._period_ticks) * tk)
            lead = int(WRITE_LEAD * tk)
        shift = (tk // 2 - lead - (int(deadline_ns) - self._write_at)) % tk
        # the writes' own phase starts again at the middle: no delay of its own (one
        # set by the arming's writes, made between deadlines, would stay while the writes
        # it moved stayed in the band, the answer's time short by it); the writes before
        # the new deadline are on no grid (:meth:`_wait_for_band`)
        self._phase_z = None
        self._delay_ns = 0
        self._aligned_ns = int(deadline_ns) + int(shift)
        return self._aligned_ns

    def _host_period(self, rate_hz: float):
        """The host loop's period at ``rate_hz`` [Hz], kept on the host loop's own grid
        [ns] (its deadlines are ``round(1e9 / rate)`` apart: :meth:`_write_on_grid` counts
        them so, however far a whole number of ticks drifts from it over a long run);
        returns the period in whole ticks of the board (``driver.period_ticks``), or
        None."""
        self._grid_period_ns = int(round(1e9 / float(rate_hz)))
        return self.driver.period_ticks(float(rate_hz))

    def _write_on_grid(self, t: int) -> None:
        """Wait for the time of this tick's write on the aligned deadlines' grid: the
        deadline the loop woke for, ``t`` [monotonic ns] after it, plus :data:`WRITE_LEAD`
        of a tick (the middle of the board's tick, :meth:`align_deadline`), slept to
        within :data:`SPIN` of a tick and polled for the rest; at once when ``t`` is past
        it (a late tick: its phase noted where it falls). The deadlines are whole periods
        apart, each a whole number of ticks, so the writes are too: no write waits for
        another tick than its own."""
        tk = self._tick_ns
        g = self._grid_ns
        due = self._aligned_ns + (t - self._aligned_ns) // g * g + int(WRITE_LEAD * tk)
        rest = due - t
        if rest > 0:
            if rest > SPIN * tk:
                time.sleep((rest - SPIN * tk) * 1e-9)
            while time.monotonic_ns() < due:
                pass
        self._note_tick(time.monotonic_ns())

    def end_probe(self) -> dict | None:
        """At each stop, probe the board's tick again and say how far it walked against
        the host's writes since the first arming (``driver.tick_moved``, also returned):
        a board whose oscillator is off the host's clock walks its tick across writes
        aligned once (docs/drivers.md, "A board whose oscillator is off the host's
        clock"), and a walk changes the loop's delay within the record.

        The probe is :meth:`tick_phase`'s measurement (:meth:`_probe_boundary`: its
        zero-force commands), :data:`END_FIRST` placements, and :data:`END_PROBES`
        :data:`END_GAP_S` after the first's median, or a third of the time since the
        arming (:data:`END_GAP_FRACTION`, at most :data:`END_GAP_MAX_S`; the board holding
        the probes' zero force between): :func:`walk_from_placements` gives the walk to
        the nearest whole tick (``moved``, the first group's median against the arming's
        boundary carried on at the nominal tick, folded into half a tick either way), and
        the whole ticks from
        the board's rate between the groups (``walk``, ``walk_rate``, ``walk_sd``,
        ``rate_ppm``); ``seconds`` is the time since the arming [s], ``found`` whether
        both groups placed the boundary (each placement to about a sixteenth of a tick;
        the walk during a probe's own 0.1 s shifts it too). The alignment and
        :attr:`tick_probe` are left as they were. None where the writes were not aligned
        (no probe at the arming, lockstep). The probes and the wait take about 0.9 s
        before the stop's bytes, and a third of the run more for a run over 1.2 s.

        Returns
        -------
        dict or None
            :func:`walk_from_placements`'s dict and ``found``.
        """
        if self._write_at is None:
            return self.driver.tick_moved
        before = self.driver.tick_moved            # (a stop before this one's)
        j0 = (self._write_at, self._write_at_t)
        first = self._placements(END_FIRST)
        second = []
        if first:
            t1 = sorted(t for _, t in first)[len(first) // 2]      # (the group's median)
            gap = min(max(END_GAP_S, END_GAP_FRACTION * (t1 - j0[1]) * 1e-9), END_GAP_MAX_S)
            wait = t1 + int(gap * 1e9) - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            second = self._placements()
        found = bool(first) and bool(second)
        if first:
            got = walk_from_placements(j0, self._tick_ns, first, second)
        else:
            got = {"moved": 0.0, "seconds": (time.monotonic_ns() - j0[1]) * 1e-9}
        if before is not None and not before["found"]:
            found = False                          # (a probe at an earlier stop failed)
        self.driver.tick_moved = {**got, "found": found}
        return self.driver.tick_moved

    def _placements(self, k: int = END_PROBES) -> list:
        """``k`` placements of the boundary ``(boundary, time)`` [monotonic ns] (one probe
        a loaded host timed badly places it up to an eighth of a tick off: 0.15 seen on
        the wall clock beside two CPU-bound processes), with as many refusals as the
        arming allows; fewer when the port failed."""
        got = []
        try:
            for _ in range(k + PROBE_TRIES - 1):
                found, at = self._probe_boundary()
                if at is not None:
                    got.append((at, found["t_ns"]))
                    if len(got) == k:
                        break
        except DeviceError:
            pass
        return got

    def tick_landed_median(self) -> float | None:
        """Where the writes went, on the host's clock: the median phase after the jump the
        probe found [fraction of a tick] (the aim: a half), to :data:`LANDED_BINS` of a
        tick (the middle of its bin); None before any.

        Returns
        -------
        float or None
            A fraction of a tick, in (0, 1).
        """
        bins = getattr(self, "_landed", None)
        n = sum(bins) if bins else 0
        if not n:
            return None
        seen = 0
        for i, c in enumerate(bins):
            seen += c
            if 2 * seen > n:
                return (i + 0.5) / LANDED_BINS

    def _note_tick(self, t_ns: int) -> None:
        """Where a write at ``t_ns`` falls on the board's tick grid: ``_write_tick`` =
        ``(tick index, near)``, the index counted from the probed boundary and ``near``
        whether it is within :data:`BAND` of a tick of a boundary (the probe places the
        boundary to a sixteenth of a tick; the link's latency varies too), where the board
        may take it at one tick or the other."""
        tk = self._tick_ns
        n, ph = divmod(t_ns - self._write_at, tk)
        self._write_tick = (int(n), min(ph, tk - ph) < self.BAND * tk)
        self._landed[ph * LANDED_BINS // tk] += 1      # (ints: nothing allocated)

    def tick_phase(self) -> dict | None:
        """Measure where the host's writes fall in the board's tick, and write in its
        middle from then on (a driver whose board takes commands on its own tick:
        ``driver.tick_s``).

        The board reads a command at its first tick after the command's first byte has
        come and samples at the tick after that, or at the command's end when that is
        later, so the time from a write to its reply, plus the write's phase within a
        tick, is flat then rising over the tick and jumps back where the first byte
        comes just too late for a tick (the board's boundary), whatever the link's
        latency in either direction: a shape located by :data:`TICK_PROBES` zero-force
        commands written at phases a sixteenth of a tick apart, their replies timed
        (:func:`fit_tick_jump`: least absolute deviations, each clipped at half a tick:
        a late reply moves no boundary). A
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
        is left out, and at least :data:`PROBES_NEEDED` must be answered. The sweep is
        made again until two placements agree within :data:`ARM_AGREE` of a tick
        (:func:`agreeing_placement`, the later taken; at most ``1 + PROBE_TRIES`` sweeps):
        the writes are never re-timed after it, and one sweep a loaded host read in a
        burst of late replies places the boundary up to half a tick off with a clean fit,
        which put a whole run's writes at the boundary (their median 0.09 of a tick after
        it).

        Returns
        -------
        dict or None
            ``boundary_us`` (the jump's phase after the first probe's write, [us]),
            ``flat_us`` (the phases after it sampled on the tick, [us]), ``spread_us``
            (the median distance of the probes from the fit), ``outliers`` (probes more
            than a quarter tick off it), ``probes`` (:func:`fit_tick_jump`); None when
            the probe could not place the jump (no alignment); the last sweep's, with
            ``placements`` (the boundaries placed; the last of them one of the agreeing
            pair). Also kept in :attr:`tick_probe` (there also when None is returned,
            None when no sweep was answered).

        Raises
        ------
        DeviceError
            The port failed.
        """
        self._write_at = None
        self._phase_z = None
        self._delay_ns = 0
        self._over_ns = 0
        self._aligned_ns = 0                         # (the last aligned deadline)
        self._grid_ns = 0                            # (their period, once aligned)
        self._landed = [0] * LANDED_BINS
        self.tick_probe = None
        placed = []
        found = None
        for _ in range(1 + PROBE_TRIES):                 # (two placements' sweeps)
            found, at = self._probe_boundary()
            if at is None:
                continue                    # (no clean fit: this sweep places nothing)
            pair = agreeing_placement(placed, (at, found["t_ns"]), self._tick_ns)
            placed.append((at, found["t_ns"]))
            if pair is not None:
                self._write_at, self._write_at_t = pair
                self.tick_probe = {**found, "placements": len(placed)}
                return self.tick_probe
        # (no two agree, or fewer than two placed: the phase is not known)
        self.tick_probe = None if found is None else {**found, "placements": len(placed)}
        return None

    def _probe_boundary(self) -> tuple:
        """:meth:`tick_phase`'s measurement, the alignment left as it is: ``(finding,
        boundary)``, the fit (:func:`fit_tick_jump`'s dict; ``{"probes": n}`` when too few
        were answered; None when the board did not answer) and the monotonic time [ns] of
        a boundary it placed (None when it placed none).

        Raises
        ------
        DeviceError
            The port failed.
        """
        dr = self.driver
        tk = self._tick_ns
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
                return None, None
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
            return {"probes": n}, None
        found = fit_tick_jump(q, e, tk)
        if found["spread_us"] * 1e3 > tk / 8 or found["outliers"] > n // 4:
            return found, None              # no clean fit: the phase is not known
        # the probe that met the boundary is the one whose phase is the jump's: its write
        # is the time of the placement (the probes sweep the tick over 0.1 s, and a
        # walking tick is where they met it then, not at the first)
        J = int(round(found["boundary_us"] * 1e3))
        found["t_ns"] = start + int(round(J * k / tk)) * step
        return found, start + J

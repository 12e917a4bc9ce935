"""The Hapkit sketch takes commands on its own 0.992 ms tick: the host writes in its middle.

The sketch reads the handle and applies a command's force at its first tick after the
command has come (:class:`hapsim.emulated.driver_mock.HapkitSerialDevice`). A host whose
writes come near a tick's boundary has them taken at one tick or the next by its jitter:
sample intervals of 3 and 5 ticks in a loop modelled at 4. Where the host's writes fell
was an accident of its latency at the arming (its first deadline is a third of a period
after the arming's reply): beside two CPU-bound processes one run in 20 had 77 % of its
commands within a tenth of a tick of the boundary. The transport now measures the
boundary at the first arming (:meth:`hapsim.drivers.transport.DriverTransport.tick_phase`) and
delays its writes into the tick's middle; the driver refuses a rate whose period is no
whole number of ticks (the sampling would alternate by construction).

In process, a board on a tick grid of its own (a phase and a link latency chosen by the
test, both unknown to the host): the probe finds the boundary, and writes the host makes
exactly at the boundary reach the board mid-tick. Over a pty, beside two CPU-bound
processes: the closed loop on the board's own clock is within the stated uncertainty, and
a hidden friction the scene does not state is still seen.
"""

from __future__ import annotations

import struct
import time
from collections import deque

import numpy as np
import pytest

from hapsim.drivers import hapkit_serial as hk
from hapsim.drivers.tick_align import TICK_PROBES
from hapsim.drivers.transport import DriverTransport
from hapsim.errors import ConfigError

#: The sketch's Timer1 tick [ns] (62 counts of 16 us: 0.992 ms, hk.FIRMWARE_TICK_S).
TICK_NS = 992_000
assert TICK_NS == round(hk.FIRMWARE_TICK_S * 1e9)
#: The reply's 9 bytes at 57600 baud [ns] (the sketch's reply leaves at its tick).
WIRE_NS = 9 * 10 * 10**9 // 57600


#: One byte's time on the wire at 57600 baud [ns] (10 bits).
BYTE_NS = 10 * 10**9 // 57600
#: The sketch's render, from its read of the handle to its reply's write [ns]
#: (hk.RENDER_S).
RENDER_NS = round(hk.RENDER_S * 1e9)


class TickingPort:
    """A serial port whose far end is the sketch's tick (ticks at ``phase_ns`` plus whole
    ``TICK_NS``, on the monotonic clock); a command written at ``t`` comes at
    ``t + transit_ns``.

    ``sketch=False``: a board that takes it at the first tick after that, its reply
    readable ``WIRE_NS`` after that tick (a step of one tick in the write-to-reply time:
    the model of the probe before). ``sketch=True``: the sketch's ``loop``
    (haphub/WHC2017 ``Hapkit_arduino.ino:96-135``), written here from its lines, not from
    the probe's fit: the header byte complete ``BYTE_NS`` after the arrival, read at the
    first tick from then, the 9 more bytes read as they come (the command's end ``10
    BYTE_NS`` after the arrival), the handle read at the next flag (the tick after the
    read's, or at once at the command's end when a tick passed during the read: a one-bit
    flag), the reply written ``RENDER_NS`` later and readable ``WIRE_NS`` after that.
    ``arrivals`` keeps each command's arrival phase within its tick [ns after the tick
    before it: the header's end for the sketch, where its jump is] and ``ticks`` the tick
    it was taken (read) at. ``numbered``: each reply's position is 1e-4 m times the
    number of the write it answers (1, 2, ...). ``tick_ns``: its tick on the host's clock
    (a board whose oscillator is off it; default ``TICK_NS``)."""

    def __init__(self, phase_ns: int, transit_ns: int, sketch: bool = False,
                 numbered: bool = False, tick_ns: float = TICK_NS) -> None:
        self.tick = tick_ns if isinstance(tick_ns, int) else float(tick_ns)
        self.phase = int(phase_ns)
        self.transit = int(transit_ns)
        self.sketch = bool(sketch)
        self.numbered = bool(numbered)
        self.writes = 0
        self.pending: deque = deque()
        self.rx = bytearray()
        self.arrivals: list = []
        self.ticks: list = []
        self.timeout = 0.005

    def _move(self) -> None:
        now = time.monotonic_ns()
        while self.pending and self.pending[0][0] <= now:
            self.rx += self.pending.popleft()[1]

    @property
    def in_waiting(self) -> int:
        self._move()
        return len(self.rx)

    def write(self, data: bytes) -> int:
        arr = time.monotonic_ns() + self.transit
        tk = self.tick
        if self.sketch:
            head = arr + BYTE_NS
            k = -((self.phase - head) // tk)               # the first tick at or after
            self.arrivals.append((head - self.phase) % tk)
            self.ticks.append(k)
            read = max(arr + 10 * BYTE_NS, self.phase + (k + 1) * tk)
            ready = read + RENDER_NS + WIRE_NS
        else:
            k = (arr - self.phase) // tk + 1
            self.arrivals.append((arr - self.phase) % tk)
            self.ticks.append(k)
            ready = self.phase + k * tk + WIRE_NS
        # the reply's position names the write it answers (1e-4 m a write), the
        # handle's for a test that does not ask (0.01 m)
        self.writes += 1
        x = 1e-4 * self.writes if self.numbered else 0.01
        # the sketch's reply carries the Tp of the force it rendered (sim.h:191)
        from hapsim.drivers.output_stage import sketch_tp
        tp = float(sketch_tp([struct.unpack_from("<f", data, 6)[0]])[0])
        self.pending.append((ready, hk.reply_packet(hk.HOST_FORCE_FUNCTION, x, tp)))
        return len(data)

    def read(self, n: int = 1) -> bytes:
        end = time.monotonic_ns() + int(self.timeout * 1e9)
        while True:
            self._move()
            if self.rx:
                out = bytes(self.rx[:n])
                del self.rx[:n]
                return out
            now = time.monotonic_ns()
            if now >= end:
                return b""
            nxt = self.pending[0][0] if self.pending else end
            time.sleep(max(min(nxt, end) - now, 0) * 1e-9)

    def set_low_latency_mode(self, on: bool) -> None:
        raise NotImplementedError("a test port")

    def close(self) -> None:
        pass


class SimClock:
    """Simulated time for the host, its transport and the test's board alike: each reading
    moves it 2 us on (the host's own work between two readings), a sleep by its length.
    The in-process board's ticks are then exact whatever the machine's load (in real time
    a loaded CI run, both workers busy, preempted this process between a write's time
    stamp and the write: a probe with 6 outliers, refused)."""

    def __init__(self) -> None:
        self.t = 10**12

    def monotonic_ns(self) -> int:
        self.t += 2_000
        return self.t

    def monotonic(self) -> float:
        return self.monotonic_ns() * 1e-9

    def perf_counter(self) -> float:
        return self.monotonic()

    def sleep(self, d) -> None:
        self.t += max(int(float(d) * 1e9), 0)


def _transport(monkeypatch, port: TickingPort) -> DriverTransport:
    import sys
    import types

    import serial

    from hapsim.drivers import tick_align, transport
    clk = SimClock()
    fake = types.SimpleNamespace(monotonic_ns=clk.monotonic_ns, monotonic=clk.monotonic,
                                 perf_counter=clk.perf_counter, sleep=clk.sleep)
    for mod in (tick_align, transport, sys.modules[__name__]):
        monkeypatch.setattr(mod, "time", fake)
    monkeypatch.setattr(serial, "serial_for_url", lambda *a, **k: port)
    return DriverTransport(hk.HapkitSerial(), "ticking://test", delay=1)


def _near(phases, frac: float = 0.1) -> float:
    """Fraction of arrival phases [ns] within ``frac`` of a tick of its boundary."""
    p = np.asarray(phases, float) / TICK_NS
    return float(np.mean((p < frac) | (p > 1 - frac)))


@pytest.mark.parametrize("sketch", [False, True], ids=["step", "sketch"])
@pytest.mark.parametrize("phase_us, transit_us", [(0, 0), (300, 200), (700, 1300),
                                                  (950, 40)])
def test_the_probe_finds_the_boundary_and_the_writes_come_mid_tick(monkeypatch, phase_us,
                                                                   transit_us, sketch):
    """The probe at arming places the boundary (the write time whose command comes just
    too late for a tick: the board's phase less the link's transit, neither known to the
    host) to within an eighth of a tick: half the probes' spacing (a sixteenth of a tick)
    for the midpoint between the two probes either side of it, and the write's time stamp
    (taken just before the write: microseconds, unless the test process is preempted
    there; the fit's clipped deviations absorb most of that, not all: 64 us off in a
    fresh-clone CI run in real time, against the sixteenth, 62.5 us, this test held it
    to before; the host and the board now share a simulated clock, :class:`SimClock`, as
    a real board's ticks are exact whatever the host's load). An eighth is far inside
    what the alignment needs: the writes are put half a tick from the boundary and
    re-centred only within 0.15 of a tick of it. On the sketch's loop (``sketch``) the
    boundary is where the header byte comes just too late for a tick: the write-to-reply
    time there is flat, then rising, then jumps by 0.42 ms, not a tick (the step's fit
    counted 4 of 16 probes as outliers there, its refusal threshold: the independent
    sketch model refused 4 runs in 10 so). Then 60 writes the host makes at
    a period of 4 ticks at that boundary (the worst phase its latency can give it; the test
    process's own lateness measured over 20 writes and taken off), jittered by +-50 us:
    unaligned, their median arrival is within 0.15 tick of the boundary (asserted: the
    test's board is a real tick and the writes are at its jump); aligned, the median
    arrival is at least 0.15 tick from the boundary and at most a quarter come within a
    tenth of a tick of the boundary (the band the delay keeps the writes in is 0.15 from
    it; what comes nearer is the test process's sleep overshooting by more: measured 0
    to 13 % of 60 beside a load of 4, so the bound has a margin of about 2)."""
    port = TickingPort(phase_us * 1000, transit_us * 1000, sketch=sketch)
    tr = _transport(monkeypatch, port)
    found = tr.tick_phase()
    assert found is not None, tr.tick_probe
    assert found["probes"] >= TICK_PROBES - 4
    assert found["outliers"] == 0, found
    truth = (port.phase - port.transit - (BYTE_NS if sketch else 0)) % TICK_NS
    err = (tr._write_at - truth + TICK_NS // 2) % TICK_NS - TICK_NS // 2
    # measured 64 us at worst (a fresh-clone CI run, both workers busy), margin 2
    assert abs(err) <= TICK_NS // 8, (err, found)
    rng = np.random.default_rng(phase_us)
    cmd = tr.driver.encode_force(0.0)

    def writes(aligned: bool, shift: int = 0, n: int = 60) -> list:
        port.arrivals.clear()
        at = tr._write_at + TICK_NS * (1 + (time.monotonic_ns() - tr._write_at) // TICK_NS)
        saved = tr._write_at
        if not aligned:
            tr._write_at = None
        for j in range(n):
            due = at - shift + j * 4 * TICK_NS + int(rng.uniform(-50e3, 50e3))
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            tr._command(cmd)
        tr._write_at = saved
        return list(port.arrivals)

    # the test process's own lateness (its sleep's overshoot and the call): taken off the
    # natural write times, so that they come at the boundary
    late = (np.asarray(writes(False, n=20)) + TICK_NS // 2) % TICK_NS - TICK_NS // 2
    shift = int(np.median(late))
    raw = writes(False, shift)
    signed = (np.asarray(raw) + TICK_NS // 2) % TICK_NS - TICK_NS // 2
    assert abs(np.median(signed)) <= 0.15 * TICK_NS, sorted(raw)   # at the jump
    got = writes(True, shift)
    med = float(np.median(got)) / TICK_NS
    # the bound is the band's, derived: the writes are re-centred only where they come
    # within 0.15 of a tick of the boundary, so their median stays within 0.5 - 0.15
    assert abs(med - 0.5) <= 0.5 - 0.15, (med, sorted(got))
    assert _near(got) <= 0.25, sorted(got)


@pytest.mark.parametrize("phase_us, transit_us", [(300, 200), (950, 40)])
def test_writes_the_host_made_a_tick_late_are_marked_and_cut(monkeypatch, phase_us,
                                                             transit_us):
    """On the simulated board's tick (its truth: the tick that took each command), the
    aligned writes of a 4-tick period, one in ten made late by 0.6-0.9 of a tick by the host
    (its own lateness, which it sees): every write the board took at another number of
    ticks after the one before than the period's is marked (``mistimed``), and so is the
    write after it; no write taken at the period's tick both before and after is marked
    unless it came within the band of a boundary. The measurement's mask
    (:meth:`hapsim.drivers.base.Driver.mistimed_rows`) then holds rows ``k - 1`` and
    ``k`` of each marked tick ``k``."""
    port = TickingPort(phase_us * 1000, transit_us * 1000)
    tr = _transport(monkeypatch, port)
    assert tr.tick_phase() is not None, tr.tick_probe
    tr._period_ticks = 4
    rng = np.random.default_rng(phase_us)
    cmd = tr.driver.encode_force(0.0)
    port.ticks.clear()
    at = time.monotonic_ns()
    late_seqs = set()
    for seq in range(200):
        due = at + seq * 4 * TICK_NS
        if seq % 10 == 5:
            due += int(rng.uniform(0.6, 0.9) * TICK_NS)
            late_seqs.add(seq)
        wait = due - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait * 1e-9)
        tr._write_tick = None
        tr._command(cmd)
        tr._note_hold(seq)
    ticks = np.asarray(port.ticks)
    off = {i for i in range(1, len(ticks)) if ticks[i] - ticks[i - 1] != 4}
    assert off, "the late writes moved no hold"
    assert off <= tr.mistimed, (sorted(off - tr.mistimed), sorted(tr.mistimed))
    # every late write is the start of an off hold (the board took it a tick later)
    assert late_seqs <= off
    # nothing else marked but writes near a boundary
    assert len(tr.mistimed - off) <= 0.1 * 200, sorted(tr.mistimed - off)
    seqs = np.arange(200)
    mask = tr.driver.mistimed_rows({"seq": seqs})
    want = np.isin(seqs, sorted(tr.mistimed))
    want[:-1] |= want[1:]
    assert np.array_equal(mask, want)


def test_a_deadline_is_put_where_its_write_lands_mid_tick(monkeypatch):
    """After the probe, the host loop's deadline is moved on (by less than a tick) to where
    a write made at it lands half a tick after the jump found, and the writes' own delay
    starts again at 0: a write delayed after its deadline left the answer the period less
    that delay (up to a tick), and the sketch's answer, 3.5-4.3 ms after a write at 4
    ticks a period, came after the next deadline."""
    port = TickingPort(300_000, 200_000, sketch=True)
    tr = _transport(monkeypatch, port)
    assert tr.tick_phase() is not None, tr.tick_probe
    tr._delay_ns = 123_000                       # a delay the arming's writes had set
    for t in np.linspace(10**12, 10**12 + 3 * TICK_NS, 7).astype(np.int64):
        d = tr.align_deadline(int(t))
        assert 0 <= d - t < TICK_NS
        assert (d - tr._write_at) % TICK_NS == TICK_NS // 2 - tr._over_ns
        assert tr._delay_ns == 0 and tr._phase_z is None


@pytest.mark.parametrize("seed", range(6))
def test_on_the_aligned_grid_each_write_comes_mid_tick_whatever_the_hosts_lateness(
        monkeypatch, seed):
    """Once the host loop's deadlines are aligned (a period of whole ticks known), each
    write is made at its deadline plus ``WRITE_LEAD`` of a tick, the middle of the board's
    tick, however late the host woke and worked within that (``_write_on_grid``): over
    random boards (phase, link, 4 or 5 ticks a period) and host lateness of 0-0.3 of a
    tick, the sketch's header bytes all arrive at one phase of its tick -- a spread of a
    few of the simulated clock's 2-us steps (the polling's last step and the readings
    between it and the write; measured 2 us, bound 10 us), where before each write came
    at its deadline plus the host's lateness (a spread of 0.3 of a tick, 300 us) -- within
    an eighth of a tick of the middle (the probe's own error,
    test_the_probe_finds_the_boundary_and_the_writes_come_mid_tick), and every hold the
    board took is the period's. A write the host makes later than the lead (0.6-0.9 of a
    tick after its deadline, one in nine) is made at once, where it falls: each hold of
    another number of ticks is marked mistimed (the class of
    test_writes_the_host_made_a_tick_late_are_marked_and_cut)."""
    from hapsim.drivers import transport as transport_mod
    from hapsim.drivers.tick_align import WRITE_LEAD
    rng = np.random.default_rng(seed)
    port = TickingPort(int(rng.uniform(0, TICK_NS)), int(rng.uniform(0, 1.5e6)), sketch=True)
    tr = _transport(monkeypatch, port)
    assert tr.tick_phase() is not None, tr.tick_probe
    clk = transport_mod.time                     # the simulated clock (_transport)
    per = int(rng.choice([4, 5]))
    tr._period_ticks = per
    deadline = tr.align_deadline(clk.monotonic_ns())
    assert (deadline - tr._write_at) % TICK_NS == TICK_NS // 2 - int(WRITE_LEAD * TICK_NS)
    cmd = tr.driver.encode_force(0.0)
    port.arrivals.clear()
    port.ticks.clear()
    late = set()
    for k in range(90):
        lateness = rng.uniform(0.0, 0.3)
        if k % 9 == 4:
            lateness = rng.uniform(0.6, 0.9)
            late.add(k)
        clk.sleep(max(deadline + k * per * TICK_NS + int(lateness * TICK_NS)
                      - clk.monotonic_ns(), 0) * 1e-9)
        tr._write_tick = None
        tr._command(cmd)
        tr._note_hold(k)
    on = [k for k in range(90) if k not in late]
    arr = np.asarray(port.arrivals, float)
    assert np.ptp(arr[on]) <= 10_000, np.ptp(arr[on])
    assert abs(np.median(arr[on]) - TICK_NS / 2) <= TICK_NS / 8, np.median(arr[on])
    ticks = np.asarray(port.ticks)
    off = {k for k in range(1, 90) if ticks[k] - ticks[k - 1] != per}
    assert not off - late - {k + 1 for k in late}, sorted(off)     # only around late ones
    assert off <= tr.mistimed, (sorted(off - tr.mistimed), sorted(tr.mistimed))


@pytest.mark.parametrize("seed", range(8))
def test_the_write_made_on_waking_from_a_stall_moves_no_write_after_it(monkeypatch, seed):
    """A host wakes from a stall at a random phase of the tick: its loop puts the next
    deadline mid-tick (``align_deadline``) and writes the FORCE it owes at once, on no
    grid; the writes after it come at the aligned deadlines, a period apart. Each of
    those lands in the middle third of the tick, is not near the boundary, and none but
    the first (its hold begun by the wake's write: off the period) is marked mistimed.
    Before, the wake's write was taken for the writes' phase: where it fell outside the
    band, it set a delay that put the aligned writes near the boundary, each marked and
    cut until the running mean forgot it (15-20 writes after each stall of a host stopped
    10 ms in every 100: the shipped scene's records cut to one stretch)."""
    port = TickingPort(300_000, 200_000, sketch=True)
    tr = _transport(monkeypatch, port)
    assert tr.tick_phase() is not None, tr.tick_probe
    from hapsim.drivers import transport as transport_mod
    clk = transport_mod.time                     # the simulated clock (_transport)
    tr._period_ticks = 5
    period = 5 * TICK_NS
    cmd = tr.driver.encode_force(0.0)
    rng = np.random.default_rng(seed)
    for stall in range(3):
        clk.sleep(rng.uniform(2, 6) * period * 1e-9)   # the stall, ending anywhere
        first = stall * 100
        deadline = tr.align_deadline(clk.monotonic_ns())
        tr._write_tick = None
        tr._command(cmd)                         # the FORCE owed, written on waking
        tr._note_hold(first)
        for k in range(1, 30):
            clk.sleep(max(deadline + k * period - clk.monotonic_ns(), 0) * 1e-9)
            tr._write_tick = None
            tr._command(cmd)
            tr._note_hold(first + k)
            n, near = tr._write_tick
            ph = (clk.monotonic_ns() - tr._write_at) % TICK_NS / TICK_NS
            assert not near and 1 / 3 <= ph <= 2 / 3, (stall, k, ph)
        marked = {s - first for s in tr.mistimed if first <= s < first + 30}
        assert marked <= {0, 1}, (stall, sorted(marked))


@pytest.mark.parametrize("hold", [0, 6])
@pytest.mark.parametrize("transit_us", [200, 1200])
def test_an_answer_read_after_the_next_write_is_the_command_before(monkeypatch, transit_us,
                                                                  hold):
    """A link of 1.2 ms in: the sketch's reply comes 4.8-5.2 ms after its write, a period
    is 3.97 ms, and it is read at the deadline after the next write. Taken for the newest
    command (the rule before), every reading was one command off: a loop of one delay
    more, measured as the scene's. The reply carries the Tp of the force its command
    rendered (sim.h:191), which names its command where the host's forces differ.
    ``hold``: the first commands' forces are equal (the excitation's hold), so the echo
    names none of them: before, the first of them was taken for the newest's and every
    reading after it stayed one command off, the echo no longer asked (an idle machine's
    runs of configs/hapkit_serial.yaml said "differs" 2 times in 8). Each STATE's
    position names the write it answers (the port's truth): equal to its seq on both
    links except on rows the transport marked for the measurement to cut (``mistimed``:
    a pairing the echo showed one command off), none of them past the hold's first named
    force; the short link's replies (in before the next write) are never shifted."""
    port = TickingPort(300_000, transit_us * 1000, sketch=True, numbered=True)
    tr = _transport(monkeypatch, port)
    tr._armed = True
    tr._settle = 0
    tr._answered = tr._cmd = 0
    tr.stats["read_late"] = 0
    got = []
    at = time.monotonic_ns()
    for j in range(1, 41):
        wait = at + j * 4 * TICK_NS - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait * 1e-9)
        got += [m for m in tr.receive(0.0) if hasattr(m, "position")]
        tr._command(tr.driver.encode_force(0.01 * max(j, hold)))
    assert len(got) >= 30, len(got)
    wrong = {m.seq for m in got if round(m.position[0] / 1e-4) != m.seq}
    assert wrong <= tr.mistimed, (sorted(wrong), sorted(tr.mistimed))
    assert all(s <= hold + 1 for s in tr.mistimed), sorted(tr.mistimed)
    if transit_us == 200:
        assert tr.stats["read_late"] == 0 and not tr.mistimed
    else:
        # every answer after the hold's first named one was read late and so paired
        assert tr.stats["read_late"] >= sum(m.seq > hold + 1 for m in got), tr.stats


def test_a_rate_whose_period_is_no_whole_number_of_ticks_is_refused():
    """The sketch samples and applies forces on its 0.992 ms ticks: 250 Hz would sample 4
    ticks apart and 5 once in 31 periods, 300 Hz at 3, 3 and 4 ticks (another loop than
    the one modelled), so they are refused with the nearest rates that hold; a period
    shorter than the latest answer at any write phase (4.27 ms: both messages on the wire,
    the render's largest latency and the tick's wait) is refused for that, 4 ticks among
    them (an idle host's runs at 4 ticks read much of the answers after the next deadline);
    periods of whole ticks within the link's limit pass, written exactly or to six figures
    (201.613 Hz: 1.6e-6 of a tick off, inside the driver's 1e-4)."""
    from tolerance import rel_tol  # same directory (pytest prepend import mode)
    drv = hk.HapkitSerial()
    tick = hk.FIRMWARE_TICK_S
    wire = 19 * 10 / 57600
    # the latest answer, from its parts (Hapkit_arduino.ino:96-135, tick_align.
    # fit_tick_jump)
    parts = (wire, hk.RENDER_LATENCY_S[1], 2 * tick, -9 * 10 / 57600)
    late = sum(parts)
    # derived (tests/tolerance.rel_tol): four terms, each at most 3 roundings deep
    # (a product and a quotient), summed in either order (3 more) by the driver and here:
    # 2 x 6 roundings, the sum's condition sum |x| / |sum x| (the subtraction, ~1.7)
    cond = sum(abs(x) for x in parts) / abs(late)
    assert abs(drv.latest_answer_s() - late) <= rel_tol(12, cond) * late
    for n in (5, 6, 8, 1008):
        drv.check_rate(1.0 / (n * tick))
        assert drv.period_ticks(1.0 / (n * tick)) == n
    for rate, n in ((201.613, 5), (168.011, 6)):
        drv.check_rate(rate)
        assert drv.period_ticks(rate) == n
    assert drv.native_rate_hz == 1.0 / (5 * tick)       # its HELLO's rate: 5 ticks
    # 250 Hz: 4.03 ticks; 4 cannot hold the answer, so 5 alone is named
    with pytest.raises(ConfigError, match=r"cannot be held.*4\.27 ms.*201\.613 Hz \(5 of"):
        drv.check_rate(250.0)
    with pytest.raises(ConfigError, match=r"no whole number.*nearest: 201\.613 Hz, 168\.011 Hz"):
        drv.check_rate(185.0)
    with pytest.raises(ConfigError, match=r"252\.016 Hz cannot be held.*4\.27 ms"):
        drv.check_rate(252.016)
    with pytest.raises(ConfigError, match="no whole number"):
        drv.check_rate(1.0)
    # 2e-4 of a tick off: a walk the aligned writes would re-centre every 1,750 periods
    with pytest.raises(ConfigError, match="no whole number"):
        drv.check_rate(1.0 / (5.0002 * tick))
    with pytest.raises(ConfigError, match=r"cannot be held.*201\.613 Hz \(5 of"):
        drv.check_rate(500.0)


def test_the_loop_is_modelled_and_run_at_the_boards_own_period():
    """``configs/hapkit_serial.yaml`` says 201.613 Hz: the run's scene (its prediction, its
    engine, its host loop) takes 5 of the sketch's ticks exactly, as the board does; at the
    six-figure rate a matching paddle's exact record said "differs" (the driver's
    ``board_rate_hz``). A framed device (no tick of its own) keeps the scene's rate."""
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    sc = load_scene("configs/hapkit_serial.yaml")
    assert sc.rate_hz == 201.613
    prep = prepare_run(sc, RunOptions(driver="hapkit-serial", handle_signals=False))
    assert prep.scene.period == 5 * hk.FIRMWARE_TICK_S
    # at 6 ticks the shipped spring is unstable with its reading a period late (refused,
    # tests below): the rate is this test's, run past that refusal
    prep = prepare_run(sc, RunOptions(driver="hapkit-serial", handle_signals=False,
                                      rate_hz=168.011, allow_unstable=True))
    assert prep.scene.period == 6 * hk.FIRMWARE_TICK_S
    assert prepare_run(sc, RunOptions(handle_signals=False)).scene.rate_hz == 201.613


def test_check_analyses_the_loop_the_board_runs_as_run_predicts_it(tmp_path, capsys):
    """``hapsim check`` on a scene whose device speaks the sketch's bytes analyses the loop
    the board runs: 5 whole ticks, and the scene's one period of delay with the render's
    latency after the read at its bounds' middle. It predicted with the scene's whole
    delay alone, b 0.2014 N s/m where ``hapsim run`` states 0.1836 before it runs: a user
    who checked, then ran, saw two predictions 10 % apart.

    Compared with a scene written by hand with that rate and that real delay on hapsim's
    framed protocol (the delay formed as the run forms it, so the two loops are the same
    floats, and the felt pairs equal exactly); the run's prediction is of that loop too."""
    from pathlib import Path

    import yaml

    from hapsim.api import check
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    from inproc import hapsim_main  # same directory (pytest prepend import mode)

    src = Path(__file__).resolve().parents[1] / "configs" / "hapkit_serial.yaml"
    rep = check(str(src))
    rate = 1.0 / (5 * hk.FIRMWARE_TICK_S)
    lo, hi = hk.RENDER_LATENCY_S
    delay = 1.0 + 0.5 * (lo + hi) / (1.0 / rate)
    assert rep.rate_hz == rate and rep.board["rate_written_hz"] == 201.613
    assert rep.board["delay_modelled"] == delay and rep.board["render_latency_s"] == [lo, hi]
    doc = yaml.safe_load(src.read_text())
    doc["rate_hz"] = rate
    doc["device"]["delay"] = delay
    for key in ("protocol", "protocol_options"):
        doc["device"].pop(key, None)
    hand = tmp_path / "by_hand.yaml"
    hand.write_text(yaml.safe_dump(doc))
    ref = check(str(hand))
    assert ref.board is None
    assert (rep.k, rep.b, rep.spectral_radius) == (ref.k, ref.b, ref.spectral_radius)
    # the whole delay alone (the check before) is another loop: 10 % more damping
    doc["device"]["delay"] = 1
    hand.write_text(yaml.safe_dump(doc))
    assert check(str(hand)).b > 1.05 * rep.b
    # the run's prediction is of the same loop: equal to the hand-written scene's
    # (check and run take the felt pair by two routes, which part at round-off alike for
    # every scene: compared loop with loop, not route with route)
    prep = prepare_run(load_scene(str(src)), RunOptions(driver="hapkit-serial",
                                                        handle_signals=False))
    doc["device"]["delay"] = delay
    hand.write_text(yaml.safe_dump(doc))
    own = prepare_run(load_scene(str(hand)), RunOptions(handle_signals=False))
    assert (prep.pred["k"], prep.pred["b"]) == (own.pred["k"], own.pred["b"])
    # 250 Hz is analysed with the latency and said to be refused by the run, with the
    # rates that hold
    doc = yaml.safe_load(src.read_text())
    doc["rate_hz"] = 250
    bad = tmp_path / "at_250.yaml"
    bad.write_text(yaml.safe_dump(doc))
    code, out, _ = hapsim_main(["check", str(bad)])
    assert code == 0
    assert "hapsim run refuses this rate" in out and "can hold is 201.613 Hz" in out
    assert "renders 0.15-0.55 ms after its read" in out


def test_a_target_is_felt_in_the_loop_the_board_runs(tmp_path):
    """A ``target {k, b}`` link on a scene whose device speaks the sketch's bytes: the
    (K, B) sent are calibrated for the loop the board runs (its render latency's middle
    in the delay, where the run states its prediction), so ``check`` and the run's
    prediction feel the target; calibrated for the scene's whole delay alone (before),
    configs/hapkit_serial.yaml's (35, 0.5) was predicted 2.5 % off its b (0.4876 N s/m).
    Random paddles, targets and two whole-tick rates the board holds, 12 seeded draws. In
    lockstep (no time of the
    board's) the whole delay is the loop, and the target is felt there. ``simulate``
    sends the run's (K, B)."""
    import yaml

    from hapsim.api import check, simulate
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    from tolerance import measured
    rng = np.random.default_rng(3)
    # measured 1.4e-13 relative at most over 30 draws (the calibration's root finders and
    # two eigenvalue routes), margin 70
    tol = measured(1.4e-13, 70)
    for i in range(12):
        doc = yaml.safe_load(open("configs/hapkit_serial.yaml"))
        k, b = float(rng.uniform(20, 150)), float(rng.uniform(0.2, 1.5))
        doc["links"][0] = {**{q: v for q, v in doc["links"][0].items()
                              if q not in ("stiffness", "damping")},
                           "target": {"k": k, "b": b}}
        doc["device"].update(mass=float(rng.uniform(0.05, 0.2)),
                             friction=float(rng.uniform(0.05, 0.5)))
        doc["rate_hz"] = float(rng.choice([201.613, 168.011]))
        path = tmp_path / f"target{i}.yaml"
        path.write_text(yaml.safe_dump(doc))
        rep = check(str(path))
        assert rep.board["delay_modelled"] > 1.0
        # a target the reading a period late makes unstable: check says so, the run
        # refuses it (the test above); its calibration is this test's, run past that
        late = "late_reading_unstable" in rep.board
        assert rep.stable is not late
        for lock in (False, True):
            prep = prepare_run(load_scene(str(path)), RunOptions(
                driver="hapkit-serial", handle_signals=False, lockstep=lock,
                allow_unstable=late))
            for kk, bb in ((rep.k, rep.b), (prep.pred["k"], prep.pred["b"])):
                assert abs(kk - k) <= tol * k and abs(bb - b) <= tol * b, (i, lock, kk, bb)
            assert prep.scene.device.delay == 1       # the scene's own delay is kept
        # simulate sends the run's (K, B) (no device there: the calibration alone)
        sim = simulate(str(path), 1).calibrations[0]
        prep = prepare_run(load_scene(str(path)), RunOptions(
            driver="hapkit-serial", handle_signals=False, allow_unstable=late))
        assert (sim["K"], sim["B"]) == (prep.targets[0]["K"], prep.targets[0]["B"])


def test_a_loop_unstable_anywhere_in_the_boards_latency_or_a_reading_late_is_refused(
        tmp_path):
    """The sketch renders 0.15-0.55 ms after its read, where in that range its text does
    not fix, and its reply, up to 4.27 ms after the write, is taken a period late by a
    host that wakes 0.69 ms late (``late_reading_periods`` 1): a loop stable at the middle
    but not at the range's end, or not with the reading a period late, may run away on a
    board (a 50 N/m spring at 5 ticks, stable to 1.52 periods, ran the paddle to its
    0.2 m envelope beside the suite's load). Random paddles and port damping, 6 seeded
    draws, the stiffness limits from the loop model itself at the three delays (K_max
    falls with the delay): a spring between the limit at 0.55 ms and the one at the
    middle, or between the limit a period later and the one at 0.55 ms, is unstable for
    ``check`` (exit 1, its reason), refused by the run (before: run, stable at the middle;
    and before this, run at any spring stable at 0.55 ms) but run with
    ``--allow-unstable`` and on hapsim's framed protocol, whose late samples are known
    inputs; ``stability --scene`` states the least limit; a spring below the late
    reading's limit is stable for all three; ``advise``'s (K, B) for the spring as a
    target, where it finds some, the run takes."""
    import json

    import yaml

    from hapsim.analysis.loop import LoopModel
    from hapsim.api import check, stability
    from hapsim.errors import UnstableConfigError
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    from inproc import hapsim_main  # same directory (pytest prepend import mode)
    from hapsim.bench.advise import advise_scene
    rng = np.random.default_rng(5)
    rate = 1.0 / (5 * hk.FIRMWARE_TICK_S)
    lo, hi = hk.RENDER_LATENCY_S
    assert hk.HapkitSerial.late_reading_periods == 1
    advised = 0
    for i in range(6):
        m, b0, B = (float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.05, 0.5)),
                    float(rng.uniform(0.0, 0.5)))
        k_mid, at_hi, at_late = (stability(LoopModel(m, b0, rate, d, "zoh"), B) for d in (
            1.0 + 0.5 * (lo + hi) * rate, 1.0 + hi * rate, 2.0 + hi * rate))
        k_mid, k_hi, k_late = k_mid.K_max, at_hi.K_max, at_late.K_max
        assert k_late < k_hi < k_mid
        for K, why in ((0.5 * (k_hi + k_mid), "latency"), (0.5 * (k_late + k_hi), "late"),
                       (0.98 * k_late, None)):
            doc = yaml.safe_load(open("configs/hapkit_serial.yaml"))
            doc["links"][0].update(stiffness=K, damping=B)
            doc["device"].update(mass=m, friction=b0)
            path = tmp_path / f"edge{i}{why}.yaml"
            path.write_text(yaml.safe_dump(doc))
            rep = check(str(path))
            assert rep.stable is (why is None) and rep.analysis.stable, (i, K, rep.board)
            opts = RunOptions(driver="hapkit-serial", handle_signals=False)
            if why is None:
                prepare_run(load_scene(str(path)), opts)
            else:
                assert (rep.board.get("unstable_latency_s") == hi) is (why == "latency")
                assert ("late_reading_unstable" in rep.board) is (why == "late")
                with pytest.raises(UnstableConfigError, match="not at 0.55 ms" if why ==
                                   "latency" else "taken 1 period late"):
                    prepare_run(load_scene(str(path)), opts)
                prepare_run(load_scene(str(path)), RunOptions(
                    driver="hapkit-serial", handle_signals=False, allow_unstable=True))
            if why == "late":     # the framed protocol: no late reading, no latency
                prepare_run(load_scene(str(path)), RunOptions(handle_signals=False))
                # what advise sends for the spring as a target, the run takes
                doc["links"][0] = {q: v for q, v in doc["links"][0].items()
                                   if q not in ("stiffness", "damping")}
                doc["links"][0]["target"] = {"k": K, "b": B + b0}
                tpath = tmp_path / f"target{i}.yaml"
                tpath.write_text(yaml.safe_dump(doc))
                adv = advise_scene(load_scene(str(tpath)))
                if adv.ok:
                    advised += 1
                    prepare_run(adv.apply(load_scene(str(tpath))), opts)
            code, out, _ = hapsim_main(["check", str(path)])
            assert code == (0 if why is None else 1)
            assert ("the board may render 0.55 ms after its read" in out) is (
                why == "latency")
            assert ("takes the board's reply 1 period late" in out) is (why == "late")
            code, out, _ = hapsim_main(["stability", "--scene", str(path), "--json"])
            got = json.loads(out)["K_max"][0]
            # the same limit by the scene's route as by the loop's: inside the loop
            # route's certified bracket (exact arithmetic: no pole on |z| = 1 below it;
            # measured equal over 30 draws, both routes forming the same delay)
            k_lo, k_up = at_late.K_max_interval
            assert k_lo <= got <= k_up and code == 0, (got, at_late.K_max_interval)
    # and over targets on the shipped paddle near the late reading's limit (38.32 N/m at
    # B = 0.2 N s/m): advise held its margin at the latency's end alone before, and its
    # (K, B) for (60, 0.3) was refused by the run
    for k, b in ((40.0, 0.3), (50.0, 0.3), (60.0, 0.3), (60.0, 0.4)):
        doc = yaml.safe_load(open("configs/hapkit_serial.yaml"))
        doc["links"][0] = {"name": "spring", "kind": "spring_damper",
                           "between": ["handle", "wall"], "target": {"k": k, "b": b}}
        tpath = tmp_path / f"grid{k}_{b}.yaml"
        tpath.write_text(yaml.safe_dump(doc))
        adv = advise_scene(load_scene(str(tpath)))
        if adv.ok:
            advised += 1
            prepare_run(adv.apply(load_scene(str(tpath))), RunOptions(
                driver="hapkit-serial", handle_signals=False))
    assert advised >= 6, advised

def test_a_hand_family_on_the_board_is_judged_over_its_latency(tmp_path):
    """``hapsim family`` of a Hapkit-serial scene with a hand (0.05-0.5 kg, grip
    300-3000 N/m): the family of the loop the board runs, its render latency's middle in
    the delay, and held stable at the latency's two bounds and with the reply taken a
    period late (the driver's ``late_reading_periods``, as the run holds the loop) with
    the (K, B) the run sends. A spring of 197 N/m (at 5 ticks: the members' edge at
    0.55 ms lies in 194-195 N/m, at the middle in 199-200): every sampled member stable
    with the whole delay alone and at the middle (the verdict before: robustly stable),
    one unstable at 0.55 ms: not robustly stable now, its report the family there;
    125 N/m: stable at both bounds, not with the reading a period late (the edge there
    lies in 116-120 N/m, measured with grid 5), named so; 110 N/m: robust over all
    three. The same scenes on hapsim's framed protocol keep their whole delay (robust)."""
    import yaml

    from hapsim.api import family
    from tolerance import rel_tol  # same directory (pytest prepend import mode)
    doc = yaml.safe_load(open("configs/hapkit_serial.yaml"))
    doc["device"]["hand"] = {"mass": [0.05, 0.5], "damping": 1.0,
                             "grip_stiffness": [300, 3000], "grip_damping": 2.0}
    got = {}
    springs = (110.0, 125.0, 197.0)
    for K in springs:
        for proto in ("hapkit-serial", "framed"):
            doc["links"][0]["stiffness"] = K
            doc["device"]["protocol"] = proto
            path = tmp_path / f"hand_{proto}_{K:g}.yaml"
            path.write_text(yaml.safe_dump(doc))
            got[K, proto] = family(str(path), grid=5, certify=0)
    assert all(got[K, "framed"].robust for K in springs)
    assert "board" not in got[197.0, "framed"].extra
    ok, late, edge = (got[K, "hapkit-serial"] for K in springs)
    assert ok.robust and not {"unstable_latency_s", "late_reading_unstable"} & set(
        ok.extra["board"])
    assert ok.extra["board"]["delay_modelled"] == 1.0 + 0.35e-3 / (5 * hk.FIRMWARE_TICK_S)
    assert not late.robust and late.unstable >= 1
    assert "unstable_latency_s" not in late.extra["board"]
    lr = late.extra["board"]["late_reading_unstable"]
    want = 2.0 + hk.RENDER_LATENCY_S[1] / (5 * hk.FIRMWARE_TICK_S)
    # derived (tests/tolerance.rel_tol): the same delay formed another way, the driver's
    # 1 + (0.55 ms + T) / T with T = 1 / rate and rate = 1 / (5 tick) (6 roundings)
    # against 2 + 0.55 ms / (5 tick) (3): 9 roundings of positive terms (condition 1)
    # on a value of ~2.1
    assert lr["periods"] == 1 and abs(lr["delay"] - want) <= rel_tol(9) * want
    assert not edge.robust and edge.unstable >= 1
    assert edge.extra["board"]["unstable_latency_s"] == hk.RENDER_LATENCY_S[1]
    assert "late_reading_unstable" not in edge.extra["board"]


# ------------------------------------------------------------------ real time, loaded

def _burn(until: float) -> None:
    while time.monotonic() < until:
        pass


@pytest.fixture
def two_cpu_hogs():
    """Two CPU-bound processes for the test's length (each ends by itself within 90 s)."""
    import multiprocessing as mp

    from load import burners_for  # same directory (pytest prepend import mode)
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_burn, args=(time.monotonic() + 90.0,), daemon=True)
             for _ in range(burners_for(2))]
    for p in procs:
        p.start()
    time.sleep(0.2)
    try:
        yield procs
    finally:
        for p in procs:
            p.terminate()
            p.join(5.0)


def _run(seed: int, **kw) -> dict:
    from pathlib import Path

    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    sc = load_scene(str(Path(__file__).resolve().parents[1] / "configs" / "hapkit_serial.yaml"))
    return run_scene(sc, driver="hapkit-serial", duration=1.5, handle_signals=False,
                     seed=seed, driver_faults={"drop_tx": 0.0, "drop_rx": 0.0, "seed": seed},
                     **kw)


@pytest.mark.parametrize("seed", [2, 6])
def test_on_the_boards_own_clock_beside_two_hogs_the_writes_are_mid_tick(two_cpu_hogs, seed):
    """The THS through the sketch's bytes on the board's own clock, two CPU-bound
    processes running (SCHED_FIFO 10 where the OS permits, as ``hapsim run``): the
    transport found the board's tick at the arming and its commands came away from the
    boundary -- their median arrival phase (the board's own count) within a standard
    deviation of 0.15-0.85 of a tick, and at most half of them within a tenth of a tick of the boundary. The
    median's bound: a median lies within one standard deviation of the mean (Mallows,
    *The American Statistician* 45(3), 1991; the phases' own, ``phase_sd``: a fixed 0.05
    allowed failed once at a median of 0.901 under the suite's load); it is taken over
    phases in [0, 1), so a cluster straddling the boundary can give any median with a
    large ``phase_sd``: the near share is the check that catches that. Its bound, derived
    from what the board counts: the commands include the probes' sweeps (two or more at
    the arming, eight at the stop: 160-190 commands spread evenly over the tick by
    design, a fifth of them near the boundary, 6-8 % of the ~480), and the loop's writes,
    put in the tick's middle on the arming's placement (``TickAligned._write_on_grid``:
    not re-centred), near only when the host made them 0.4 of a tick late. Measured beside
    two hogs and tests/test_wallclock.py and test_host_watchdog.py looping: 29-45 of
    484-505 in 46 runs (9.2 % at most: margin 5.4 against half); before two placements
    at the arming had to agree (``tests/test_tick_arming.py``), 29-41 of 469-489 in 58
    runs of 59, and in the 59th, its arming placed 0.41 of a tick off by a burst of late
    probe replies, 283 of 478 -- writes systematically at the boundary,
    the class the aligner exists for (median ~0, 77 % near in the unaligned run it was
    written for). Before: 21 % (median phase 0.81) once in a fresh-clone CI run, 70 % (335
    of 480) once in a load check. The verdict is not "differs" (within, or
    not measurable with its reason after a safety stop on the host's own lateness). Seed
    6 is the table's run that said "differs" (docs/driver_timing.json)."""
    assert all(p.is_alive() for p in two_cpu_hogs)
    rep = _run(seed)
    loop, m = rep["loop"], rep["measured"]
    assert loop["mock"]["clock"] == "wall"
    assert loop["driver"]["tick_aligned"], loop["driver"].get("tick_probe")
    arr = loop["mock"]["tick_arrivals"]
    verdict = str(m.get("verdict"))
    info = (verdict, m.get("rel_err"), m.get("k_unc"), m.get("b_unc"), arr,
            {q: loop.get(q) for q in ("estimated", "overruns", "late", "missed",
                                      "stop_reason")},
            loop["driver"].get("tick_probe"), m.get("error"))
    assert not verdict.startswith("measured differs"), info
    if loop.get("safety_stop"):
        # the one stop allowed: the host's own lateness (a loaded machine), zero torque
        assert "the host was" in loop["stop_reason"], info
        return
    # the band's bound, derived (docstring): the median within a standard deviation of
    # the band
    sd = arr["phase_sd"]
    assert 0.15 - sd <= arr["median_phase"] <= 0.85 + sd, info
    assert arr["near_boundary"] <= 0.5 * arr["commands"], info
    # within, or not measurable with its reason (the run's own reading of the measurement,
    # an error included: the unseen holds cut can leave too few cycles on a loaded machine
    # -- 30 holds off the period in one run beside the hogs and a helper's work)
    from hapsim.pipeline.report import verdict_summary
    summary = verdict_summary(m)
    assert summary["verdict"] in ("within", "not measurable"), (summary, info)
    assert summary["verdict"] == "within" or summary["reason"], (summary, info)


def test_on_the_boards_own_clock_a_hidden_friction_is_still_seen(monkeypatch):
    """The same loop, the writes timed mid-tick, against a paddle with a viscous friction
    of 0.3 N s/m more than the scene states (the felt b, predicted 0.5 N s/m with the
    spring's 0.2, becomes 0.8): "differs", the measured b above the prediction by more
    than its stated uncertainty (stated: 1-8 % of b in the runs above); never "within",
    and "not measurable" (with its reason) only of a record cut at 3 or more holds.
    Beside two and four CPU-bound processes 30 of 30 runs said "differs" (stop 57).

    The measurement is asserted as it stood before the stop's tick-walk review
    (:func:`hapsim.pipeline.unseen_review.review_tick_walk`, its own subject in
    ``tests/test_board_clock.py``): the emulated board is on the host's clock, but under
    the suite's load the stop's probe once placed its boundary 0.40 of a tick off the
    arming's (the board's replies late by its own scheduling), and the review made the
    "differs" "not measurable" naming the walk, which is its rule. The final verdict is
    still never "within"."""
    import copy
    import dataclasses

    import hapsim.emulated.driver_mock as dm
    import hapsim.pipeline.unseen_review as ur
    init = dm.EmbeddedDriverMock.__init__

    def hidden(self, driver, device, *a, **k):
        init(self, driver, dataclasses.replace(device, friction=device.friction + 0.3),
             *a, **k)
    monkeypatch.setattr(dm.EmbeddedDriverMock, "__init__", hidden)
    before = []
    real_review = ur.review_tick_walk
    monkeypatch.setattr(ur, "review_tick_walk", lambda measured, driver: (
        before.append(copy.deepcopy(measured)), real_review(measured, driver))[1])
    rep = _run(1)
    loop, m = rep["loop"], rep["measured"]
    assert m.get("within") is not True, m.get("verdict")
    if "tick_walk" in m:
        assert str(m["verdict"]).startswith("not measurable: the board's tick"), m["verdict"]
        assert before, "the review ran"
        m = before[-1]                     # what the record measured, before the review
    assert loop["driver"]["tick_aligned"], loop["driver"].get("tick_probe")
    assert m.get("within") is not True, m.get("verdict")
    cut = int(m.get("unseen_holds") or 0) + int(m.get("mistimed_rows") or 0)
    if m.get("within") is None and cut >= 3:
        # a record the suite's load cut up (7 holds the board took late, 220 of ~370 rows
        # left, once in a whole-suite run): with the known inputs taken out through the
        # loop it measures, the fit there finds too few cycles; "not measurable" with that
        # reason, never "within" (asserted above)
        from hapsim.pipeline.report import verdict_summary
        summary = verdict_summary(m)
        assert summary["verdict"] == "not measurable" and summary["reason"], summary
        return
    assert str(m.get("verdict")).startswith("measured differs"), (
        m.get("verdict"), {q: m.get(q) for q in (
            "b", "b_unc", "k", "k_unc", "samples_used", "unseen_holds", "prediction_test",
            "estimated_samples", "render_latency_s", "cycles")}, rep["predicted"].get("b"))
    assert m["b"] - rep["predicted"]["b"] > m["b_unc"], (m["b"], rep["predicted"]["b"],
                                                         m["b_unc"])


def test_a_live_change_is_judged_over_the_boards_latency():
    """``run --osc`` on a board that renders after its read: the live controller judges a
    change over the latency's bounds, as the run's refusal does. A stiffness between the
    limit at 0.55 ms (62.15 N/m on the shipped paddle at 5 ticks, B = 0.2 N s/m) and the
    middle's (63.74) is refused, naming the latency (before: the whole delay alone was
    checked, its limit 66.75, and it was taken); one below is accepted; a felt target is
    calibrated with the middle in the delay, as the run's. With the reply taken a period
    late too (the run's ``late_reading_periods``), a change unstable there is refused. In
    the calling thread."""
    from hapsim.audio.control import Controller
    from hapsim.engine import Engine
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    prep = prepare_run(load_scene("configs/hapkit_serial.yaml"),
                       RunOptions(driver="hapkit-serial", handle_signals=False))
    lo, hi = prep.pred["render_latency_s"]
    ctl = Controller(prep.scene, Engine(prep.scene), ramp_s=0.01, background=False,
                     latency=(0.5 * (lo + hi), hi))
    try:
        ok, why = ctl.request("/hapsim/link/stiffness", "spring", 63.0)
        assert not ok and "0.55 ms after its read" in why, why
        ok, got = ctl.request("/hapsim/link/stiffness", "spring", 61.0)
        assert ok, got
        k, b = 50.0, 0.5
        ok, got = ctl.request("/hapsim/link/target", "spring", k, b)
        assert ok, got
        from tolerance import measured
        # measured 1.4e-13 relative at most (the calibration's root finders, two
        # eigenvalue routes; the target test above), margin 70
        tol = measured(1.4e-13, 70)
        assert abs(got[1] - k) <= tol * k and abs(got[2] - b) <= tol * b, got
    finally:
        ctl.close()
    # and with the reply taken a period late (the run's late_reading_periods): the limit
    # there is 38.32 N/m (B = 0.2 N s/m; tests above): 61 N/m refused, naming it, 37 taken
    ctl = Controller(prep.scene, Engine(prep.scene), ramp_s=0.01, background=False,
                     latency=(0.5 * (lo + hi), hi), late_reading_s=prep.scene.period)
    try:
        ok, why = ctl.request("/hapsim/link/stiffness", "spring", 61.0)
        assert not ok and "4.96 ms late" in why, why
        ok, got = ctl.request("/hapsim/link/stiffness", "spring", 37.0)
        assert ok, got
    finally:
        ctl.close()

"""The Hapkit sketch reads its commands without framing: a host byte lost puts every
later command out of step until the host is silent longer than the sketch's read timeout
(issue 29, the independent board models: ``tools/independent_boards/hapkit_sketch.py``).

The WHC2017 sketch (haphub/WHC2017 ``hFirmware/Hapkit_Arduino_Control/Hapkit_arduino/``)
reads a command as one header byte and ``Serial.readBytes`` of nine, whatever they are;
``readBytes`` waits for each byte up to the Stream's 1000 ms of ``millis()``, which runs 64
times fast once its set-up sets Timer0's prescaler to 1 for the motor's PWM: 15.625 ms;
a byte not come by then leaves the buffer's old content. So one host byte lost makes the
command complete with the next command's header, and every later command is read one
byte out of step (its function byte the host's first float's first byte, 0: no force),
its replies no replies for the host, until a silence of the host realigns the reads.
hapsim's emulated board realigned on the header and function bytes instead, which the
sketch does not, so its runs with bytes lost stayed in step; against the independent
model the loop lost its board at the first byte lost, 16 losses and recoveries in a
1.5 s run, the paddle coasting to its end stops between them.

Here, on a **simulated clock** (deterministic, seeded; no pty): hapsim's driver transport
drives a sketch written in this test from the firmware (not hapsim's emulator: its
own reads, the 57600-baud wire each way, the 1 kHz tick, the paddle's exact physics),
with host bytes lost at random places of random commands. What must hold: after each
loss the sketch reads the host's commands in step again within the bound the
transport's rule gives (its evidence, :attr:`~hapsim.drivers.hapkit_serial.HapkitSerial.
garbled_commands` and ``garbled_s``, then its silence, ``realign_quiet_s``); the loop is
never lost; no realignment without a loss. On the code before (no realignment: the
transport wrote every tick) the sketch never came back in step. And hapsim's emulated
board reads as the sketch does (:class:`hapsim.emulated.hapkit_serial_board.SketchReader`
against this test's reads, random streams and silences).
"""

from __future__ import annotations

import math
import struct
import types

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.drivers import get_driver
from hapsim.drivers import transport as tp

BYTE_S = 10 / 57600          # one byte on the wire [s]
TICK_S = 62 * 256 / 16e6     # the sketch's Timer1 tick, 0.992 ms (the driver's tick_s)
TIMEOUT_S = 1.0 / 64         # readBytes' 1000 ms of a 64-times-fast millis() [s]
T = 4 * TICK_S               # the host's period: 4 ticks, 252.016 Hz
M, B0 = 0.1, 0.3             # the paddle [kg], its friction [N s/m]
K, BV = 50.0, 0.2            # the virtual spring [N/m] and damper [N s/m]


from test_haply_silence import SimClock, host_command  # noqa: E402  (same directory)


class Sketch:
    """The sketch's reads and loop as its firmware makes them (module notes), on the
    simulated clock: host bytes available one byte time apart, a command read once its
    tenth byte came (or its wait timed out: the old bytes complete it), taken at the next
    tick, the paddle read there, the force rendered from there (the host's for function
    255, none for 0 and any byte but 1-3, which are the sketch's own environments), the
    9-byte reply on the wire after it."""

    def __init__(self, x0=0.01):
        self.rx = []                 # (time available [s], byte)
        self.line = 0.0              # the wire to the board is busy until then
        self.cur = bytearray()
        self.stale = bytearray(9)
        self.t_last = None
        self.x, self.v, self.f, self.t = x0, 0.0, 0.0, 0.0
        self.tick = -1
        self.out = []                # (time readable, bytes)
        self.frames = []             # (time taken, 10 bytes read)
        self.done = []               # when each command was complete [s]

    def write(self, t, data):
        for b in data:
            self.line = max(self.line, t) + BYTE_S
            self.rx.append((self.line, b))

    def _physics(self, t):
        dt = t - self.t
        if dt > 0:
            r = B0 / M
            e = math.exp(-r * dt)
            vinf = self.f / B0
            self.x += vinf * dt + (self.v - vinf) * (1 - e) / r
            self.v = vinf + (self.v - vinf) * e
            self.t = t

    def _complete(self, t):
        self.done.append(t)
        raw = bytes(self.cur[:1]) + bytes(self.cur[1:]) + bytes(self.stale[len(self.cur) - 1:])
        body = raw[1:]
        self.stale = bytearray(body)
        self.cur = bytearray()
        k = max(math.floor(t / TICK_S) + 1, self.tick + 1)
        self.tick = k
        tk = k * TICK_S
        self._physics(tk)
        fn = body[0]
        force = struct.unpack_from("<f", body, 5)[0]
        f = force if fn == 255 and math.isfinite(force) else \
            (-400 * (self.x - 0.005) if fn == 1 and self.x > 0.005 else
             -15 * self.v if fn == 2 else -100 * self.x if fn == 3 else 0.0)
        self.f = max(-2.0, min(2.0, f))
        self.frames.append((tk, raw))
        self.out.append((tk + 9 * BYTE_S, bytes([fn]) + struct.pack("<ff", self.x, self.f)))

    def run_to(self, t):
        while True:
            nb = self.rx[0][0] if self.rx else math.inf
            nt = self.t_last + TIMEOUT_S if self.cur and self.t_last is not None else math.inf
            if min(nb, nt) > t:
                break
            if nt < nb:
                self._complete(nt)
                continue
            at, b = self.rx.pop(0)
            self.cur.append(b)
            self.t_last = at
            if len(self.cur) == 10:
                self._complete(at)
        self._physics(t)


class SketchPort:
    """The sketch behind a port in memory; host bytes lost at the given (write, byte)
    places."""

    is_open = True

    def __init__(self, clock, sketch, lose=()):
        self.clock, self.sketch = clock, sketch
        self.lose = set(lose)
        self.n_writes = 0
        self.written = []            # (time, bytes as sent)
        self.lost_at = []            # times a byte was lost

    def write(self, data):
        data = bytes(data)
        t = self.clock.t
        self.written.append((t, data))
        kept = bytearray()
        for i, b in enumerate(data):
            if (self.n_writes, i) in self.lose:
                self.lost_at.append(t)
                continue
            kept.append(b)
        self.n_writes += 1
        self.sketch.run_to(t)
        self.sketch.write(t, bytes(kept))
        return len(data)

    def _due(self):
        self.sketch.run_to(self.clock.t)
        return [o for o in self.sketch.out if o[0] <= self.clock.t]

    @property
    def in_waiting(self):
        return sum(len(b) for _, b in self._due())

    def read(self, n):
        got = bytearray()
        for o in self._due():
            if len(got) >= n:
                break
            got += o[1]
            self.sketch.out.remove(o)
        if not got:
            # pyserial's read waits for a byte: to the next one due, at most 1 ms
            nxt = min([o[0] for o in self.sketch.out] + [self.clock.t + 1e-3])
            self.clock.t = max(self.clock.t + 1e-5, nxt)
        return bytes(got)

    def flush(self):
        pass

    def close(self):
        self.is_open = False


def _run(monkeypatch, lose=(), n_ticks=375):
    """Arm at 252.016 Hz (4 ticks) and close the loop ``n_ticks`` host ticks (the host loop's order: a
    FORCE per new STATE, estimated ticks, else the last force again); returns the
    transport, the port, the sketch and the host's commands (encoded) in order."""
    from hapsim.drivers import tick_align
    clock = SimClock()
    monkeypatch.setattr(tp, "time", clock)
    monkeypatch.setattr(tick_align, "time", clock)      # (the tick probe at the arming)
    drv = get_driver("hapkit-serial")
    tr = tp.DriverTransport(drv, "loop://")
    tr._ser.close()
    sketch = Sketch()
    port = SketchPort(clock, sketch, lose)
    tr._ser = port
    tr.send(fp.Config(1.0 / T, 5000, 10.0))
    t0 = clock.t = math.ceil(clock.t / T) * T + T
    used, run_est, xs = -1, 0, []
    st = types.SimpleNamespace(seq=0, time_us=0, status=0, force_seq=0)

    def force(x):
        v = (x - xs[-1]) / T if xs else 0.0
        return -K * x - BV * v

    for k in range(n_ticks):
        clock.t = max(clock.t, t0 + k * T)
        states = [m for m in tr.receive(0.0) if isinstance(m, fp.State)]
        used, run_est = host_command(tr, states, st, used, run_est, force, xs)
    sketch.run_to(clock.t)
    return tr, port, sketch


def _out_of_step(port, sketch):
    """For each byte lost, the time [s] from the loss to the first command after it the
    sketch read as the host sent it (an exact host command of 10 bytes: in step)."""
    sent = {d[-10:] for _, d in port.written if len(d) >= 10}
    waits = []
    for t_lost in port.lost_at:
        later = [t for t, raw in sketch.frames if t > t_lost + 2 * BYTE_S and raw in sent]
        waits.append((later[0] - t_lost) if later else math.inf)
    return waits


def test_no_loss_no_realignment(monkeypatch):
    """Without a byte lost the sketch reads every command in step and the transport never
    goes quiet (its rule needs bytes that made no reply)."""
    tr, port, sketch = _run(monkeypatch)
    assert tr.stats["resyncs"] == 0, tr.stats
    assert tr.stats["records"] > 300
    sent = {d for _, d in port.written if len(d) == 10}
    assert all(raw in sent for _, raw in sketch.frames)


@pytest.mark.parametrize("seed", range(8))
def test_a_lost_host_byte_is_realigned(monkeypatch, seed):
    """1 to 4 host bytes lost at random places of random commands, at least 60 ms apart:
    after each, the sketch reads the host's commands in step again within the rule's
    bound -- the commands written before its evidence is complete (``garbled_commands`` +
    1 unanswered, the oldest ``garbled_s`` old, each a period after the one before), the
    silence ``realign_quiet_s`` from the last write, the read timeout within it, and two
    periods for the next write and its tick -- and the loop goes on to the end (records
    in its last 100 ms). On the code before, the transport wrote every tick and the
    sketch never read a command in step again (every wait infinite)."""
    rng = np.random.default_rng(4100 + seed)
    drv = get_driver("hapkit-serial")
    n_loss = int(rng.integers(1, 5))
    writes = sorted(rng.choice(np.arange(40, 300, 16), n_loss, replace=False))
    lose = [(int(w), int(rng.integers(0, 10))) for w in writes]
    tr, port, sketch = _run(monkeypatch, lose)
    bound = ((drv.garbled_commands + 2) * T + drv.garbled_s + drv.realign_quiet_s
             + 2 * T)
    waits = _out_of_step(port, sketch)
    assert len(waits) == n_loss
    assert max(waits) <= bound, (lose, waits, bound, tr.stats)
    assert tr.stats["resyncs"] <= 2 * n_loss, tr.stats
    last = [t for t, raw in sketch.frames if t > sketch.t - 0.1]
    assert last and tr.stats["records"] > 200, tr.stats
    # one byte lost at a time: the sketch's replies say by how much it reads late, and
    # the fill puts it back at the next command (its commands out of step: the damaged
    # one's, one or two more and the fill's, each a period)
    assert tr.stats["resync_reasons"]["shifted"] == n_loss, tr.stats
    assert max(waits) <= 4 * T, waits


def _amplitudes(monkeypatch, lose, n_ticks=750):
    """The paddle's largest |x| [m] in each 0.3 s of a run (``_run``)."""
    seen = []
    real = Sketch._physics

    def physics(self, t):
        real(self, t)
        seen.append((t, self.x))

    monkeypatch.setattr(Sketch, "_physics", physics)
    tr, port, sketch = _run(monkeypatch, lose, n_ticks)
    xs = np.array(seen)
    edges = np.arange(xs[0, 0], xs[-1, 0] - 0.3, 0.3)
    return tr, [float(np.max(np.abs(xs[(xs[:, 0] >= a) & (xs[:, 0] < a + 0.3), 1])))
                for a in edges]


@pytest.mark.parametrize("seed", range(3))
def test_a_lossy_link_keeps_the_loop_damped(monkeypatch, seed):
    """A host byte lost every 20 commands or so (1 in 200, as the tables' runs lose):
    every loss realigned at once, the loop keeps its damping: the paddle's amplitude in
    the run's last 0.3 s within twice the lossless run's and a millimetre (an
    out-of-step sketch applies no force for a few periods each time). Realigned with the
    read timeout's silence alone (about 30 ms of no force a loss), these three runs kept
    their damping too, but on this test's sketch with one loss every 40 commands over 3 s
    the 10 mm swing grew to 42 mm (every 20 or 80: it decayed): the fill, which costs a
    period, is asked first (``shifted``, all but the last losses')."""
    rng = np.random.default_rng(4300 + seed)
    w = 40
    lose = []
    while w < 700:
        lose.append((w, int(rng.integers(0, 10))))
        w += int(rng.integers(15, 26))
    tr0, quiet = _amplitudes(monkeypatch, ())
    tr, amp = _amplitudes(monkeypatch, lose)
    assert amp[-1] <= 2 * quiet[-1] + 1e-3, (amp, quiet)
    assert tr.stats["resync_reasons"]["shifted"] >= len(lose) - 2, tr.stats


def test_emulated_board_reads_as_the_sketch(monkeypatch):
    """hapsim's emulated board takes the commands the sketch reads: random streams of
    commands, stray bytes and silences (some longer than the read timeout), each byte at
    its time on the wire; the same commands (function byte and values, bit for bit)
    complete at the same times as this test's sketch's. Before, the emulated board realigned on the header and the
    function byte (its commands after a stray byte were the host's; the sketch's are
    not)."""
    from hapsim.emulated.hapkit_serial_board import SketchReader
    drv = get_driver("hapkit-serial")
    rng = np.random.default_rng(77)
    for trial in range(20):
        ref = Sketch()
        reader = SketchReader()
        t = 0.0
        mine = []
        for _ in range(60):
            t += float(rng.choice([0.004, 0.001, 0.02, 0.0005]))
            r = rng.random()
            if r < 0.7:
                data = drv.encode_force(float(rng.normal(0, 1)))
            elif r < 0.85:
                data = bytes(rng.integers(0, 256, int(rng.integers(1, 4))).astype(np.uint8))
            else:
                data = drv.encode_force(0.5)[: int(rng.integers(1, 10))]
            # the bytes as the sketch gets them, one byte time apart
            ref.run_to(t)
            ref.write(t, data)
            times = [ref.rx[-len(data) + i][0] for i in range(len(data))]
            for i in range(len(data)):
                mine += reader.feed(data[i:i + 1], times[i])
        ref.run_to(t + 1.0)
        mine += reader.expire(t + 1.0)
        # (a NaN's payload is not kept through a double: compared as NaN)
        got = [(fn, a, b) for _, fn, a, b in mine]
        want = [(raw[1], *struct.unpack("<ff", raw[2:10])) for _, raw in ref.frames]
        assert len(got) == len(want), trial
        # (the same floats: a byte's time, or the last byte's time plus the timeout)
        assert [m[0] for m in mine] == ref.done, trial
        for g, w in zip(got, want):
            assert g[0] == w[0] and all(p == q or (p != p and q != q)
                                        for p, q in zip(g[1:], w[1:])), (trial, g, w)

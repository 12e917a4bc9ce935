"""The compiled mock tick (issue 13) against the Python mock, its reference.

Same host bytes at the same device times -> byte-identical device streams (STATE frames,
hence physics, late / clamp / watchdog flags), identical counters; over seeded random
devices and scripts with late, duplicated, stale, early, clamped and non-finite FORCEs,
PINGs, bad frames, frames split across reads, a watchdog gap, a re-CONFIG and STOP. Then
the compiled stretch on a real pty, and what stays in Python.
"""

from __future__ import annotations

import math
import os
import threading
import time

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.emulated.faults import FaultyDevice, parse_faults
from hapsim.emulated.fastmock import CompiledMock
from hapsim.host.loop import StopFlag
from hapsim.emulated.mock import MockDevice
from hapsim.emulated.serve import compiled_reason, serve_fd
from hapsim.scene import Device, Excitation, Hand, Impulse


def _random_device(rng) -> tuple[Device, Excitation, float]:
    hold = "zoh" if rng.random() < 0.7 else "ideal"
    dev = Device(mass=float(rng.uniform(0.02, 0.5)), friction=float(rng.uniform(0, 2)),
                 delay=int(rng.integers(1, 4)), hold=hold,
                 force_limit=float(rng.choice([math.inf, rng.uniform(0.5, 5)])),
                 position_resolution=float(rng.choice([0.0, 1e-5, 2.5e-6])),
                 coulomb=float(rng.choice([0.0, rng.uniform(0.01, 0.3), rng.uniform(0.3, 1.0)]))
                 if hold == "zoh"
                 else 0.0)
    imp = None
    if rng.random() < 0.5:
        imp = Impulse(force=float(rng.uniform(-3, 3)), start=0.002,
                      duration=float(rng.uniform(0.001, 0.01)))
    exc = Excitation(x0=float(rng.uniform(-0.01, 0.01)), v0=float(rng.uniform(-0.1, 0.1)),
                     impulse=imp)
    return dev, exc, float(rng.choice([500.0, 1000.0, 2000.0, 5000.0]))


def _force(seq: int, f: float) -> bytes:
    return fp.encode(fp.Force(seq & 0xFFFFFFFF, (f,)))


def _script(rng, rate: float, n_ticks: int, d: int) -> list:
    """(time_us, kind, bytes) events: the host's bytes before each tick, then the tick."""
    period = 1e6 / rate
    cfg = fp.encode(fp.Config(rate, 50_000, float(rng.uniform(1, 20))))
    ev = [(0, "feed", fp.encode(fp.HelloRequest(fp.PROTOCOL_VERSION))), (0, "feed", cfg)]
    t = 10.0
    carry = b""
    scale = float(rng.choice([0.1, 2.0]))      # small forces: Coulomb friction sticks
    for n in range(n_ticks):
        t += period * (1.0 + 0.2 * rng.standard_normal() if rng.random() < 0.3 else 1.0)
        if rng.random() < 0.01:
            t += 60_000.0                       # a gap beyond the watchdog period
        frames = []
        u = rng.random()
        seq = n - 1
        if u < 0.08:
            pass                                # late: no answer before the tick
        elif u < 0.12:
            frames += [_force(seq, 1.0), _force(seq, 2.0)]
        elif u < 0.15:
            frames.append(_force(seq - d - 2, 3.0))      # stale
        elif u < 0.17:
            frames.append(_force(seq + d + 3, 3.0))      # ahead
        elif u < 0.19:
            frames.append(fp.encode(fp.Ping(n, n)))
        elif u < 0.21:
            frames.append(b"\x05\x11\x22\x33\x00")                       # bad frame
        elif u < 0.23:
            frames.append(_force(seq, float(rng.uniform(-40, 40))))
        else:
            frames.append(_force(seq, float(rng.normal(0, scale))))
        if n == n_ticks // 3:                   # VELOCITY frames on (ZOH): Python ticks
            frames.append(fp.encode(fp.SensorsRequest(fp.SENSOR_VELOCITY)))
        if n == n_ticks // 3 + 20:              # and off again: compiled
            frames.append(fp.encode(fp.SensorsRequest(0)))
        if n == n_ticks // 2:
            frames.append(cfg)                  # re-CONFIG: the physics restarts
        if n == n_ticks - 20:
            frames.append(_force(seq, math.nan))        # fault, disarm
            frames.append(cfg)                  # and armed again
        data = carry + b"".join(frames)
        cut = int(rng.integers(0, len(data) + 1)) if data and rng.random() < 0.2 else len(data)
        data, carry = data[:cut], data[cut:]    # split across reads
        if data:
            ev.append((int(t), "feed", data))
        ev.append((int(t) + 1, "tick", b""))
    ev.append((int(t) + 2, "feed", carry + fp.encode(fp.Stop())))
    return ev


def _python_stream(dev, exc, rate, events) -> tuple[bytes, MockDevice, FaultyDevice]:
    mock = MockDevice(dev, exc, native_rate_hz=rate, lockstep=False)
    fd = FaultyDevice(mock)
    out = []
    for t, kind, data in events:
        if kind == "feed":
            fd.feed(data, t)
        else:
            fd.tick(t)
        out.append(fd.pop_due(t))
    return b"".join(out), mock, fd


def _compiled_stream(dev, exc, rate, events) -> tuple[bytes, MockDevice, FaultyDevice, int]:
    mock = MockDevice(dev, exc, native_rate_hz=rate, lockstep=False)
    fd = FaultyDevice(mock)
    cm = CompiledMock(fd)
    out = []
    compiled = 0
    for t, kind, data in events:
        fast = mock.armed and compiled_reason(mock) is None
        if kind == "feed":
            if fast:
                cm.load()
                rest = cm.feed(data, t)
                assert cm.store() == b""
                if rest:
                    fd.feed(rest, t)             # the Python receiver takes over
            else:
                fd.feed(data, t)
            out.append(fd.pop_due(t))
        elif fast:
            cm.load()
            out.append(cm.tick(t))
            cm.store()
            compiled += 1
        else:
            fd.tick(t)
            out.append(fd.pop_due(t))
    return b"".join(out), mock, fd, compiled


@pytest.mark.parametrize("seed", range(12))
def test_compiled_tick_is_byte_identical_to_the_python_mock(seed):
    rng = np.random.default_rng(seed)
    dev, exc, rate = _random_device(rng)
    events = _script(rng, rate, 400, dev.delay)
    want, mp, fp_ = _python_stream(dev, exc, rate, events)
    got, mc, fc, compiled = _compiled_stream(dev, exc, rate, events)
    assert compiled > 280                        # the compiled path did the ticks
    assert got == want
    assert mc.totals() == mp.totals()
    assert mc.stats.to_dict() == mp.stats.to_dict()
    assert fc.decoder.stats.as_dict() == fp_.decoder.stats.as_dict()
    assert mp.stats.faults == ["NON_FINITE_FORCE"] or mp.totals()["configs"] >= 2
    states = [m for m in fp.StreamDecoder().feed(want) if isinstance(m, fp.State)]
    flags = {bit for s in states for bit in (fp.STATUS_OVERRUN, fp.STATUS_FORCE_CLAMPED,
                                             fp.STATUS_WATCHDOG_TRIPPED) if s.status & bit}
    assert fp.STATUS_OVERRUN in flags            # the script exercised late ticks


def test_quantised_position_rounds_half_to_even_as_python():
    """The encoder step: Python's round() (ties to even), also on exact ties."""
    dev = Device(mass=0.1, friction=0.0, delay=1, position_resolution=0.5)
    for x0 in (0.25, 0.75, -0.25, -1.25, 1.2500000001, 3.0, -0.0):
        exc = Excitation(x0=x0)
        ev = [(0, "feed", fp.encode(fp.Config(1000.0, 50_000, 1.0))), (5, "tick", b"")]
        assert _compiled_stream(dev, exc, 1000.0, ev)[0] == \
            _python_stream(dev, exc, 1000.0, ev)[0]


def test_what_stays_in_python():
    dev = Device(mass=0.1, friction=0.5, delay=1)
    cfg = fp.Config(1000.0, 50_000, 10.0)

    def armed(**kw):
        m = MockDevice(kw.pop("device", dev), Excitation(x0=0.001), **kw)
        m.handle(cfg)
        return m

    assert compiled_reason(armed(lockstep=False)) is None
    assert compiled_reason(armed(lockstep=True)) == "lockstep"
    assert compiled_reason(armed(lockstep=False), parse_faults("drop=0.1", 0)) == "faults"
    assert compiled_reason(armed(lockstep=False, device=Device(
        mass=0.1, friction=0.5, delay=1, noise=1e-6))) == "noise"
    assert compiled_reason(armed(lockstep=False, device=Device(
        mass=0.1, friction=0.5, delay=1, hand=Hand(mass=0.2, damping=1.0, grip_stiffness=500.0,
                                                   grip_damping=2.0)))) == "hand grip or arm stiffness (state-space plant)"
    m = armed(lockstep=False)
    m.handle(fp.SensorsRequest(fp.SENSOR_VELOCITY))
    assert compiled_reason(m) == "velocity sensor"
    m = armed(lockstep=False)
    m.trace = []
    assert compiled_reason(m) == "trace"
    assert compiled_reason(MockDevice(dev, lockstep=False)) == "not configured"


def _drive_pty(n: int, tick: str = "compiled") -> tuple[dict, list]:
    """serve_fd on a real pty in a thread; a host answering each STATE for ``n`` STATEs,
    then STOP. Returns the mock's report and the STATEs seen."""
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    dev = Device(mass=0.1, friction=0.5, delay=1, force_limit=10.0)
    mock = MockDevice(dev, Excitation(x0=0.005), lockstep=False)
    box = {}
    th = threading.Thread(target=lambda: box.update(serve_fd(
        master, mock, exit_on_stop=True, handle_signals=False, flag=StopFlag(), tick=tick)),
        daemon=True)
    th.start()
    dec = fp.StreamDecoder()
    os.write(slave, fp.encode(fp.Config(1000.0, 50_000, 10.0)))
    seen = []
    t_end = time.monotonic() + 20.0
    while len(seen) < n and time.monotonic() < t_end:
        for msg in dec.feed(os.read(slave, 4096)):
            # one read may hold several STATEs (a host slowed by a loaded machine): the
            # first n are answered and kept, as a host that stops after n would
            if isinstance(msg, fp.State) and len(seen) < n:
                seen.append(msg)
                os.write(slave, _force(msg.seq, -100.0 * msg.position[0]))
    os.write(slave, fp.encode(fp.Stop()))
    th.join(10.0)
    os.close(slave)
    return box, seen


def test_compiled_stretch_serves_a_pty_host():
    """serve_fd with the compiled tick on a real pty: the ticks are the compiled code's,
    every FORCE is taken or counted, STOP (handed to Python) ends it."""
    rep, seen = _drive_pty(600)
    assert rep["end"] == "stop" and rep["saw_stop"]
    assert rep["compiled_ticks"] == rep["ticks"] >= 600       # loaded before HELLO
    assert rep["forces_rx"] + rep["stale"] == len(seen)      # every FORCE taken or counted
    assert rep["forces_rx"] > 0
    assert [s.seq for s in seen] == list(range(len(seen)))          # no tick skipped
    assert any(s.status & fp.STATUS_FORCE_APPLIED for s in seen[5:])


def test_python_tick_serves_when_the_compiled_one_cannot_load(monkeypatch):
    import hapsim.emulated.serve as fm

    def broken():
        raise ImportError("no numba here")

    monkeypatch.setattr(fm, "warm_up_mock", broken)
    rep, seen = _drive_pty(200)
    assert rep["end"] == "stop" and rep["compiled_ticks"] == 0
    assert rep["compiled_note"] == "compiled tick unavailable: ImportError: no numba here"
    assert [s.seq for s in seen] == list(range(len(seen))) and len(seen) == 200
    rep, _ = _drive_pty(100, tick="python")
    assert rep["compiled_ticks"] == 0 and "compiled_note" not in rep

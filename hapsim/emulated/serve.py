"""The mock device served on a byte stream (the master side of a pseudo-terminal): its
lockstep and real-time serving loop (:func:`serve_fd`), the tick in Python or compiled
(:mod:`hapsim.emulated.fastmock`, :func:`compiled_reason` says why not), what a silence, a
signal or a vanished host does. The device itself is :class:`hapsim.emulated.mock.MockDevice`."""

from __future__ import annotations

import gc
import os
import select
import signal
import time

import firmware_protocol as fp
from hapsim.device_model import DEFAULT_DEVICE, DEFAULT_EXCITATION, MockPhysics
from hapsim.emulated.mock import MockDevice
from hapsim.errors import ConfigError
from hapsim.outputs import write_json
from hapsim.spawn import StopFlag

__all__ = ["serve_fd", "compiled_reason", "warm_up_mock", "AUTO_COMPILED_HZ", "MOCK_SPIN_NS"]


#: Real-time ticks: the mock waits in ``select`` until this long before each deadline and
#: reads the host's bytes in a loop for the rest [ns]. 0: no spin (the wait ends at the
#: deadline; select's timeout is exact to the timer under SCHED_FIFO, whose timer slack is
#: 0). A spin to each deadline made the mock, a SCHED_FIFO process, throttled under load.
#: Above this native rate [Hz] ``serve_fd(tick="auto")`` ticks in numba; at and below it in
#: Python (the compiled tick's loading delays the HELLO by 0.5-1 s; 1 kHz runs do not need it).
AUTO_COMPILED_HZ = 2000.0


MOCK_SPIN_NS = 0


def _write(fd: int, data: bytes) -> bool:
    """Write ``data`` to a non-blocking fd; False when the peer is gone or the buffer full."""
    if not data:
        return True
    try:
        os.write(fd, data)
        return True
    except BlockingIOError:
        return False
    except OSError:        # EIO: no host has the port open; the next read says so
        return False


def _load_tick(dev):
    """The compiled tick for ``dev`` (numba's cache loaded, or compiled once), before any
    tick; ``(CompiledMock, None)``, or ``(None, reason)`` when it cannot load (the Python
    tick serves). Not in a thread beside the serving loop: a loading thread holding the GIL
    while the scheduler preempts it stalled the serving thread (late ticks, losses)."""
    try:
        from hapsim.emulated import fastmock
        from hapsim.blas import preload_numba_blas
        preload_numba_blas()
        warm_up_mock()
        return fastmock.CompiledMock(dev), None
    except Exception as exc:  # noqa: BLE001 - the Python tick serves instead
        return None, f"{type(exc).__name__}: {exc}"


def serve_fd(fd: int, mock: MockDevice, *, exit_on_stop: bool = True,
             report_path: str | None = None, flag: StopFlag | None = None,
             handle_signals: bool = True, plan=None, reopen=None, persistent: bool = False,
             on_host_gone=None, tick: str = "auto", hello: bool = True) -> dict:
    """Serve the mock device on a byte stream (the master side of a pty).

    Parameters
    ----------
    fd : int
        File descriptor to read host frames from and write device frames to; made
        non-blocking (a full buffer drops the frame rather than stalling the device).
    mock : MockDevice
        The device; its ``lockstep`` selects the serving loop (FORCE-driven or clock-driven).
    exit_on_stop : bool
        Return after a STOP from the host.
    report_path : str, optional
        Write :class:`MockStats` (plus decoder counters) there as JSON on exit (atomic).
    flag : StopFlag, optional
        Polled each iteration; serving ends when its ``set`` becomes true.
    handle_signals : bool
        Install SIGTERM/SIGINT handlers that end serving cleanly (main thread only).
    plan : FaultPlan, optional
        Faults to inject (:mod:`hapsim.emulated.faults`): wire faults on every frame sent
        and (``rx.`` names) on every frame received, stall / reset / vanish at device
        ticks, no HELLO.
    reopen : callable, optional
        ``reopen() -> fd``: a new port after a ``vanish`` (the old ``fd`` is closed when
        the port vanishes, after ``reopen.gone()`` when it has one: the port's path
        removed, :func:`hapsim.emulated.faults.reopener`); required when the plan can make
        the port vanish.
    persistent : bool
        Outlive hosts: when the host closes the port (EIO: no slave fd open, e.g. a run
        that ended or was killed) the device zeroes its force, disarms and waits for the
        next host to open the port, instead of returning; waiting also at the start (the
        caller may close its own slave fd). Use with ``exit_on_stop=False``.
    on_host_gone : callable, optional
        ``on_host_gone(stats)`` with :meth:`MockStats.to_dict` of the session that ended,
        called (outside any tick) each time a persistent device loses its host.
    tick : {"auto", "compiled", "python"}
        ``"auto"`` (default): ``"compiled"`` when the device's native rate is above
        :data:`AUTO_COMPILED_HZ`, else ``"python"`` -- loading numba and the compiled tick
        costs the child about 0.5-1 s before its HELLO (``tools/bench_startup.py``), which a
        1 kHz run does not need: the Python tick keeps 1 kHz (``tools/bench_mock.py``).
        ``"compiled"``: while armed in real time, the ticks run in numba
        (:class:`hapsim.emulated.fastmock.CompiledMock`: same bytes, no GIL, absolute-deadline
        sleeps) wherever :func:`compiled_reason` allows (not in
        lockstep, with a fault plan, sensor noise or a compliant grip: then Python);
        ``"python"``: this function's Python loop throughout (the reference).
    hello : bool
        Say ``0x00`` + HELLO at once, as a device does when its port opens (default). False:
        only when asked (HELLO_REQUEST), for a port the host opens *after* this starts
        (``hapsim run``'s embedded mock): pyserial's open flushes the input and could cut
        an early HELLO in half (a bad frame); the host always asks.

    Returns
    -------
    dict
        The final report (same content as the JSON file), with ``faults_injected`` and
        ``fault_events`` when a plan was given, and ``totals`` over every CONFIG.

    Raises
    ------
    ConfigError
        A plan with ``vanish`` but no ``reopen``, or an unknown ``tick``.

    Notes
    -----
    Real-time ticks run on ``time.monotonic_ns``: ``select`` sleeps until the absolute
    deadline (waking for the host's bytes meanwhile), then the tick; no spin (a
    ``SCHED_FIFO`` process spinning to each deadline is throttled under load;
    :data:`MOCK_SPIN_NS` before it, 0 by default). The mock is a process on a
    shared machine, not a microcontroller: when the OS schedules it more than half a period
    late, the tick is counted in ``overruns`` and the next tick is put at least half a period
    later (the schedule slips rather than compressing the host's time to answer, so ``late``
    counts the host's lateness, not the mock's). The physics is per tick, so slips do not
    change it. The garbage collector is disabled while serving.
    Serving ends on EOF/EIO (host side closed; not when ``persistent``), STOP (when
    ``exit_on_stop``), or the flag.
    """
    from hapsim.emulated.faults import FaultyDevice

    flag = flag or StopFlag()
    if tick not in ("auto", "compiled", "python"):
        raise ConfigError(f"unknown tick {tick!r}; valid: auto, compiled, python", key="--tick")
    if tick == "auto":
        tick = "compiled" if mock.native_rate_hz > AUTO_COMPILED_HZ else "python"
    if plan is not None and plan.has_vanish and reopen is None:
        raise ConfigError("a vanish fault needs a port that can come back (--link PATH)",
                          key="--faults")
    if handle_signals:
        def _on_signal(signum, frame):
            flag.request(signum)
        for s in (signal.SIGTERM, signal.SIGINT):
            signal.signal(s, _on_signal)
    os.set_blocking(fd, False)
    dev = FaultyDevice(mock, plan)
    fast = load_error = None
    if tick == "compiled" and not mock.lockstep and (plan is None or plan.empty):
        fast, load_error = _load_tick(dev)       # before HELLO: every tick is compiled
    python_once = False              # the compiled stretch saw the port hang up: Python reads
    t0 = time.monotonic_ns()

    def now_us() -> int:
        return (time.monotonic_ns() - t0) // 1000

    if hello:
        dev.connect(now_us())
        _write(fd, dev.pop_due(now_us()))
    gc_was = gc.isenabled()
    gc.disable()
    deadline = None            # monotonic ns of the next real-time tick
    period_ns = 0
    reason = "flag"
    awaiting_host = persistent      # a persistent device starts with no host (EIO) too
    try:
        while not flag.set:
            now_ns = time.monotonic_ns()
            t_us = (now_ns - t0) // 1000
            if dev.vanish_pending:               # the port disappears: its path first
                dev.vanish_pending = False       # (faults.reopener), then the master
                gone = getattr(reopen, "gone", None)
                if gone is not None:
                    gone()
                if fd is not None:
                    os.close(fd)
                fd = None
            if fd is None and not dev.vanished(t_us):
                fd = reopen()
                os.set_blocking(fd, False)
                awaiting_host = True             # EIO until the host opens the new port
                dev.poll(t_us)                   # 0x00 + HELLO on the new port
            if not mock.lockstep and mock.armed:
                if deadline is None:
                    period_ns = int(round(1e9 / mock.rate_hz))
                    deadline = now_ns
                wait = (deadline - now_ns - MOCK_SPIN_NS) / 1e9
            else:
                deadline = None
                wait = 0.05
            rel = dev.next_release_us()
            if rel is not None:
                wait = min(wait, max((rel - t_us) * 1e-6, 0.0))
            down = fd is None or dev.link_down(t_us)
            if down:
                end = max(dev.stalled_until_us, dev.vanished_until_us)
                wait = min(wait, max((end - t_us) * 1e-6, 0.0))
            pending = None           # host bytes the compiled stretch handed over
            if (fast is not None and deadline is not None and not down and not python_once
                    and not awaiting_host and not dev._out and not dev.decoder._overflow
                    and compiled_reason(dev.mock, dev.plan) is None):
                code, deadline, pending = fast.serve(fd, t0, deadline, period_ns, flag)
                if code != fast.R_HANDOFF:
                    python_once = code == fast.R_PORT
                    continue
            python_once = False
            r = []
            if pending is not None:
                r = [fd]
            elif wait > 0:
                try:
                    if down:
                        time.sleep(min(wait, 0.05))
                    else:
                        r, _, _ = select.select([fd], [], [], min(wait, 0.05))
                except InterruptedError:
                    continue
            elif not down:
                r = [fd]
            if r:
                try:
                    chunk = pending if pending is not None else os.read(fd, 4096)
                except BlockingIOError:
                    chunk = None
                except OSError:            # EIO: every slave fd closed
                    chunk = b""
                if chunk == b"" and awaiting_host:
                    time.sleep(0.001 if dev.vanished_until_us else 0.005)
                    chunk = None
                elif chunk == b"" and persistent:      # the host went away: wait for the next
                    mock.stop()
                    mock.new_hand()                    # ... whose hand takes the handle afresh
                    dev.decoder.reset()
                    awaiting_host = True
                    if on_host_gone is not None:
                        on_host_gone(mock.stats.to_dict())
                    continue
                elif chunk == b"":
                    reason = "host closed"
                    break
                if chunk:
                    awaiting_host = False
                    msgs = dev.feed(chunk, now_us())
                    if exit_on_stop and dev.plan.empty and any(
                            isinstance(m, fp.Stop) for m in msgs):
                        _write(fd, dev.pop_due(now_us()))
                        reason = "stop"
                        break
            if deadline is not None and mock.armed:
                now = time.monotonic_ns()
                if now >= deadline:
                    if now - deadline > period_ns // 2:
                        mock.stats.overruns += 1
                    dev.tick(now_us())
                    # the host always gets at least half a period to answer: a mock
                    # scheduled late slips its schedule (counted) instead of compressing it
                    deadline = max(deadline + period_ns, now + period_ns // 2)
                else:
                    dev.poll(now_us())           # host frames held by rx. faults
            else:
                dev.poll(now_us())
            if fd is not None:
                data = dev.pop_due(now_us())
                if data:
                    _write(fd, data)
    finally:
        if gc_was:
            gc.enable()
        mock.stop()
        report = mock.stats.to_dict()
        if reason == "flag" and flag.signal is not None:
            reason = f"signal {signal.Signals(flag.signal).name}"
        report["end"] = reason
        report["decoder"] = dev.decoder.stats.as_dict()
        report["totals"] = mock.totals()
        report["compiled_ticks"] = fast.ticks if fast is not None else 0
        if load_error is not None:
            report["compiled_note"] = f"compiled tick unavailable: {load_error}"
        if plan is not None:
            report["faults_injected"] = dict(plan.to_dict()["injected"])
            report["fault_events"] = dev.events
        if report_path:
            write_json(report_path, report)
    return report


# ----------------------------------------------------------------------------- Python side
def compiled_reason(mock, plan=None) -> str | None:
    """Why the compiled tick cannot serve this mock now; None when it can.

    Parameters
    ----------
    mock : MockDevice
        The device (its current CONFIG: physics and mode).
    plan : FaultPlan, optional
        The fault plan of :func:`~hapsim.emulated.serve.serve_fd`.

    Returns
    -------
    str or None
        ``"lockstep"``, ``"faults"``, ``"velocity sensor"`` (VELOCITY frames enabled by
        the host), ``"noise"``, ``"hand grip or arm stiffness (state-space plant)"``,
        ``"sub-sample delay (the split hold)"``, ``"hold"``, ``"subclass"``, ``"trace"`` or
        ``"not configured"``; None: compiled.
    """
    if type(mock) is not MockDevice:
        return "subclass"
    if mock.lockstep:
        return "lockstep"
    if plan is not None and not plan.empty:
        return "faults"
    if getattr(mock, "sensors", 0):
        return "velocity sensor"        # VELOCITY frames before each STATE: Python's
    if mock.trace is not None or mock.applied_log is not None:
        return "trace"
    ph = mock.physics
    if ph is None:
        return "not configured"
    if type(ph) is not MockPhysics:
        return "subclass"
    if ph._rng is not None:
        return "noise"
    if ph._grip is not None:
        return "hand grip or arm stiffness (state-space plant)"
    if ph.split > 0:
        return "sub-sample delay (the split hold)"
    if ph.hold not in ("zoh", "ideal"):
        return "hold"
    return None


def warm_up_mock() -> float:
    """Compile (or load from numba's cache) the compiled tick, on a pipe; seconds taken.

    Returns
    -------
    float
        Wall time [s].
    """
    from hapsim.emulated.faults import FaultyDevice
    from hapsim.spawn import StopFlag
    from hapsim.emulated.fastmock import CompiledMock

    t = time.perf_counter()
    mock = MockDevice(DEFAULT_DEVICE, DEFAULT_EXCITATION, lockstep=False)
    dev = FaultyDevice(mock)
    dev.feed(fp.encode(fp.Config(1000.0, 50_000, 10.0)), 0)
    cm = CompiledMock(dev)
    cm.load()
    cm.feed(fp.encode(fp.Force(0, (0.0,))), 0)
    cm.tick(0)
    cm.store()
    r, w = os.pipe()
    try:
        os.set_blocking(r, False)
        os.write(w, fp.encode(fp.Stop()))
        flag = StopFlag()
        now = time.monotonic_ns()
        cm.serve(r, now, now, 1_000_000, flag)       # reads the STOP: hands it over
    finally:
        os.close(r)
        os.close(w)
    return time.perf_counter() - t

"""The host loop: handshake, fixed-rate device- or host-clocked loop, safety.

Hot path (CONVENTIONS §4): per sample it decodes the STATE, steps the engine (numba), clamps,
encodes and writes the FORCE and writes one telemetry row *by index* into preallocated
arrays. No logging, no file I/O, no allocation beyond the protocol's message objects and
byte strings (unavoidable in Python). Counters (late, missed, clamped, overruns) are kept as
integers and reported at the end.

Timing convention: STATE ``n`` (``x(nT)``) is answered by FORCE ``seq = n`` computed from
``x[n]`` and ``x[n-1]``; the device applies it over ``[(n+d)T, (n+d+1)T)``.

Safety (from the first version): host-side clamp at the force limit; a non-finite position
or force sends zero force and stops; a stop flag (set by SIGINT/SIGTERM handlers) ends the
loop; safety stops end it with zero force: force at the limit in at least ``clamp_max`` of the
last ``clamp_window`` samples, or ``|x|`` beyond ``position_bound``. Every end sends a zero
FORCE then STOP.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, field

import numpy as np

import firmware_protocol as fp
from hapsim.errors import DeviceError

__all__ = ["LoopConfig", "LoopResult", "StopFlag", "HostLoop", "percentiles_us"]

_U32 = 0xFFFFFFFF


class StopFlag:
    """A flag a signal handler sets to end the loop cleanly (zero force, STOP, flush).

    Attributes
    ----------
    set : bool
        True once a stop was requested.
    signal : int or None
        Number of the signal that set it, if any.
    """

    def __init__(self) -> None:
        self.set = False
        self.signal = None

    def request(self, signum: int | None = None) -> None:
        """Request a stop (safe to call from a signal handler)."""
        self.set = True
        self.signal = signum


@dataclass
class LoopConfig:
    """Parameters of one host-loop run.

    Parameters
    ----------
    rate_hz : float
        Loop rate [Hz] sent in CONFIG.
    n_samples : int
        Samples to run (the telemetry capacity).
    delay : int
        Expected device delay d [samples] (for the late count from ``force_seq``).
    force_limit : float
        Host-side clamp and CONFIG.force_limit [N]; ``inf``: the device's HELLO limit.
    lockstep : bool
        The device is a lockstep mock: generous timeouts, no real-time expectations.
    host_clocked : bool
        Use the host's monotonic clock (sleep, then spin to each deadline) instead of
        answering each STATE: at each deadline the latest STATE is answered. With a
        lockstep device the host's clock paces the device (exact THS in real time); with
        a real-time device two clocks run side by side (host ticks a third of a period
        after the device's; ticks without a new STATE are skipped and counted as missed).
    watchdog_us : int
        CONFIG.watchdog_us [us].
    state_timeout : float
        Longest wait for a STATE before :class:`DeviceError` [s].
    hello_timeout : float
        Longest wait for HELLO [s].
    clamp_window, clamp_max : int
        Safety stop when the force was clamped in ``clamp_max`` of the last
        ``clamp_window`` samples.
    position_bound : float
        Safety stop when ``|x|`` exceeds it [m].
    """

    rate_hz: float
    n_samples: int
    delay: int = 1
    force_limit: float = math.inf
    lockstep: bool = False
    host_clocked: bool = False
    watchdog_us: int = 50_000
    state_timeout: float = 1.0
    hello_timeout: float = 3.0
    clamp_window: int = 100
    clamp_max: int = 50
    position_bound: float = math.inf


@dataclass
class LoopResult:
    """What a host-loop run did.

    Attributes
    ----------
    samples : int
        Samples answered (telemetry rows).
    stop_reason : str
        ``"duration"``, ``"signal SIGTERM"``/``"signal SIGINT"``, ``"safety: ..."`` or
        ``"device: ..."``.
    safety_stop : bool
        True when a safety rule ended the run.
    late : int
        Ticks the device reported holding an older force (``seq - force_seq != d`` or
        STATUS_OVERRUN).
    missed : int
        STATE sequence numbers never seen (gaps); host-clocked: host ticks without a new
        STATE (skipped: no engine step, no FORCE).
    overruns : int
        Host-clocked deadlines missed by more than one period.
    clamped : int
        Samples whose force the host clamped.
    turnaround_us : dict
        ``p50``, ``p99``, ``p999``, ``max`` of STATE-read to FORCE-written [us].
    hello : Hello or None
        The device's HELLO.
    faults : list of str
        FAULT names received.
    decoder : dict
        Stream decoder counters (serial transports).
    ping_rtt_us : dict
        PING -> PONG round trip before arming [us]: ``p50``, ``p99``, ``p999``, ``max``,
        ``answered``, ``sent``.
    """

    samples: int = 0
    stop_reason: str = "duration"
    safety_stop: bool = False
    late: int = 0
    missed: int = 0
    overruns: int = 0
    clamped: int = 0
    turnaround_us: dict = field(default_factory=dict)
    hello: object = None
    faults: list = field(default_factory=list)
    decoder: dict = field(default_factory=dict)
    ping_rtt_us: dict = field(default_factory=dict)


def percentiles_us(values: np.ndarray) -> dict:
    """``p50``, ``p99``, ``p999`` and ``max`` of ``values`` [us] (None when empty)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None}
    p = np.percentile(v, [50, 99, 99.9])
    return {"p50": float(p[0]), "p99": float(p[1]), "p999": float(p[2]), "max": float(v.max())}


class HostLoop:
    """The fixed-rate host loop between an engine and a device transport.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        The scene (warmed up: its kernel already compiled/loaded).
    transport : object
        A transport of :mod:`hapsim.daemon.transport`.
    config : LoopConfig
        Run parameters.
    telemetry : Telemetry
        Preallocated buffer (capacity >= ``config.n_samples``).
    stop : StopFlag, optional
        Polled every sample.
    """

    def __init__(self, engine, transport, config: LoopConfig, telemetry,
                 stop: StopFlag | None = None):
        self.engine = engine
        self.transport = transport
        self.config = config
        self.tel = telemetry
        self.stop = stop or StopFlag()
        self.result = LoopResult()
        self._last_seq = -1

    # ------------------------------------------------------------------ handshake
    def handshake(self) -> fp.Hello:
        """Ask for HELLO, check it, send CONFIG (arms the device).

        Returns
        -------
        Hello or None
            None when the stop flag was set before the device answered.

        Raises
        ------
        DeviceError
            No HELLO within ``hello_timeout``, a protocol version mismatch, or not 1 axis.
        """
        cfg = self.config
        tr = self.transport
        hello = None
        end = time.monotonic() + cfg.hello_timeout
        next_ask = 0.0
        while hello is None:
            if self.stop.set:
                return None
            now = time.monotonic()
            if now >= end:
                raise DeviceError(f"no HELLO from the device within {cfg.hello_timeout:g} s "
                                  f"(port {tr.info.get('port')}); last frames:\n"
                                  f"{tr.last_frames() or '(none received)'}")
            if now >= next_ask:
                tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
                next_ask = now + 0.5
            for msg in tr.receive(0.05):
                if isinstance(msg, fp.Hello):
                    hello = msg
        if hello.protocol_version != fp.PROTOCOL_VERSION:
            raise DeviceError(f"device speaks protocol {hello.protocol_version}, "
                              f"hapsim speaks {fp.PROTOCOL_VERSION}")
        if hello.n_axes != 1:
            raise DeviceError(f"device has {hello.n_axes} axes; hapsim run drives 1-DoF devices")
        limit = cfg.force_limit if math.isfinite(cfg.force_limit) else hello.force_limit
        self.force_limit = min(float(limit), float(hello.force_limit))
        self._measure_ping()
        tr.receive(0.0)  # drop anything stale before arming
        tr.send(fp.Config(float(cfg.rate_hz), int(cfg.watchdog_us), float(self.force_limit)))
        self.result.hello = hello
        return hello

    def _measure_ping(self, count: int = 16) -> None:
        """Round-trip PING -> PONG before arming [us] (transport + device answer time)."""
        tr = self.transport
        rtts = []
        for nonce in range(count):
            t0 = time.perf_counter_ns()
            tr.send(fp.Ping(nonce, t0 // 1000))
            end = time.monotonic() + 0.2
            got = False
            while not got and time.monotonic() < end:
                for msg in tr.receive(0.02):
                    if isinstance(msg, fp.Pong) and msg.nonce == nonce:
                        got = True
            if got:
                rtts.append((time.perf_counter_ns() - t0) * 1e-3)
        self.result.ping_rtt_us = percentiles_us(np.array(rtts))
        self.result.ping_rtt_us["answered"] = len(rtts)
        self.result.ping_rtt_us["sent"] = count

    # ------------------------------------------------------------------ run
    def run(self) -> LoopResult:
        """Handshake, run the loop, then always send zero force and STOP.

        Returns
        -------
        LoopResult

        Raises
        ------
        DeviceError
            Device silent, port failure, or handshake failure (zero force + STOP are still
            attempted).
        """
        gc_was = gc.isenabled()
        gc.collect()             # before CONFIG arms the device: a real-time device ticks
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
                self._run_host_clocked()
            else:
                self._run_device_clocked()
        finally:
            self._shutdown()
            if gc_was:
                gc.enable()
        res = self.result
        if self.stop.set and res.stop_reason == "duration" and self.stop.signal is not None:
            res.stop_reason = f"signal {_signame(self.stop.signal)}"
        res.samples = self.tel.n
        res.turnaround_us = percentiles_us(self.tel.turnaround_us[:self.tel.n])
        dec = getattr(self.transport, "decoder", None)
        if dec is not None:
            res.decoder = dec.stats.as_dict()
        return res

    def _shutdown(self) -> None:
        tr = self.transport
        try:
            tr.send(fp.Force((self._last_seq + 1) & _U32, (0.0,)))
            tr.send(fp.Stop())
        except DeviceError:
            pass

    def _state_timeout(self) -> None:
        tr = self.transport
        raise DeviceError(f"no STATE from the device for {self.config.state_timeout:g} s "
                          f"(port {tr.info.get('port')}); last frames:\n"
                          f"{tr.last_frames() or '(none received)'}")

    def _run_device_clocked(self) -> None:
        cfg = self.config
        tr = self.transport
        eng = self.engine
        tel = self.tel
        stop = self.stop
        res = self.result
        n_max = min(cfg.n_samples, tel.capacity)
        t_arr, x_arr, f_arr, s_arr, ta_arr, late_arr = (tel.time, tel.position, tel.force,
                                                        tel.seq, tel.turnaround_us, tel.late)
        lim = self.force_limit
        d = cfg.delay
        pos_bound = cfg.position_bound
        win = np.zeros(max(cfg.clamp_window, 1), dtype=np.int8)
        wlen = win.size
        wsum = 0
        clamp_max = cfg.clamp_max
        State, Fault, Force = fp.State, fp.Fault, fp.Force
        overrun_bit = fp.STATUS_OVERRUN
        isfinite = math.isfinite
        perf = time.perf_counter_ns
        mono = time.monotonic
        receive, send = tr.receive, tr.send
        expect = -1
        i = 0
        last_rx = mono()
        timeout = cfg.state_timeout
        while i < n_max and not stop.set:
            msgs = receive(0.1)
            t_rx = perf()
            if not msgs:
                if mono() - last_rx > timeout:
                    self._state_timeout()
                continue
            last_rx = mono()
            for msg in msgs:
                if type(msg) is not State:
                    if type(msg) is Fault:
                        name = fp.FAULT_NAMES.get(msg.code, f"0x{msg.code:04X}")
                        res.faults.append(name)
                        res.stop_reason = f"device: FAULT {name} (detail {msg.detail})"
                        stop.set = True
                        break
                    continue
                seq = msg.seq
                x = msg.position[0]
                if expect < 0:
                    eng.set_port_position(x, at_rest=True)
                elif seq != expect:
                    res.missed += (seq - expect) & _U32
                expect = (seq + 1) & _U32
                lt = 0
                if seq >= d and ((seq - msg.force_seq) & _U32 != d or msg.status & overrun_bit):
                    if d > 0 or msg.status & overrun_bit:
                        lt = 1
                        res.late += 1
                f = eng.port_step(x) if isfinite(x) else math.nan
                if not isfinite(f):
                    send(Force(seq, (0.0,)))
                    self._last_seq = seq
                    res.stop_reason = "safety: non-finite position or force"
                    res.safety_stop = True
                    stop.set = True
                    break
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
                j = i % wlen
                wsum += c - win[j]
                win[j] = c
                res.clamped += c
                t_arr[i] = msg.time_us * 1e-6
                x_arr[i] = x
                f_arr[i] = f
                s_arr[i] = seq
                ta_arr[i] = (t_tx - t_rx) * 1e-3
                late_arr[i] = lt
                i += 1
                tel.n = i
                if wsum >= clamp_max:
                    res.stop_reason = (f"safety: force at the limit {lim:g} N in {wsum} of the "
                                       f"last {wlen} samples")
                    res.safety_stop = True
                    stop.set = True
                    break
                if x > pos_bound or x < -pos_bound:
                    res.stop_reason = f"safety: position {x:.6g} m beyond +-{pos_bound:g} m"
                    res.safety_stop = True
                    stop.set = True
                    break
                if i >= n_max:
                    break
        if stop.set and res.stop_reason == "duration" and stop.signal is not None:
            res.stop_reason = f"signal {_signame(stop.signal)}"

    def _run_host_clocked(self) -> None:
        cfg = self.config
        tr = self.transport
        eng = self.engine
        tel = self.tel
        stop = self.stop
        res = self.result
        n_max = min(cfg.n_samples, tel.capacity)
        lim = self.force_limit
        pos_bound = cfg.position_bound
        win = np.zeros(max(cfg.clamp_window, 1), dtype=np.int8)
        wlen = win.size
        wsum = 0
        State, Force = fp.State, fp.Force
        isfinite = math.isfinite
        mono_ns = time.monotonic_ns
        perf = time.perf_counter_ns
        sleep = time.sleep
        receive, send = tr.receive, tr.send
        period_ns = int(round(1e9 / cfg.rate_hz))
        latest = None
        # wait for the first STATE, then tick on the host clock
        end = time.monotonic() + cfg.state_timeout
        while latest is None and not stop.set:
            for msg in receive(0.05):
                if type(msg) is State:
                    latest = msg
            if latest is None and time.monotonic() > end:
                self._state_timeout()
        if latest is None:
            return
        eng.set_port_position(latest.position[0], at_rest=True)
        used_seq = -1
        last_new = time.monotonic()
        # a real-time device ticks on the same monotonic clock: tick a third of a period
        # after its STATE arrives, so the STATE is in and the FORCE is back before its
        # next tick (ticking in phase with the device would race it every period)
        deadline = mono_ns() + (0 if cfg.lockstep else period_ns // 3)
        i = 0
        while i < n_max and not stop.set:
            remaining = deadline - mono_ns()
            if remaining > 600_000:
                sleep((remaining - 400_000) * 1e-9)
            while mono_ns() < deadline:
                for msg in receive(0.0):
                    if type(msg) is State:
                        latest = msg
            for msg in receive(0.0):
                if type(msg) is State:
                    latest = msg
            t_rx = perf()
            if latest.seq == used_seq:
                # no new sample since the last tick: stepping the engine with a stale
                # position would corrupt its velocity; skip this tick (counted)
                res.missed += 1
                if time.monotonic() - last_new > cfg.state_timeout:
                    self._state_timeout()
                deadline += period_ns
                continue
            last_new = time.monotonic()
            x = latest.position[0]
            seq = latest.seq
            lt = 0
            if seq != used_seq and seq >= cfg.delay > 0 and (
                    (seq - latest.force_seq) & _U32 != cfg.delay
                    or latest.status & fp.STATUS_OVERRUN):
                lt = 1
                res.late += 1
            used_seq = seq
            f = eng.port_step(x) if isfinite(x) else math.nan
            if not isfinite(f):
                send(Force(seq, (0.0,)))
                res.stop_reason = "safety: non-finite position or force"
                res.safety_stop = True
                break
            c = 0
            if f > lim:
                f, c = lim, 1
            elif f < -lim:
                f, c = -lim, 1
            send(Force(seq, (f,)))
            t_tx = perf()
            self._last_seq = seq
            j = i % wlen
            wsum += c - win[j]
            win[j] = c
            res.clamped += c
            tel.time[i] = latest.time_us * 1e-6
            tel.position[i] = x
            tel.force[i] = f
            tel.seq[i] = seq
            tel.turnaround_us[i] = (t_tx - t_rx) * 1e-3
            tel.late[i] = lt
            i += 1
            tel.n = i
            if wsum >= cfg.clamp_max:
                res.stop_reason = (f"safety: force at the limit {lim:g} N in {wsum} of the "
                                   f"last {wlen} samples")
                res.safety_stop = True
                break
            if x > pos_bound or x < -pos_bound:
                res.stop_reason = f"safety: position {x:.6g} m beyond +-{pos_bound:g} m"
                res.safety_stop = True
                break
            deadline += period_ns
            now = mono_ns()
            if now - deadline > period_ns:
                res.overruns += 1
                deadline = now
        if stop.set and res.stop_reason == "duration" and stop.signal is not None:
            res.stop_reason = f"signal {_signame(stop.signal)}"


def _signame(signum: int) -> str:
    import signal
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)

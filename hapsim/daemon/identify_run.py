"""Excite a device safely and record its STATE / FORCE stream (``hapsim identify``).

The excitation is a scene-less "engine" for :class:`hapsim.daemon.loop.HostLoop`: so the
identification runs under the very same loop as ``hapsim run`` -- handshake, CONFIG with the
device watchdog armed, host-side force clamp, the safety stops (force at the limit in half
of the last 100 samples, position beyond the envelope, non-finite values), zero force and
STOP at the end, loss recovery.

Force sent answering the position ``x[n]``::

    f[n] = -Kc (x[n] - x_start) - Bc (x[n] - x[n-1]) / T + r[n]

a weak centring spring-damper (``Kc = 0.5 F_lim / envelope``: half the force limit at the
envelope's edge; ``Bc = 1.5 Kc (d_max + 1) T`` [N s/m], enough to outweigh the negative
damping ``~Kc (d + 1) T`` a delay of up to ``d_max`` samples and the backward difference
give the spring) plus ``g r[n]``:
a pseudo-random binary sequence of amplitude ``0.1 F_lim`` whose levels last 1..40
samples at random (a wide band: the mass line above the friction corner, the friction
below), added to a square wave of ``0.1 F_lim`` with a 0.5 s period (slow constant-force
steps: long stretches of one velocity sign, which is what separates Coulomb from viscous
friction). The gain ``g`` starts at 1 and halves each time the device passes 60 % of the
envelope (then 66 %, ...), so a light device stays inside it. The fit (:mod:`hapsim.analysis.device_fit`) uses the forces as sent, so the
centring loop does not bias it.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["ExcitationPlan", "ExcitationEngine", "excitation_plan", "record"]


class ExcitationPlan:
    """The precomputed excitation of one identification run.

    Parameters
    ----------
    r : ndarray, shape (n,)
        Open-loop part of the force per sample [N].
    kc : float
        Centring stiffness [N/m].
    bc : float
        Centring damping [N s/m].
    rate_hz : float
        Sample rate [Hz].
    envelope : float
        Half-width of the position envelope [m]; the open-loop part is halved each time
        the device passes 60 % of it.
    """

    def __init__(self, r: np.ndarray, kc: float, bc: float, rate_hz: float,
                 envelope: float) -> None:
        self.r = np.asarray(r, float)
        self.envelope = float(envelope)
        self.kc = float(kc)
        self.bc = float(bc)
        self.rate_hz = float(rate_hz)


def excitation_plan(n: int, rate_hz: float, force_limit: float, envelope: float, *,
                    max_delay: int = 5, seed: int = 0) -> ExcitationPlan:
    """Build the excitation (module notes).

    Parameters
    ----------
    n : int > 0
        Samples.
    rate_hz : float > 0
        Sample rate [Hz].
    force_limit : float > 0
        Largest force sent [N].
    envelope : float > 0
        Half-width of the position envelope [m].
    max_delay : int >= 0
        Largest device delay the centring loop must stay stable with [samples].
    seed : int
        Seed of the PRBS.

    Returns
    -------
    ExcitationPlan

    Raises
    ------
    ConfigError
        Non-positive force limit, envelope, rate or length.
    """
    if not (math.isfinite(force_limit) and force_limit > 0):
        raise ConfigError(f"must be a positive force [N], got {force_limit!r}",
                          key="--force-limit")
    if not (math.isfinite(envelope) and envelope > 0):
        raise ConfigError(f"must be a positive distance [m], got {envelope!r}",
                          key="--envelope")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"must be a positive rate [Hz], got {rate_hz!r}", key="--rate")
    if n < 1:
        raise ConfigError(f"must be > 0 samples, got {n}", key="--duration")
    T = 1.0 / rate_hz
    rng = np.random.default_rng(seed)
    a = 0.1 * force_limit
    r = np.empty(n)
    i = 0
    level = a
    while i < n:
        k = int(rng.integers(1, 41))
        r[i:i + k] = level
        level = -level if rng.random() < 0.5 else level
        i += k
    t = np.arange(n) * T
    r += a * np.where((t % 0.5) < 0.25, 1.0, -1.0)
    # ramp in and out over 20 ms: no step at arming, zero force at the end
    nr = min(max(int(0.02 * rate_hz), 1), n // 4 or 1)
    ramp = np.ones(n)
    ramp[:nr] = np.linspace(0.0, 1.0, nr)
    ramp[n - nr:] = np.minimum(ramp[n - nr:], np.linspace(1.0, 0.0, nr))
    r *= ramp
    kc = 0.5 * force_limit / envelope
    bc = 1.5 * kc * (max_delay + 1) * T
    return ExcitationPlan(r, kc, bc, rate_hz, envelope)


class ExcitationEngine:
    """The excitation as an engine of :class:`~hapsim.daemon.loop.HostLoop`.

    Parameters
    ----------
    scene : ExcitationPlan
        Called ``scene`` because the loop rebuilds an engine after a loss as
        ``type(engine)(engine.scene)`` (the excitation then restarts).

    Notes
    -----
    :meth:`port_step` is the hot path: two multiplications and an array read, no allocation.
    """

    def __init__(self, scene: ExcitationPlan) -> None:
        self.scene = scene
        self._r = scene.r
        self._n = scene.r.size
        self._kc = scene.kc
        self._bc = scene.bc * scene.rate_hz
        self._k = 0
        self._xc = 0.0
        self._xp = 0.0
        self._g = 1.0
        self._edge = 0.6 * scene.envelope

    def set_port_position(self, position: float, at_rest: bool = False) -> None:
        """Centre the excitation at the device's position ``position`` [m]."""
        self._xc = float(position)
        self._xp = float(position)

    def port_step(self, position: float) -> float:
        """Force [N] answering the position ``position`` [m] (module notes)."""
        k = self._k
        e = position - self._xc
        if (e > self._edge or e < -self._edge) and self._g > 1e-3:
            self._g *= 0.5                 # nearing the envelope: excite less from now on
            self._edge *= 1.1
        r = self._g * self._r[k] if k < self._n else 0.0
        self._k = k + 1
        f = -self._kc * e - self._bc * (position - self._xp) + r
        self._xp = position
        return f


def _progress_thread(tel, total: int, stop_evt: threading.Event, label: str):
    from hapsim.progress import Progress

    def run():
        with Progress(total, label, "samples", delay=0.5) as bar:
            while not stop_evt.wait(0.25):
                bar.update(min(tel.n, total))
            bar.update(min(tel.n, total))
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def record(device=None, *, port: str | None = None, baud: int = 115200,
           rate_hz: float = 1000.0, duration: float = 4.0, force_limit: float = 2.0,
           envelope: float = 0.01, max_delay: int = 5, seed: int = 0, noise_seed: int = 0,
           transport: str | None = None, lockstep: bool = False, progress: bool = True,
           handle_signals: bool = True, stop=None, driver: str | None = None):
    """Run the excitation on a device (or the mock of ``device``) and return the record.

    Parameters
    ----------
    device : hapsim.scene.Device, optional
        The device the mock models (ignored with ``port``); default: the mock's default.
    port : str, optional
        Serial port of a device speaking the framed protocol.
    baud : int
        Baud rate for ``port``.
    rate_hz : float
        Loop rate [Hz].
    duration : float
        Excitation length [s].
    force_limit : float
        Largest force sent [N] (also the CONFIG force limit).
    envelope : float
        Position envelope [m]: the loop stops (zero force, STOP) beyond it.
    max_delay : int
        Largest delay the centring loop is made stable for [samples].
    seed : int
        Seed of the excitation.
    noise_seed : int
        Seed of the mock's sensor noise.
    transport : {"inprocess", "pty", "serial"}, optional
        Default: ``"serial"`` with ``port``, ``"pty"`` (embedded mock) otherwise.
    lockstep : bool
        Lockstep mock (``"inprocess"`` implies it).
    progress : bool
        Show a progress bar on a terminal (stderr).
    handle_signals : bool
        SIGINT/SIGTERM end the excitation cleanly (zero force, STOP; main thread only).
    stop : StopFlag, optional
        External stop flag.
    driver : str, optional
        A protocol of :mod:`hapsim.drivers` (host-clocked; without ``port``, that
        driver's mock of ``device``); None or ``"framed"``: hapsim's own.

    Returns
    -------
    dict
        ``position``, ``force``, ``late``, ``time``, ``seq`` (arrays), ``period`` [s], ``loop``
        (stop reason, safety stop, late, clamped, samples, transport).

    Raises
    ------
    ConfigError
        Bad values (:func:`excitation_plan`), an unknown transport.
    DeviceError, ProtocolError
        As :meth:`hapsim.daemon.loop.HostLoop.run`.
    """
    from hapsim.daemon.loop import HostLoop, LoopConfig, StopFlag
    from hapsim.daemon.mock import DEFAULT_DEVICE, MockDevice
    from hapsim.daemon.telemetry import Telemetry
    from hapsim.scene import Excitation

    if not (math.isfinite(duration) and duration > 0):
        raise ConfigError(f"must be a positive number of seconds, got {duration!r}",
                          key="--duration")
    n = max(int(round(duration * rate_hz)), 1)
    plan = excitation_plan(n, rate_hz, force_limit, envelope, max_delay=max_delay, seed=seed)
    if transport is None:
        transport = "serial" if port else "pty"
    if transport not in ("inprocess", "pty", "serial"):
        raise ConfigError(f"unknown transport {transport!r}; valid: inprocess, pty, serial",
                          key="transport")
    dev = device or DEFAULT_DEVICE
    stop = stop or StopFlag()
    old = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    embedded = None
    lock = lockstep or transport == "inprocess"
    use_driver = driver not in (None, "framed")
    if use_driver:
        from hapsim.drivers import get_driver
        drv = get_driver(driver)
        lock = lock or port is None
    try:
        if use_driver:
            from hapsim.drivers.transport import DriverTransport
            if port is None:
                from hapsim.drivers.mock import EmbeddedDriverMock
                embedded = EmbeddedDriverMock(driver, dev, Excitation(), rate_hz, seed=noise_seed)
                tr = DriverTransport(drv, embedded.port, delay=dev.delay)
                embedded.release_slave()
            else:
                tr = DriverTransport(drv, port, delay=1)
        elif transport == "inprocess":
            from hapsim.daemon.transport import InProcessTransport
            mock = MockDevice(dev, Excitation(), native_rate_hz=rate_hz, lockstep=True,
                              seed=noise_seed)
            tr = InProcessTransport(mock)
        elif transport == "pty":
            from hapsim.daemon.transport import EmbeddedMock, SerialTransport
            embedded = EmbeddedMock(dev, Excitation(), rate_hz, lockstep=lock, seed=noise_seed)
            tr = SerialTransport(embedded.port, baud)
            embedded.release_slave()
        else:
            from hapsim.daemon.transport import SerialTransport
            tr = SerialTransport(port, baud)
        d_expect = dev.delay if port is None else 1
        cfg = LoopConfig(rate_hz=rate_hz, n_samples=n, delay=d_expect, force_limit=force_limit,
                         lockstep=lock, host_clocked=use_driver,
                         state_timeout=(0.5 if transport == "inprocess" else 10.0) if lock
                         else 1.0,
                         hello_timeout=30.0 if transport == "pty" else 5.0,
                         position_bound=envelope, reconnect=False)
        tel = Telemetry(n)
        loop = HostLoop(ExcitationEngine(plan), tr, cfg, tel, stop)
        evt = threading.Event()
        th = None
        if progress:
            th = _progress_thread(tel, n, evt, "hapsim identify: exciting")
        try:
            res = loop.run()
        finally:
            evt.set()
            if th is not None:
                th.join(1.0)
            tr.close()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if embedded is not None:
            embedded.report()
            embedded.close()
    cols = tel.columns()
    force = cols["force"].copy()
    if use_driver:          # what the device was sent: the protocol's quantised force
        force = np.array([drv.applied_force(v) for v in force])
    return {"position": cols["position"].copy(), "force": force,
            "late": cols["late"].astype(bool), "time": cols["time"].copy(),
            "seq": cols["seq"].copy(),
            "period": 1.0 / rate_hz,
            "loop": {"samples": int(res.samples), "requested": n,
                     "stop_reason": res.stop_reason, "safety_stop": bool(res.safety_stop),
                     "late": int(res.late), "clamped": int(res.clamped),
                     "transport": transport, "lockstep": bool(lock),
                     "port": tr.info.get("port"), "faults": list(res.faults),
                     "f_max": float(res.f_max), "v_max": float(res.v_max),
                     "centring": {"K": plan.kc, "B": plan.bc}}}

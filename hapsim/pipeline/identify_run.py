"""Excite a device safely and record its STATE / FORCE stream (``hapsim identify``).

The excitation (:mod:`hapsim.pipeline.excitation`) is a scene-less "engine" for
:class:`hapsim.host.loop.HostLoop`: so the identification runs under the very same loop as
``hapsim run`` -- handshake, CONFIG with the device watchdog armed, host-side force clamp,
the safety stops (force at the limit in half of the last 100 samples, position beyond the
envelope, non-finite values), zero force and STOP at the end, loss recovery.
"""

from __future__ import annotations

import math
import signal
import threading
import time

import numpy as np

from hapsim.errors import ConfigError, DeviceError, error_record
from hapsim.pipeline.excitation import ExcitationEngine, excitation_plan

__all__ = ["record"]


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
           handle_signals: bool = True, stop=None, driver: str | None = None,
           driver_options: dict | None = None, mock_options: dict | None = None,
           travel: float | None = None, rt_priority: int = 10):
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
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``).
    mock_options : dict, optional
        The driver mock's hardware (default: the device the driver describes).
    travel : float, optional
        The FireFader's travel between its end stops [m]: before the excitation, a sweep
        between the stops finds its position scale
        (:func:`hapsim.drivers.firefader_travel.find_travel`), which the excitation and
        ``protocol_options`` then use.
    rt_priority : int
        ``SCHED_FIFO`` priority of the loop on a real-time port (pty or serial, not
        lockstep) where the OS permits it, as ``hapsim run``'s (0: normal scheduling;
        :class:`hapsim.host.realtime.RealtimePriority`): a host preempted mid-push leaves
        the device its force for the preemption, beyond the excitation's plan.

    Returns
    -------
    dict
        ``position``, ``force``, ``late``, ``time``, ``seq`` (arrays), ``period`` [s], ``loop``
        (stop reason, safety stop, late, clamped, samples, transport, ``force_scale``,
        ``direction_probe``: what a driver that finds its motor direction first found,
        :class:`hapsim.drivers.haply_probe.DirectionProbe`, else None; ``travel_sweep``:
        :class:`hapsim.drivers.firefader_travel.TravelSweep` as a dict, or None),
        ``protocol_options`` (the driver's parameters, the direction found included),
        ``lost`` (None, or the DeviceError that ended the excitation after its first row:
        the record up to it is returned, ``loop["stop_reason"]`` "device lost: ..." and
        ``loop["error"]`` its type and message).
        ``force`` is the force the device applied for each sample: what the host sent,
        on the actuator's grid when the device reports one (a driver's protocol
        resolution, or a framed device's ``HELLO.force_scale`` > 0 [N], the nearest
        step: a PWM of 256 steps rounds every force, and a fit of the force sent would
        see that rounding's gain on the excitation as a wrong mass).

    Raises
    ------
    ConfigError
        Bad values (:func:`excitation_plan`), an unknown transport.
    DeviceError, ProtocolError
        As :meth:`hapsim.host.loop.HostLoop.run`, before the first row was recorded (a
        DeviceError after it ends the record: ``lost``).
    IdentificationError
        The Haply joint's motor direction cannot be found (it does not move under the
        probe's torque pulses, or moves the same way under both signs); the FireFader's
        sweep found no end stop it can take as one (``travel``).
    """
    from hapsim.drivers import DEFAULT, family
    from hapsim.host.loop import HostLoop, LoopConfig, StopFlag
    from hapsim.emulated.mock import DEFAULT_DEVICE, MockDevice
    from hapsim.host.telemetry import Telemetry
    from hapsim.scene import Excitation

    if travel is not None and not getattr(family(driver or DEFAULT).load(), "travel_sweep",
                                          False):
        raise ConfigError(f"a travel sweep finds the FireFader's position scale; the "
                          f"{driver or DEFAULT} protocol has none to find (valid with "
                          f"--travel: --driver firefader)", key="--travel")
    if not (math.isfinite(duration) and duration > 0):
        raise ConfigError(f"must be a positive number of seconds, got {duration!r}",
                          key="--duration")
    use_driver = driver not in (None, DEFAULT)
    if use_driver:
        from hapsim.drivers import get_driver
        drv = get_driver(driver, **(driver_options or {}))
        # a board on its own tick runs whole ticks (Driver.board_rate_hz)
        rate_hz = drv.board_rate_hz(rate_hz)
    n = max(int(round(duration * rate_hz)), 1)
    plan = excitation_plan(n, rate_hz, force_limit, envelope, max_delay=max_delay, seed=seed)
    if transport is None:
        transport = "serial" if port else "pty"
    if transport not in ("inprocess", "pty", "serial"):
        raise ConfigError(f"unknown transport {transport!r}; valid: inprocess, pty, serial",
                          key="transport")
    if use_driver and transport == "inprocess":
        # (as hapsim run refuses it: before, the board ran over a pty all the same, with
        # the in-process link's 0.5 s state timeout, and the report said "inprocess")
        raise ConfigError(f"transport 'inprocess' runs hapsim's own mock in this process; "
                          f"the {drv.name} driver talks to its board over a port (its "
                          "emulated board when no port is given); valid with a driver: "
                          "pty, serial", key="transport")
    dev = device or DEFAULT_DEVICE
    stop = stop or StopFlag()
    old = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    embedded = None
    lock = lockstep or transport == "inprocess"
    if use_driver:
        drv.check_rate(rate_hz)             # a rate the device cannot hold is refused
        lock = lock or port is None
    # on the wall clock the device holds its force through a stall of this host: the
    # excitation's stop ahead counts the longest it saw (hapsim.pipeline.excitation)
    plan.clock = None if lock else time.monotonic
    probe = None
    sweep = None
    lost = None             # the DeviceError that ended the excitation after its first row
    try:
        if use_driver:
            from hapsim.drivers.transport import DriverTransport
            if port is None:
                from hapsim.emulated.driver_mock import WALL_CLOCK_MOCKS, EmbeddedDriverMock
                hardware = dict(mock_options if mock_options is not None
                                else drv.mock_hardware())
                if driver in WALL_CLOCK_MOCKS:
                    # the board's clock follows the host's pacing: an identification over
                    # a driver's embedded mock is still lockstep (named here), its probes
                    # and excitation paced by the commands
                    hardware.setdefault("clock", "lockstep" if lock else "wall")
                embedded = EmbeddedDriverMock(driver, dev, Excitation(), rate_hz, seed=noise_seed,
                                              options=hardware)
            if getattr(drv, "probes_direction", False) and \
                    "motor_direction" not in (driver_options or {}):
                # a wrong motor direction makes the excitation run away: find it first
                # (unless it is given: a device file's, or --protocol-option)
                drv, probe = _probe_direction(drv, port or embedded.port, force_limit,
                                              envelope, rate_hz, port is None)
            if travel is not None:
                # the position scale first: the excitation and its fit are in its units
                drv, sweep = _sweep_travel(drv, port or embedded.port, travel, force_limit,
                                           rate_hz, port is None)
            if port is None:
                # paced by the commands: asked again only when its account says it is
                # quiet (a slow mock process is no lost answer, whatever the time)
                acct = embedded.handled
                tr = DriverTransport(drv, embedded.port, delay=int(dev.delay),
                                     reply_deadline=0.02,
                                     board_period=None if acct is None else 1.0 / rate_hz,
                                     handled=None if acct is None else acct.totals)
                embedded.release_slave()
            else:
                tr = DriverTransport(drv, port, delay=1, delay_known=False)
        elif transport == "inprocess":
            from hapsim.emulated.links import InProcessTransport
            mock = MockDevice(dev, Excitation(), native_rate_hz=rate_hz, lockstep=True,
                              seed=noise_seed)
            tr = InProcessTransport(mock)
        elif transport == "pty":
            from hapsim.emulated.links import EmbeddedMock
            from hapsim.emulated.mock import require_whole_delay
            from hapsim.host.transport import SerialTransport
            if not lock:
                require_whole_delay(dev.delay, command="identify")
            embedded = EmbeddedMock(dev, Excitation(), rate_hz, lockstep=lock, seed=noise_seed)
            tr = SerialTransport(embedded.port, baud)
            embedded.release_slave()
        else:
            from hapsim.host.transport import SerialTransport
            tr = SerialTransport(port, baud)
        d_expect = int(dev.delay) if port is None else 1     # whole ticks (force_seq)
        cfg = LoopConfig(rate_hz=rate_hz, n_samples=n, delay=d_expect, force_limit=force_limit,
                         lockstep=lock, host_clocked=use_driver,
                         state_timeout=(0.5 if transport == "inprocess" else 10.0) if lock
                         else 1.0,
                         hello_timeout=30.0 if transport == "pty" else 5.0,
                         position_bound=envelope, reconnect=False,
                         # every STATE answered and logged: a late answer is a known
                         # input (its force_seq), a skipped STATE a hole in the record
                         backlog="all")
        tel = Telemetry(n)
        from hapsim.host.realtime import RealtimePriority
        loop = HostLoop(ExcitationEngine(plan), tr, cfg, tel, stop)
        evt = threading.Event()
        th = None
        if progress:
            th = _progress_thread(tel, n, evt, "hapsim identify: exciting")
        try:
            # the loop's thread at SCHED_FIFO where permitted, as hapsim run's: preempted
            # for a few ms mid-push (a suite beside a CPU-bound process), the device held
            # its force and passed the envelope the excitation had planned within
            with RealtimePriority(rt_priority if transport in ("pty", "serial") and not lock
                                  else 0) as rt:
                try:
                    res = loop.run()
                except DeviceError as exc:
                    if not tel.n:
                        raise                   # nothing recorded: the error alone
                    # the record up to the loss is kept, as hapsim run's report is
                    # (hapsim.pipeline.runner); the caller fits it and says the loss
                    lost = exc
                    res = loop.finish()
                    res.stop_reason = f"device lost: {str(exc).splitlines()[0]}"
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
    fs = 0.0
    account = None
    if use_driver:          # what the device was sent: the protocol's quantised force
        force = drv.applied_forces(force)
        # a driver's protocol names no applied force: its own timing may (issue 20)
        hook = getattr(drv, "account", None)
        account = hook(cols, force) if hook is not None else None
        # what the board's motor got of each command (Driver.output_stage: the Hapkit
        # sketch's 256 levels, the M3's 8-bit duty), fitted when no account names the
        # applied force (over a port the delay is not known, and the account needs it):
        # before, the commands' values were fitted, and the sketch's truncated levels,
        # about 5 % below them on the excitation's forces, read as a mass 3-7 % too
        # heavy with its interval beside the truth (10 of 14 runs of configs/
        # hapkit_serial.yaml's emulated board on the wall clock). A force on a level's
        # edge (its half-width > 0, within a few units in the last place) is taken at
        # the stage's middle of the two levels
        stage = drv.output_stage(np.asarray(cols["force"], float))
        if stage is not None:
            force = np.asarray(stage[0], float)
        late = cols["late"].astype(bool) if account is None else account.late
    else:                   # a framed device's actuator grid, as its HELLO reports it
        from hapsim.applied import account_from_force_seq
        hello = getattr(res, "hello", None)
        fs = float(getattr(hello, "force_scale", 0.0) or 0.0)
        if not (math.isfinite(fs) and fs > 0):
            fs = 0.0
        hl = float(getattr(hello, "force_limit", math.inf) or math.inf)
        # the force the device applied at every tick, from its STATEs' force_seq: the
        # delay is the one the device shows, late ticks are known inputs
        account = account_from_force_seq(cols["seq"], force, cols["force_seq"],
                                         cols["status"], zero_delay=lock and d_expect == 0,
                                         force_limit=min(force_limit, hl), force_scale=fs)
        force = np.round(force / fs) * fs if fs else force
        late = account.late
    return {"position": cols["position"].copy(), "force": force,
            "late": late, "time": cols["time"].copy(),
            "seq": cols["seq"].copy(), "account": account,
            "period": 1.0 / rate_hz,
            "loop": {"samples": int(res.samples), "requested": n,
                     "stop_reason": res.stop_reason, "safety_stop": bool(res.safety_stop),
                     "late": int(np.count_nonzero(late)), "clamped": int(res.clamped),
                     "host_stall_s": float(getattr(loop.engine, "host_stall", 0.0)),
                     "device_delay": None if account is None else int(account.delay),
                     "transport": transport, "lockstep": bool(lock), "scheduling": rt.note,
                     "port": tr.info.get("port"), "faults": list(res.faults),
                     "f_max": float(res.f_max), "v_max": float(res.v_max),
                     "centring": {"K": plan.kc, "B": plan.bc}, "force_scale": fs,
                     "driver": tr.report() if use_driver else None,
                     "direction_probe": None if probe is None else probe.to_dict(),
                     "travel_sweep": None if sweep is None else sweep.to_dict(),
                     "error": error_record(lost)},
            "protocol_options": drv.options() if use_driver else None, "lost": lost}


def _sweep_travel(drv, port: str, travel: float, force_limit: float, rate_hz: float,
                  mock: bool):
    """The FireFader driver with the position scale a sweep between its end stops found
    (:func:`hapsim.drivers.firefader_travel.sweep_port`), and what was found."""
    from hapsim.drivers import get_driver
    from hapsim.drivers.firefader_travel import sweep_port
    # a mock advances one period per packet, however slowly it runs: wait for it, unpaced
    found = sweep_port(drv, port, travel=travel, force=force_limit, rate_hz=rate_hz,
                       timeout=0.5 if mock else 0.05, pace=not mock)
    return get_driver(drv.name, **{**drv.options(),
                                   "metres_per_count": found.metres_per_count}), found


def _probe_direction(drv, port: str, force_limit: float, envelope: float, rate_hz: float,
                     mock: bool):
    """The driver with the motor direction found by a torque pulse of each sign
    (:func:`hapsim.drivers.haply_probe.probe_port`), and what was found."""
    from hapsim.drivers import get_driver
    from hapsim.drivers.haply_probe import probe_port
    # a mock advances one period per write, however slowly it runs: wait for it, unpaced
    found = probe_port(drv, port, force_limit=force_limit, envelope=envelope,
                       rate_hz=rate_hz, timeout=0.5 if mock else 0.05, pace=not mock)
    return get_driver(drv.name, **{**drv.options(),
                                   "motor_direction": found.motor_direction}), found

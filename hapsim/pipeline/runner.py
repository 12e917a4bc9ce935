"""``run_scene``: calibrate, check, close the THS on a device, identify it, report.

A pipeline of named steps, each returning a small result object (docs/design.md, 'The THS'
and 'The mock device'):
:meth:`RunOptions.check` -> :func:`prepare_run` (prepare scene + predict:
:class:`PreparedRun`) -> :func:`connect` (:class:`Connection`) -> :func:`run_loop`
(:class:`LoopRun`) -> :func:`identify_run` (:mod:`hapsim.pipeline.measure`) ->
:func:`build_report` (:mod:`hapsim.pipeline.report`); the steps' results are the records of
:mod:`hapsim.pipeline.run_types`.

1. Links given as a felt ``target: {k, b}`` are calibrated with
   :func:`hapsim.analysis.calibrate` on ``LoopModel.from_device(scene.device, rate)``; a
   target that is not renderable is refused (:class:`UnstableConfigError`, with the reason).
2. The closed loop is predicted (``check_scene`` when the analysis provides it, otherwise
   :func:`hapsim.analysis.render` for the one port-ground spring-damper of a wall scene); an
   unstable loop is refused with its spectral radius and the stiffness limit
   (:func:`hapsim.analysis.stability_limit`) unless ``allow_unstable``.
3. The engine is built and warmed up (numba kernel loaded before the real-time loop), the
   transport opened (in-process mock, embedded mock on a pty, or a given port), and the host
   loop run (:class:`~hapsim.host.loop.HostLoop`).
4. The logged positions after the excitation has ended are identified with
   :func:`hapsim.analysis.identify.measure_felt`: the full-order matrix pencil when the
   record is exact (noise-free, reproduced to round-off), otherwise a least-squares fit of
   the felt pair, the slow modes and the offset, robust to a quantised or noisy sensor
   (step from ``device.position_resolution`` or HELLO's ``position_scale``), with standard
   errors; the report states the interval and whether it holds the prediction, or why the
   record supports no measurement.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import threading
import time

from hapsim.analysis.measurement import identify
from hapsim.analysis.prediction import predict, prepare_scene, refusal
from hapsim.analysis.late_growth import late_growth
from hapsim.pipeline.render_latency import (late_force, late_reading_refusal,
                                            latency_middle, latency_refusal,
                                            missing_reply_warning, timed_prediction)
from hapsim.blas import limit_blas_threads
from hapsim.host.loop import HostLoop, LoopConfig, StopFlag
from hapsim.braking import brake_damping, brake_rest
from hapsim.pipeline.measure import (LATE_SHARE_MAX, identify_run, informative_s,  # noqa: F401
                                     timing_verdict)
from hapsim.emulated.mock import MockDevice, require_whole_delay
from hapsim.pipeline.options import RunOptions
from hapsim.host.realtime import RealtimePriority
from hapsim.pipeline.report import build_report, format_report
from hapsim.pipeline.run_types import Connection, LoopRun, PreparedRun
from hapsim.pipeline.startup import compile_notice, compiled_loop_possible, preload_numba_blas
from hapsim.host.telemetry import ChunkWriter, Telemetry, load, save_columns
from hapsim.host.transport import open_transport
from hapsim.device_model import hand_force_samples
from hapsim.errors import ConfigError, DeviceError, ProtocolError, error_record
from hapsim.scene import Scene

__all__ = ["prepare_scene", "predict", "identify", "run_scene", "format_report",
           "RunOptions", "PreparedRun", "Connection", "LoopRun", "prepare_run", "connect",
           "run_loop", "identify_run", "build_report",
           "DEFAULT_DURATION"]

#: Default run length [s] (at least; longer when the predicted oscillation is slow).
DEFAULT_DURATION = 1.0
#: Telemetry ring [s]: rows after the identification window go round it (drained to the
#: journal by the writer thread); a run no longer than window + ring is kept whole.
RING_SECONDS = 4.0


def prepare_run(scene: Scene, opts: RunOptions) -> PreparedRun:
    """Steps 1-2: calibrate the targets, predict the loop, refuse an unstable one, size the run.

    Parameters
    ----------
    scene : Scene
        Validated scene with a port and a device.
    opts : RunOptions
        Checked options (:meth:`RunOptions.check`).

    Returns
    -------
    PreparedRun

    Raises
    ------
    ConfigError
        No port/device, or d = 0 outside lockstep; a driver of another axis kind than
        the scene's device.protocol (:func:`hapsim.drivers.protocol_of`).
    UnstableConfigError
        A target not renderable, or an unstable loop without ``allow_unstable``.
    """
    rate_hz, drv = opts.rate_hz, None
    if opts.driver is not None:
        from hapsim.drivers import get_driver, protocol_of
        protocol_of(scene, opts.driver)     # (refuses a driver of the other axis kind)
        # the board's own rate: a board on its own tick runs whole ticks (the Hapkit
        # sketch's 5 x 0.992 ms for 201.613 Hz), and the loop is modelled at that period
        drv = get_driver(opts.driver, **(opts.driver_options or {}))
        asked = scene.rate_hz if rate_hz is None else rate_hz
        board = drv.board_rate_hz(asked)
        rate_hz = rate_hz if board == asked else board
    # a board that renders after its read (its driver's render latency, as configured):
    # the loop's delay is the scene's and that; a lockstep board has no time of its own.
    # The targets are calibrated for that loop (at the latency's middle, where the
    # prediction is stated), the one the board runs
    drv_lat = None if opts.lockstep else drv
    scene, targets = prepare_scene(scene, rate_hz,
                                   latency_s=latency_middle(scene, drv_lat))
    dev = scene.device
    if dev.delay == 0 and not opts.lockstep:
        raise ConfigError("device delay d = 0 (force applied at once) can only be closed in "
                          "lockstep (--lockstep); a real-time device needs d >= 1",
                          file=scene.path, key="device.delay")
    if not opts.lockstep and opts.driver is None:
        # the framed mock's delay line is whole periods; a driver's board gives the
        # fraction by its own timing
        require_whole_delay(dev.delay, file=scene.path)
    model, pred = timed_prediction(scene, drv_lat)
    if pred["stable"] is False and not opts.allow_unstable:
        raise refusal(model, pred)
    if pred.get("unstable_latency_s") is not None and not opts.allow_unstable:
        raise latency_refusal(scene, pred)
    if pred.get("late_reading_unstable") is not None and not opts.allow_unstable:
        raise late_reading_refusal(scene, pred)
    if not opts.lockstep:       # a real-time run: does the loop hold a FORCE a period late?
        lat = pred.get("render_latency_s")
        warning = late_force(scene, pred, lat[1] if lat else 0.0)
        if warning:
            pred["late_force_warning"] = warning
        # and replies that go missing now and then, stepped with the host's estimates?
        warning = missing_reply_warning(model, drv_lat, pred)
        if warning:
            pred["missing_reply_warning"] = warning
    T = scene.period
    base_dir = os.path.dirname(os.path.abspath(scene.path)) if scene.path != "<string>" else None
    exc_end = hand_force_samples(scene.excitation, T, base_dir).size * T
    # identification window: the free response at the start (what the default run is)
    window = DEFAULT_DURATION
    if pred.get("f0_hz"):
        window = max(window, exc_end + min(10.0 / pred["f0_hz"], informative_s(
            scene, pred, drv_lat)))
    duration = window if opts.duration is None else opts.duration
    _check_size(scene, duration, window, opts.duration is not None, opts.rate_hz is not None)
    n_samples = max(int(round(duration * scene.rate_hz)), 1) if duration > 0 else 0
    n_window = max(int(round(window * scene.rate_hz)), 1)
    n_ring = max(int(round(RING_SECONDS * scene.rate_hz)), 1)
    return PreparedRun(scene, targets, pred, exc_end, window, n_samples, n_window, n_ring,
                       base_dir, None if model is scene else model)


def _check_size(scene: Scene, duration: float, window: float, asked: bool,
                rate_asked: bool = False) -> None:
    """Refuse a run whose sample count or telemetry cannot fit, before anything starts.

    The telemetry holds the whole run when it fits in the identification window plus the
    ring, else the window plus a ring of :data:`RING_SECONDS`: 42 bytes a row (time,
    position, force, turnaround [float64], seq [int64], late, flags [int8]).

    Raises
    ------
    ConfigError
        ``--duration`` (when given), ``--rate`` (when given) or ``rate_hz`` (file and key),
        with the figures.
    """
    rate = scene.rate_hz
    key = "--duration" if asked else "--rate" if rate_asked else "rate_hz"
    where = {} if key != "rate_hz" else {"file": scene.path if scene.path != "<string>"
                                          else None}
    n = duration * rate
    if not math.isfinite(n) or n > 2.0 ** 62:
        raise ConfigError(f"{duration:.6g} s at {rate:.6g} Hz is {n:.3g} samples; a run "
                          "counts at most 2^62 (use --duration 0 for an open-ended run)",
                          key=key, **where)
    window_rows, ring_rows = window * rate, RING_SECONDS * rate
    rows = n if 0 < n <= window_rows + ring_rows else min(window_rows, n or window_rows) \
        + ring_rows
    try:
        from hapsim.outputs import check_fits
        check_fits(42.0 * rows, f"{rows:.3g} telemetry rows ({rate:.6g} Hz)", key)
    except ConfigError as exc:
        raise ConfigError(exc.reason, key=key, **where) from None


def _loop_config(prep: PreparedRun, opts: RunOptions) -> LoopConfig:
    """The :class:`LoopConfig` of a prepared run (safety limits from the scene)."""
    scene, dev = prep.scene, prep.scene.device
    lockstep = opts.lockstep
    x0 = abs(scene.excitation.x0)
    sf = scene.safety
    pos_bound = sf.position_limit if sf.position_limit is not None else max(0.1, 20.0 * x0)
    # the host's tick bookkeeping (force_seq) counts whole periods: a delay m + f is m
    # ticks there, the fraction is in the physics (the device's) and in the prediction
    return LoopConfig(rate_hz=scene.rate_hz, n_samples=prep.n_samples, delay=int(dev.delay),
                      force_limit=dev.force_limit, lockstep=lockstep,
                      host_clocked=opts.host_clocked,
                      compact={"auto": "auto", "full": "off", "compact": "on"}[opts.frames],
                      state_timeout=(0.5 if opts.transport == "inprocess" else 10.0)
                      if lockstep else 3.0 if opts.driver is not None else 1.0,
                      # (a driver's board may reset when its port opens: the FireFader's
                      # Nano spends ~1 s in its bootloader before its first record)
                      # the embedded mock is a fresh Python process (imports take seconds
                      # on a loaded machine); hardware answers at once
                      hello_timeout=30.0 if opts.transport == "pty" else 5.0,
                      position_bound=pos_bound, velocity_limit=sf.velocity_limit,
                      energy_limit=sf.energy_limit,
                      passivity_controller=sf.passivity_controller,
                      max_damping=sf.max_damping, reconnect=bool(opts.reconnect),
                      lost_timeout=opts.lost_timeout,
                      reconnect_attempts=int(opts.reconnect_attempts),
                      reconnect_time=float(opts.reconnect_time),
                      # after a safety stop the host brakes the device before its zero
                      # force (hapsim.host.recovery, module notes), until the coast left
                      # on friction alone, v m / b, is 1 % of the workspace (without
                      # friction: 1 % of it a second)
                      brake_damping=(brake_damping(dev.mass, scene.rate_hz) if sf.brake
                                     else 0.0),
                      brake_rest=brake_rest(pos_bound, dev.mass, dev.friction),
                      # the lateness guard: a framed device on its own clock holds each
                      # FORCE until the next (a driver's board keeps its own rules)
                      late_growth=(late_growth(scene, LoopConfig.watchdog_us * 1e-6)
                                   if not lockstep and opts.driver is None else None))


class _CompileThread(threading.Thread):
    """Load the scene's kernels (:func:`hapsim.engine.warm_up`) and, for the compiled loop, the loop
    itself (:func:`hapsim.host.fastloop.warm_up`) from numba's cache (or compile them)
    beside the device's start-up; :meth:`finish` waits for it and re-raises its error."""

    def __init__(self, scene: Scene, compiled: bool) -> None:
        super().__init__(name="hapsim-compile", daemon=True)
        self.scene = scene
        self.compiled = compiled
        self.error: BaseException | None = None
        self.start()

    def run(self) -> None:
        try:
            notice = compile_notice()   # set when the command announced a cold cache
            preload_numba_blas()        # before numba's first cache load (module notes)
            from hapsim import engine
            engine.warm_up(self.scene)
            if notice is not None:
                notice("the engine's kernels")
            if self.compiled:
                from hapsim.host import fastloop
                fastloop.warm_up(engine.Engine(self.scene))
                if notice is not None:
                    notice("the compiled host loop")
        except BaseException as exc:  # re-raised by finish() in the caller's thread
            self.error = exc

    def finish(self) -> None:
        self.join()
        if self.error is not None:
            raise self.error


def connect(prep: PreparedRun, opts: RunOptions) -> Connection:
    """Step 3: install the signal handlers, warm the kernels, open the device.

    From here on Ctrl-C / SIGTERM request a clean stop instead of raising: during the numba
    warm-up or while the embedded mock starts, the loop then ends at once (no FORCE but the
    final zero one, then STOP), with the report and the telemetry.

    Parameters
    ----------
    prep : PreparedRun
        :func:`prepare_run`'s result.
    opts : RunOptions
        Checked options.

    Returns
    -------
    Connection
        Everything :func:`run_loop` needs; on an error everything is undone first.

    Raises
    ------
    DeviceError
        The port cannot be opened.
    """
    scene, dev = prep.scene, prep.scene.device
    stop = opts.stop or StopFlag()
    old = {}
    if opts.handle_signals and threading.current_thread() is threading.main_thread():
        def _on_signal(signum, frame):
            stop.request(signum)
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, _on_signal)
    embedded = None
    rt = None
    mock = None
    transport, lockstep = opts.transport, opts.lockstep
    warm = None
    try:
        limit_blas_threads(1)
        corr = getattr(dev, "correction", None)
        sensor = corr is not None and corr.get("kind") == "velocity_sensor"
        # the kernels (and the compiled loop) load while the device (the mock's child)
        # starts and says HELLO: the loop waits for them just before it arms the device
        # (HostLoop.before_arm)
        warm = _CompileThread(scene, opts.loop == "compiled" and transport in ("pty", "serial")
                              and compiled_loop_possible(scene, osc=opts.osc, sound=opts.sound,
                                                         host_clocked=opts.host_clocked))
        # a lockstep device waits for each FORCE: nothing to keep on time, and a host and
        # mock ping-ponging as fast as they can under SCHED_FIFO would own both cores of a
        # small machine at the priority of every real-time loop on it
        # (and a driver's lockstep mock: the loop takes each tick once it has answered,
        # hapsim.host.host_clock)
        paced = lockstep and opts.port is None and (
            not opts.host_clocked or (opts.driver is not None and (
                opts.mock_options or {}).get("clock", "lockstep") == "lockstep"))
        rt = RealtimePriority(opts.rt_priority if transport in ("pty", "serial") and not paced
                              else 0)
        if paced and opts.rt_priority:
            rt.note = "normal (lockstep: paced by the device's answers, not by the clock)"
        if opts.driver is not None:
            rt.__enter__()  # the driver's embedded mock inherits the policy
        if transport == "pty" and opts.driver is None:
            # first: the child's interpreter and imports run beside everything below; it
            # starts under normal scheduling and takes SCHED_FIFO itself once its imports
            # are done: a start-up (~0.5 s of CPU) under SCHED_FIFO starved every other
            # real-time loop of the machine (a concurrent run: 40-235 ms stalls)
            from hapsim.emulated.links import EmbeddedMock
            embedded = opts.embedded or EmbeddedMock(
                dev, scene.excitation, scene.rate_hz, lockstep=lockstep, seed=opts.seed,
                base_dir=prep.base_dir, faults=opts.faults or None,
                fault_seed=opts.fault_seed, rt_priority=rt.priority)
        from hapsim.engine import Engine
        engine = Engine(scene)
        measured = None
        if corr is not None:
            # a device correction: the engine is fed the corrected port signals (any
            # scene); a velocity sensor reads the device's VELOCITY frames, which the loop
            # asks for (PROTOCOL.md §4: refused when the device offers none)
            from hapsim.host.correction import corrected_engine
            from hapsim.host.loop import MeasuredVelocity
            if sensor:
                if opts.driver is not None:
                    raise ConfigError(f"velocity_sensor: the {opts.driver} driver's wire "
                                      f"carries no velocity; use the framed protocol",
                                      key="--driver")
                measured = MeasuredVelocity()
            engine = corrected_engine(scene, velocity=measured)
        n_samples, n_window, n_ring = prep.n_samples, prep.n_window, prep.n_ring
        if n_samples and n_samples <= n_window + n_ring:
            tel = Telemetry(n_samples)                 # the whole run fits: kept whole
        else:                                          # long or open-ended: head + ring
            tel = Telemetry(min(n_window, n_samples or n_window), n_ring)
        cfg = _loop_config(prep, opts)
        if opts.driver is not None:
            from hapsim.drivers import family, get_driver
            # the device's parameters: given, else the scene's device.protocol_options
            # when the scene's device speaks this protocol
            dopt = dict(opts.driver_options if opts.driver_options is not None
                        else dev.protocol_options or {} if dev.protocol == opts.driver
                        else {})
            if opts.port is None:
                # what the embedded board's set-up takes from the scene (the Haply's
                # encoder offset: the joint armed at the excitation's x0)
                dopt = family(opts.driver).load().embedded_options(dopt,
                                                                   scene.excitation.x0)
            drv = get_driver(opts.driver, **dopt)
            drv.check_rate(scene.rate_hz)       # a rate the device cannot hold is refused
            if opts.port is None:
                from hapsim.emulated.driver_mock import WALL_CLOCK_MOCKS, EmbeddedDriverMock
                hardware = dict(opts.mock_options if opts.mock_options is not None
                                else drv.mock_hardware())
                # the board keeps its own time unless the run asks for lockstep
                wall = opts.driver in WALL_CLOCK_MOCKS and not opts.lockstep
                if opts.driver in WALL_CLOCK_MOCKS:
                    hardware.setdefault("clock", "wall" if wall else "lockstep")
                embedded = EmbeddedDriverMock(opts.driver, dev, scene.excitation,
                                              scene.rate_hz, seed=opts.seed,
                                              options=hardware, faults=opts.driver_faults)
                # a mock paced by the commands is asked again only when its account
                # says it is quiet (a slow mock process is no lost answer, whatever the
                # time: the same record on a loaded host); a board on its own clock
                # answers as hardware does. The device's mass (a rotary axis': its
                # inertia) bounds what a reading may have moved since the last (a driver
                # that checks it: the Haply M3)
                acct = embedded.handled
                tr = open_transport(embedded.port, drv, delay=int(dev.delay),
                                    reply_deadline=0.0 if acct is None else 0.02,
                                    inertia=dev.mass,
                                    board_period=None if acct is None else scene.period,
                                    handled=None if acct is None else acct.totals)
                embedded.release_slave()
            else:
                tr = open_transport(opts.port, drv, delay=int(dev.delay), inertia=dev.mass)
        elif transport == "inprocess":
            from hapsim.emulated.links import InProcessTransport
            mock = MockDevice(dev, scene.excitation, native_rate_hz=scene.rate_hz, lockstep=True,
                              seed=opts.seed, base_dir=prep.base_dir)
            tr = InProcessTransport(mock)
        elif transport == "sim":
            from hapsim.emulated.links import SimTransport
            mock = MockDevice(dev, scene.excitation, native_rate_hz=scene.rate_hz, lockstep=False,
                              seed=opts.seed, base_dir=prep.base_dir)
            tr = SimTransport(mock, opts.plan)
        else:                   # the embedded mock's pty, or a port: hapsim's own protocol
            tr = open_transport(opts.port if embedded is None else embedded.port, baud=opts.baud)
            if embedded is not None:
                embedded.release_slave()
        if not rt.active:
            rt.__enter__()  # the loop's thread only, once the start-up work is done
    except BaseException:
        if warm is not None:
            warm.join()                 # numba's loading is not left half done
        if rt is not None:
            rt.__exit__(None, None, None)
        if embedded is not None:
            embedded.close()
        _restore_signals(old)
        raise
    return Connection(engine, tel, cfg, stop, tr, rt, embedded, mock, old, measured, warm)


def run_loop(prep: PreparedRun, conn: Connection, opts: RunOptions) -> LoopRun:
    """Step 4: run the host loop with the journal writer, then close everything.

    Parameters
    ----------
    prep : PreparedRun
        :func:`prepare_run`'s result.
    conn : Connection
        :func:`connect`'s result (closed here, whatever happens).
    opts : RunOptions
        Checked options.

    Returns
    -------
    LoopRun

    Notes
    -----
    A DeviceError or ProtocolError from the loop (device lost beyond recovery) is not
    raised here: the result holds the run up to the loss and the error
    (:attr:`LoopRun.error`), so the report is still made.
    """
    tel, tr, telemetry = conn.tel, conn.tr, opts.telemetry
    writer = None
    writer_info = None
    journal = None
    mock_report = None
    error = None
    ctl = osc_server = None
    ring = out = None
    try:
        if opts.sound is not None:
            ring, out = _start_sound(prep, conn, opts)
        corr = getattr(prep.scene.device, "correction", None)
        # the compiled loop steps the kernel itself: live OSC changes and the sounding
        # engine run per sample in Python, so they keep the Python loop; so does a device
        # correction (its law runs in the engine's port_step, hapsim.host.correction).
        # The report says why (python_reason), never silently.
        why = ("--sound: the sounding engine runs per sample in Python" if opts.sound
               else "--osc: live changes run per sample in Python" if opts.osc is not None
               else "--view: the view's live changes run per sample in Python"
               if opts.view is not None
               else f"device.correction ({corr.get('kind')}): its law runs in the engine's "
               "port_step in Python" if corr is not None
               # the compiled loop steps the single-rate kernel: one audio sub-step per
               # device sample would be another loop (the contact replay found it)
               else "audio: the multi-rate kernel (sub-steps per device sample) runs in the "
               "engine's port_step in Python" if prep.scene.audio is not None else None)
        if opts.loop == "compiled" and why is None:
            from hapsim.host.fastloop import CompiledHostLoop, compiled_available
            loop = CompiledHostLoop(conn.engine, tr, conn.cfg, tel, conn.stop)
            if not loop.compiled:
                why = ("host-clocked" if conn.cfg.host_clocked else
                       "the transport has no file descriptor (in-process, virtual clock or "
                       "a driver)" if not compiled_available(tr) else
                       "a lockstep journal drained by the loop itself")
        else:
            loop = HostLoop(conn.engine, tr, conn.cfg, tel, conn.stop, measured=conn.measured)
        loop.python_reason = why if opts.loop == "compiled" else None

        def before_arm() -> None:
            _finish_warm(conn)
            if opts.on_start is not None:
                opts.on_start(tr.info.get("port"), prep.n_samples)

        loop.before_arm = before_arm
        if opts.osc is not None or opts.view is not None:
            ctl, osc_server = _start_osc(prep, conn, loop, opts)
        if opts.view is not None:
            conn.view = _start_view(prep, conn, loop, ctl, opts)
        if telemetry:
            journal = telemetry if telemetry.lower().endswith(".hst") else telemetry + ".hst"
            writer = ChunkWriter(tel, journal, opts.telemetry_interval,
                                 events=loop.result.events)
            try:                        # (a full disk at the start: a traceback before)
                writer.note(_run_event(prep, opts))
            except OSError as exc:
                raise ConfigError(f"cannot write {journal}: {exc.strerror}", key="--telemetry")
            writer.start()
            if opts.transport == "sim" or (opts.lockstep and not opts.host_clocked):
                tel.drain = _sync_drain(writer, tel)    # no deadline: may wait for the disk
        try:
            res = loop.run()
        except (DeviceError, ProtocolError) as exc:
            # the run up to the loss is reported (and its telemetry exported) as any other
            error = exc
            res = loop.finish()
            res.stop_reason = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
        ended_at = time.monotonic()
    finally:
        if out is not None:
            out.finish()                # the loop's last frames are written: the silence
            #                             after them is the run's end, not an underrun
        if conn.warm is not None:       # the loop ended before it armed the device
            conn.warm.join()
        if osc_server is not None:
            osc_server.shutdown()
            osc_server.server_close()
        if ctl is not None:
            ctl.close()                 # its analysis process
        if out is not None:
            out.close()
        conn.rt.__exit__(None, None, None)
        if writer is not None:
            try:
                writer.close()
            except OSError as exc:      # a full disk: said in the report, which is kept
                writer.error = writer.error or exc
            writer_info = {"lost_rows": writer.lost_rows, "chunks": writer.chunks,
                           "events": writer.events_written,
                           "error": str(writer.error) if writer.error else None}
        tr.close()
        if conn.embedded is not None:
            # a device lost for good never sees the host leave (its port is gone, or it
            # no longer answers): it is stopped at once (SIGTERM: zero force, its
            # report) instead of being awaited for the 3 s a device that ends by itself
            # gets
            mock_report = conn.embedded.report(timeout=0.0 if error is not None else 3.0)
            conn.embedded.close()
    if opts.transport in ("inprocess", "sim"):
        mock_report = conn.mock.stats.to_dict()
        mock_report["totals"] = conn.mock.totals()
        if opts.transport == "sim":
            mock_report["faults_injected"] = opts.plan.to_dict()["injected"]
            mock_report["fault_events"] = tr.device.events
    sound = None if ring is None else {"backend": type(out).__name__,
                                       "callback": out.callback, "xruns": out.xruns,
                                       "xrun_at_s": list(out.xrun_at), **ring.stats()}
    return LoopRun(res, mock_report, writer_info, journal, ctl, sound, error, loop, ended_at)


def _start_sound(prep: PreparedRun, conn: Connection, opts: RunOptions):
    """``run --sound``: the engine also hands each device sample's audio frames to a
    :class:`hapsim.audio.live.FrameRing` that a JACK (or PortAudio) callback plays; the
    multi-rate model stays in the loop, so the force is exactly the analysed one."""
    from hapsim.audio.live import FrameRing, open_output, sounding_engine

    scene = prep.scene
    if scene.audio is None:
        raise ConfigError("the scene has no audio section to play; see "
                          "configs/audio_string.yaml", file=scene.path, key="--sound")
    ring = FrameRing(scene.audio.rate_hz, conn.engine.channels)
    conn.engine = sounding_engine(ring)(scene)
    out = open_output(ring, opts.sound, server=opts.jack_server)
    return ring, out


def _start_osc(prep: PreparedRun, conn: Connection, loop: HostLoop, opts: RunOptions):
    """``run --osc PORT``: a :class:`hapsim.audio.control.Controller` on the run's engine,
    polled by the loop between samples, and its OSC server (address printed on stderr)."""
    import sys

    from hapsim.audio.control import Controller

    from hapsim.audio.osc import serve_osc

    # a board that renders after its read: the changes judged over its latency's bounds
    lat = prep.pred.get("render_latency_s")
    drv = getattr(conn.tr, "driver", None) if opts.driver and not opts.lockstep else None
    late = getattr(drv, "late_reading_periods", 0) or 0
    ctl = Controller(prep.scene, conn.engine, ramp_s=opts.osc_ramp,
                     latency=(0.5 * (lat[0] + lat[1]), lat[1]) if lat else (0.0, 0.0),
                     late_reading_s=late * prep.scene.period)
    ctl.events = loop.result.events             # journaled with the telemetry (.hst)
    ctl.sample_of = lambda: conn.tel.n
    loop.poll = lambda: ctl.poll(loop.engine)
    if opts.osc is None:                        # --view alone: its changes, no OSC server
        return ctl, None
    server, _ = serve_osc(ctl, opts.osc, status=lambda: {"xruns": 0, "underruns": 0})
    host, port = server.server_address[:2]
    print(f"hapsim run: OSC on {host}:{port}", file=sys.stderr, flush=True)
    return ctl, server


def _start_view(prep: PreparedRun, conn: Connection, loop: HostLoop, ctl, opts: RunOptions):
    """``run --view PORT``: the live view (:mod:`hapsim.view`) reading the run's telemetry
    arrays, the loop's engine and events, and the controller's journal; its stop button
    sets the run's stop flag (as SIGINT). :func:`run_scene` hands it the report."""
    from hapsim.view import RunSource, start_view
    # the felt pair measured live as the record grows (as the report measures it): the
    # framed protocol's runs (a driver's wire errors are the driver's, in this process)
    live = opts.driver is None
    from hapsim.pipeline.measure import MEASURE_KEYS, measure_record
    src = RunSource(prep.scene, conn.tel, lambda: loop.engine, ctl, loop.result.events,
                    prep=prep if live else None, hello_of=lambda: loop.result.hello,
                    measure=measure_record, measure_keys=MEASURE_KEYS)
    src.protocol = opts.protocol          # (the axis's units: a --driver's)
    return start_view(src, ctl, conn.stop, opts.view, "run")


def _run_event(prep: PreparedRun, opts: RunOptions) -> dict:
    """The run's description its telemetry keeps (its first event, ``"run"``): the units
    of its columns (:func:`hapsim.drivers.run_units`: a rotary joint's radians and newton
    metres), the device's delay [periods] and the rate [Hz], which ``hapsim telemetry``
    reads back; before, a Haply joint's file was summarised in metres and newtons."""
    from hapsim.drivers import run_units
    scene = prep.scene
    return {"event": "run", "sample": 0, "units": run_units(scene, opts.protocol),
            "delay": float(scene.device.delay), "rate_hz": float(scene.rate_hz)}


def _telemetry_info(conn: Connection, run: LoopRun, opts: RunOptions,
                    described: dict) -> dict | None:
    """Export the telemetry file and describe it (None without ``--telemetry``); the
    whole run's turnaround is read back from the journal once the ring went round. An
    ``.npz`` keeps the run's events, ``described`` (:func:`_run_event`) first."""
    tel, telemetry, journal = conn.tel, opts.telemetry, run.journal
    if not telemetry:
        return None
    if tel.wrapped:     # the whole run's turnaround, from the journal (off the loop)
        from hapsim.host.loop import percentiles_us
        ta = load(journal)["turnaround_us"]
        run.res.turnaround_us = dict(percentiles_us(ta), samples=int(ta.size))
    wi = dict(run.writer_info or {})
    if journal != telemetry:
        try:
            _export(tel, journal, telemetry, [described, *run.res.events])
        except OSError as exc:          # the journal keeps the rows (a traceback before)
            held = f" it held when it stopped ({wi['error']})" if wi.get("error") else ""
            wi["error"] = f"{telemetry} not written ({exc.strerror}); {journal} has the rows{held}"
    return {"path": telemetry, "samples": tel.n,
            "columns": ["time [s]", "position [m]", "force [N]", "seq",
                        "turnaround [us]", "late", "flags"],
            "in_memory": tel.head + (tel.ring if tel.wrapped else 0)
            if tel.wrapped else tel.n,
            "ring": tel.ring, "lost_rows": wi.get("lost_rows", 0),
            "events_journaled": wi.get("events", 0),
            "writer_error": wi.get("error")}


def _workspace(tel, config) -> tuple[float, float]:
    """The host's largest reading's magnitude over the run and its position bound [m or
    rad] (:func:`timing_verdict`); a ring that went round has rows no longer in memory:
    the bound itself is taken for the reading (the loop held every reading within it)."""
    import numpy as np
    bound = float(config.position_bound)
    if tel.wrapped or not tel.n:
        return (bound if tel.wrapped else 0.0), bound
    xs = np.abs(np.asarray(tel.columns()["position"], float))
    return float(np.nanmax(xs, initial=0.0)), bound


def run_scene(scene: Scene, options: RunOptions | None = None, **changes) -> dict:
    """Close the THS of a scene on a device and measure what is felt.

    Parameters
    ----------
    scene : Scene
        Validated scene with a port and a device.
    options : RunOptions, optional
        The run's options (:class:`RunOptions`: the port, duration, rate, transport,
        telemetry, faults, sound...); default ``RunOptions()``. Not modified: the run
        checks a copy.
    **changes
        Options changed from ``options`` (the fields of :class:`RunOptions`), e.g.
        ``run_scene(scene, transport="inprocess", lockstep=True)``.

    Returns
    -------
    dict
        Keys ``target`` (the first target link, None without one), ``targets`` (every
        target link: ``link``, ``k``, ``b``, ``K``, ``B``, ``renderable``, ``reason``, ``f0_hz``,
        ``damping_ratio``), ``virtual``, ``predicted``, ``measured`` (``rel_err_target``
        only with one target: with several the felt pair is their sum), ``loop``,
        ``telemetry`` (see ``hapsim run --help``) and ``exit_code`` (0, or 1 after a
        safety stop or a device fault).

    Raises
    ------
    ConfigError
        Invalid arguments or scene.
    UnstableConfigError
        Target not renderable, or unstable loop without ``allow_unstable``.
    DeviceError
        Port failure or silent device. Once the loop has started (device lost beyond
        recovery), the exception's ``report`` attribute holds the report of the run up to
        the loss (``exit_code`` 1, ``error``: ``type`` and ``message``, ``loop.stop_reason``
        naming the error).
    ProtocolError
        The device speaks another protocol version or has another number of axes than 1
        (with ``report`` as for DeviceError when the loop had started).
    """
    opts = dataclasses.replace(options if options is not None else RunOptions(), **changes)
    embedded = opts.embedded
    try:
        opts.check()
        if embedded is not None and (opts.transport != "pty"
                                     or opts.driver is not None):
            opts.embedded = None            # not this run's device
            embedded.close()
        prep = prepare_run(scene, opts)
        # before the loop starts: will the record be comparable (a contact that opens
        # within the samples the fit needs)? Said first, then run (hapsim/pipeline/precheck.py)
        from hapsim.pipeline.precheck import predict_comparable
        pre = predict_comparable(prep)
        stated = None
        if pre is not None and not pre["comparable"]:
            stated = ("not measurable, predicted before the run (lockstep simulation of the "
                      "closed loop): " + pre["reason"])
            if opts.on_precheck is not None:
                opts.on_precheck(stated)
    except BaseException:
        if embedded is not None:
            embedded.close()
        raise
    conn = connect(prep, opts)
    try:
        run = run_loop(prep, conn, opts)
        tel_info = _telemetry_info(conn, run, opts, _run_event(prep, opts))
        # the run's own driver (its parameters: given, or the scene's protocol_options)
        drv = getattr(conn.tr, "driver", None) if opts.driver is not None else None
        measured = identify_run(prep, conn.tel, run.res.hello, driver=drv)
        if pre is not None:
            measured["predicted_comparable"] = pre["comparable"]
            if stated is not None:
                measured["stated_before_run"] = stated
        if drv is not None:
            timing_verdict(measured, run.res, conn.tr.stats, wall=not opts.lockstep,
                           workspace=_workspace(conn.tel, _loop_config(prep, opts)))
        rep = build_report(prep, conn, run, opts, measured, tel_info)
        if getattr(conn, "view", None) is not None:
            conn.view.finish(rep)
    finally:
        if getattr(conn, "view", None) is not None:
            conn.view.close()
        # the handlers stay until the report is made: a SIGINT/SIGTERM after the loop
        # ended (the telemetry export, the identification and the report take seconds on
        # a loaded machine) asks for a stop already under way; with the default handler
        # back it killed the process there, report and telemetry export lost (exit -15)
        _restore_signals(conn.old_signals)
    if run.error is not None:          # device lost beyond recovery: the report goes with it
        rep["exit_code"] = 1
        rep["error"] = error_record(run.error)
        run.error.report = rep
        raise run.error
    return rep


def _finish_warm(conn: Connection) -> None:
    """Wait for the numba warm-up (:class:`_CompileThread`) once; re-raise its error."""
    warm, conn.warm = conn.warm, None
    if warm is not None:
        warm.finish()


def _sync_drain(writer: ChunkWriter, tel: Telemetry):
    """``writer.flush`` for a loop that is not real-time to call (an OSError stops it and is
    kept in ``writer.error``, as in the writer thread)."""
    def drain() -> None:
        try:
            writer.flush()
        except OSError as exc:
            writer.error = exc
            tel.drain = None
    return drain


def _export(tel: Telemetry, journal: str, path: str, events: list) -> None:
    """Write the ``.npz`` / ``.csv`` telemetry: from memory while every row is there, else
    from the journal (which has them all); then remove the journal. An ``.npz`` keeps
    ``events`` (before, a run's ``.npz`` had none, its losses and recoveries dropped)."""
    save_columns(load(journal) if tel.wrapped else tel.columns(), path, events,
                 key="--telemetry")
    _remove(journal)


def _restore_signals(old: dict) -> None:
    """Put back the signal handlers ``run_scene`` replaced (``{signum: handler}``)."""
    for s, h in old.items():
        signal.signal(s, h)


def _remove(path: str | None) -> None:
    if path:
        try:
            os.unlink(path)
        except OSError:
            pass

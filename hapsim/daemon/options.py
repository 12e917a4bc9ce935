"""The options of one run (:class:`RunOptions`): built once, from the command line
(:func:`hapsim.commands.run.run_options`) or by a program, checked by
:meth:`RunOptions.check` and taken by :func:`hapsim.daemon.runner.run_scene`."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from hapsim.daemon.loop import StopFlag
from hapsim.errors import ConfigError

__all__ = ["RunOptions"]


@dataclass
class RunOptions:
    """The options of one run: built once (from the command line by
    :func:`hapsim.commands.run.run_options`, or by a program), taken by
    :func:`hapsim.daemon.runner.run_scene`.

    :meth:`check` validates them and resolves ``transport`` (``"serial"``, ``"pty"``,
    ``"inprocess"`` or ``"sim"``), ``reconnect`` (a bool) and ``plan``.

    Attributes
    ----------
    port : str, optional
        Serial port of a device (hardware or ``hapsim mock``); None: a mock.
    baud : int
        Baud rate for ``port``.
    duration : float, optional
        Run length [s] (> 0); default :data:`hapsim.daemon.runner.DEFAULT_DURATION`,
        longer for slow loops (the identification window: excitation + 10 periods). 0:
        open-ended, until SIGINT / SIGTERM (``handle_signals``), ``stop``, a safety stop or
        a device end. Telemetry in memory is the identification window plus a ring of
        :data:`hapsim.daemon.runner.RING_SECONDS` (a run that fits in both is kept whole);
        the rest is only in the journal.
    rate_hz : float, optional
        Rate override [Hz].
    lockstep : bool
        Lockstep mock (one period per FORCE; deterministic).
    host_clocked : bool
        Host's clock instead of the device's (with ``lockstep``: the host paces the
        lockstep device in real time).
    telemetry : str, optional
        Per-sample telemetry file: ``.hst`` (chunked journal, appended every
        ``telemetry_interval`` by a writer thread and kept), or ``.npz`` / ``.csv`` (the
        journal ``PATH.hst`` is written during the run, so a killed daemon leaves its rows
        there, and removed once the export succeeded).
    allow_unstable : bool
        Run a loop the analysis finds unstable (safety stops end it).
    transport : {"serial", "pty", "inprocess", "sim"}, optional
        Default ``"serial"`` with ``port``, else ``"pty"`` (embedded mock in a child process
        on a pseudo-terminal). ``"inprocess"`` (lockstep only) calls the mock directly;
        ``"sim"`` (real-time only) runs the real-time mock in-process on a virtual clock
        (:class:`~hapsim.daemon.transport.SimTransport`: fast, deterministic fault tests).
    seed : int
        Mock sensor-noise seed.
    stop : StopFlag, optional
        External stop flag; a new one otherwise.
    handle_signals : bool
        Install SIGINT/SIGTERM handlers that request a clean stop (main thread only),
        from before the numba warm-up and the start of the embedded mock: a signal during
        start-up ends the run at once, before CONFIG (no FORCE but the final zero one,
        then STOP), with exit code 0. Restored on return.
    rt_priority : int
        ``SCHED_FIFO`` priority of the host loop (and of the embedded mock it starts) over a
        pty or a serial port, where the OS permits it; 0 for normal scheduling. Not for a
        lockstep embedded mock (paced by the answers, not the clock). The mock takes it
        after its start-up, the host once its own start-up is done. Restored after the run;
        the report's ``loop.scheduling`` says what was obtained.
    on_start : callable, optional
        Called as ``on_start(port, n_samples)`` once the signal handlers are installed,
        the device has said HELLO and the numba warm-up is done, just before the device is
        armed (e.g. to tell the user that Ctrl-C now stops cleanly).
    faults : str, optional
        Fault SPEC for the mock (:mod:`hapsim.daemon.faults`); ``pty`` and ``sim`` only.
    fault_seed : int
        Seed of the fault generator.
    reconnect : bool, optional
        Recover a lost device (default: on in real time, off in lockstep).
    lost_timeout : float, optional
        Silence after which the device is lost [s] (default: the watchdog period, 50 ms:
        the device zeroes its force after one watchdog period without a FORCE, and the
        host sends zero force and STOP then; see :class:`~hapsim.daemon.loop.LoopConfig`).
    reconnect_attempts : int
        Most HELLO + CONFIG attempts per loss.
    reconnect_time : float
        Most time spent recovering one loss [s].
    telemetry_interval : float
        Time between two telemetry chunks [s].
    driver : str, optional
        A device protocol of :mod:`hapsim.drivers` other than ``"framed"`` (the default):
        the loop is then host-clocked through a
        :class:`~hapsim.drivers.transport.DriverTransport` on ``port``, or on that
        driver's mock (paced by the host) without a port.
    driver_options : dict, optional
        The driver's device parameters (its constructor's keywords: FireFader
        ``full_scale``, ``metres_per_count``, ``axis``; Haply ``device_id``,
        ``resolution``, ``direction``).
    mock_options : dict, optional
        The driver mock's hardware (:class:`hapsim.drivers.mock.EmbeddedDriverMock`),
        which may differ from what ``driver_options`` believe.
    driver_faults : dict, optional
        Seeded byte loss and corruption on the driver mock's link, both directions
        (:class:`hapsim.drivers.mock.ByteFaults`).
    osc : int, optional
        Serve live changes over OSC on localhost:PORT (0: any free port, printed on
        stderr; :mod:`hapsim.audio.control`: checked, ramped, journaled in the report's
        ``osc``). The measured (k, b) are those of the scene at the start.
    osc_ramp : float
        Ramp time of every OSC change [s].
    sound : {"auto", "jack", "sounddevice"}, optional
        Play the scene's ``audio`` live: the frames the loop computes go through a ring to
        the sound server (report: ``sound`` with xruns and ring underruns).
    jack_server : str, optional
        JACK server name.
    plan : FaultPlan
        Set by :meth:`check`: the parsed ``faults``
        (:class:`~hapsim.daemon.faults.FaultPlan`).
    embedded : EmbeddedMock, optional
        The embedded mock already started for this run
        (:func:`hapsim.daemon.startup.start_embedded_mock`, ``transport`` ``"pty"``);
        closed here whatever happens. Default: started by
        :func:`hapsim.daemon.runner.connect`.
    loop : {"compiled", "python"}
        Host loop: the compiled hot path (:mod:`hapsim.daemon.fastloop`; over a pty or a
        serial port, device-clocked, without ``osc``/``sound``/``device.correction``;
        elsewhere the Python loop, and the report's ``loop.python_reason`` says why) or the
        Python reference loop (:class:`~hapsim.daemon.loop.HostLoop`).

    """

    port: str | None = None
    baud: int = 115200
    duration: float | None = None
    rate_hz: float | None = None
    lockstep: bool = False
    host_clocked: bool = False
    telemetry: str | None = None
    allow_unstable: bool = False
    transport: str | None = None
    seed: int = 0
    stop: StopFlag | None = None
    handle_signals: bool = True
    on_start: object = None
    rt_priority: int = 10
    faults: str | None = None
    fault_seed: int = 0
    reconnect: bool | None = None
    lost_timeout: float | None = None
    reconnect_attempts: int = 8
    reconnect_time: float = 10.0
    telemetry_interval: float = 0.05
    loop: str = "compiled"
    driver: str | None = None
    driver_options: dict | None = None
    mock_options: dict | None = None
    driver_faults: dict | None = None
    osc: int | None = None
    osc_ramp: float = 0.05
    sound: str | None = None
    jack_server: str | None = None
    plan: object = None
    embedded: object = None

    def check(self) -> "RunOptions":
        """Validate and resolve the options in place.

        Returns
        -------
        RunOptions
            ``self``.

        Raises
        ------
        ConfigError
            A bad duration, transport, fault spec, port or telemetry format, naming the
            option and the valid choices.
        """
        d = self.duration
        if d is not None and not (math.isfinite(d) and d >= 0):
            raise ConfigError(f"must be a number of seconds > 0, or 0 for an open-ended run, "
                              f"got {d!r}", key="--duration")
        if d == 0 and self.stop is None and not self.handle_signals:
            raise ConfigError("an open-ended run (duration 0) needs a way to stop it: "
                              "handle_signals or a stop flag", key="--duration")
        if self.transport is None:
            self.transport = "serial" if self.port else "pty"
        tp = self.transport
        if tp not in ("serial", "pty", "inprocess", "sim"):
            raise ConfigError(f"unknown transport {tp!r}; valid: serial, pty, inprocess, sim",
                              key="transport")
        if tp == "sim" and self.lockstep:
            raise ConfigError("the sim transport runs the real-time mock on a virtual clock; "
                              "drop --lockstep", key="--lockstep")
        from hapsim.daemon.faults import parse_faults
        self.plan = parse_faults(self.faults, self.fault_seed)
        if not self.plan.empty and tp not in ("pty", "sim"):
            raise ConfigError("faults are injected by the mock: use the embedded mock (no "
                              "--port) or 'hapsim mock --faults' behind --port", key="--faults")
        if self.driver not in (None, "framed"):
            from hapsim.drivers import get_driver
            # unknown name or bad parameters: ConfigError before any work
            get_driver(self.driver, **(self.driver_options or {}))
            if not self.plan.empty:
                raise ConfigError("faults are injected by hapsim's own mock; a driver's mock "
                                  "has none", key="--faults")
            self.host_clocked = True            # the protocols answer commands: no clock
            self.lockstep = self.lockstep or self.port is None   # its mock: host-paced
        if self.reconnect is None:
            self.reconnect = not self.lockstep
        if tp == "serial" and not self.port:
            raise ConfigError("transport 'serial' needs a port", key="--port")
        if tp == "inprocess" and not self.lockstep:
            raise ConfigError("the in-process mock is lockstep only", key="--lockstep")
        if self.loop not in ("compiled", "python"):
            raise ConfigError(f"unknown loop {self.loop!r}; valid: compiled, python",
                              key="--loop")
        if self.telemetry is not None and os.path.splitext(self.telemetry)[1].lower() not in (
                ".npz", ".csv", ".hst"):
            raise ConfigError(f"unknown telemetry format for {self.telemetry!r}; valid: .hst "
                              f"(chunked journal), .npz, .csv", key="--telemetry")
        if self.telemetry is not None:   # before start-up, not when the loop first writes
            from hapsim.outputs import check_writable
            check_writable(self.telemetry, "--telemetry")
        return self

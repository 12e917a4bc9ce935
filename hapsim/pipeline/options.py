"""The options of one run (:class:`RunOptions`), each declared once.

A field that ``hapsim run`` takes from its command line carries its flag, type, help and
value check in its metadata (:func:`option`); :func:`add_run_arguments` generates the
parser's arguments from those fields and :meth:`RunOptions.from_args` builds the options
back from the parsed namespace, so an option's name, default, help and validation are
written in one place. :meth:`RunOptions.check` validates the whole (the fields one by one,
then their combinations) and resolves what depends on several; a program builds
:class:`RunOptions` directly (or through :func:`hapsim.api.run`), and
:func:`hapsim.pipeline.runner.run_scene` takes it."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from hapsim.drivers import DEFAULT
from hapsim.errors import ConfigError
from hapsim.option_values import Number, check_kind

if TYPE_CHECKING:       # an annotation only: the parser is built without the host loop
    from hapsim.host.loop import StopFlag

#: The loop's transports (:attr:`RunOptions.transport`).
TRANSPORTS = ("serial", "pty", "inprocess", "sim")

__all__ = ["RunOptions", "option", "add_run_arguments", "command_line_fields", "check_jack_server",
           "check_ramp"]


def check_jack_server(server: str | None, sound: str | None) -> None:
    """Refuse a JACK server's name where no JACK sound is played (``run`` and ``play``;
    before, taken and ignored).

    Parameters
    ----------
    server : str or None
        ``--jack-server``.
    sound : str or None
        ``--sound`` (None: none played).

    Raises
    ------
    ConfigError
        A server named with ``sound`` other than ``auto`` or ``jack`` (key
        ``--jack-server``).
    """
    if server is not None and sound not in ("auto", "jack"):
        raise ConfigError("names the JACK server of --sound jack (or auto); "
                          + ("without --sound no sound is played" if sound is None
                             else f"--sound {sound} has none"), key="--jack-server")


def check_ramp(ramp_given: bool, osc, view, key: str = "--ramp") -> None:
    """Refuse ``play``'s ``--ramp`` where no change can come in to be ramped (before, taken
    and ignored): the changes, and OSC's pause and resume, arrive through ``--osc`` or the
    live view (``--view``) only.

    Parameters
    ----------
    ramp_given : bool
        Whether ``--ramp`` (the API's ``ramp``) was given.
    osc, view : int or None
        ``--osc`` and ``--view``'s ports (None: not served).
    key : str
        The ramp's flag (``run``'s is ``--osc-ramp``).

    Raises
    ------
    ConfigError
        The ramp given with neither (keyed by ``key``).
    """
    if ramp_given and osc is None and view is None:
        raise ConfigError("ramps the changes that come in through --osc or --view, and "
                          "neither is given: nothing would be ramped", key=key)


def option(default, flag: str, help: str, *, metavar: str | None = None, type=None,
           choices: tuple | None = None, action: str | None = None, const=None,
           cli_default=dataclasses.MISSING, check=None, nargs=None):
    """A :class:`RunOptions` field that ``hapsim run`` also takes from its command line.

    Parameters
    ----------
    default : object
        The field's default (also the parser's, unless ``cli_default`` is given).
    flag : str
        The command-line flag (``"--duration"``); it is the key of a ConfigError about
        the field.
    help : str
        The parser's help text (``{drivers}`` is replaced by the driver names).
    metavar, type, choices, action, const
        As :meth:`argparse.ArgumentParser.add_argument` takes them; a numeric option's
        type is a :class:`~hapsim.option_values.Number`, its valid range (checked by
        :meth:`RunOptions.check_values` as by the command line).
    nargs : str, optional
        ``"?"``: the flag takes an optional value (``const`` when it is given alone).
    cli_default : object, optional
        The parser's default where it differs from the field's (``--loop auto``: the
        command resolves it before the run).
    check : callable, optional
        ``check(value, flag)`` raising :class:`~hapsim.errors.ConfigError` on a bad value
        (not called for None), beyond the type's range; run by
        :meth:`RunOptions.check_values`.

    Returns
    -------
    dataclasses.Field
    """
    meta = {"flag": flag, "help": help, "metavar": metavar, "type": type,
            "choices": choices, "action": action, "const": const, "check": check,
            "nargs": nargs,
            "cli_default": default if cli_default is dataclasses.MISSING else cli_default}
    return field(default=default, metadata={"cli": meta})


def _positive(value, flag: str, unit: str = "s") -> None:
    """Refuse a value that is not a finite number > 0."""
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"must be a positive number [{unit}], got {value}", key=flag)


def _rate(value, flag: str) -> None:
    """Refuse a rate override outside the scene's rate range
    (:data:`hapsim.analysis.loop.RATE_RANGE`)."""
    _positive(value, flag, "Hz")
    from hapsim.analysis.loop import RATE_RANGE, check_range
    check_range(value, *RATE_RANGE, flag, "Hz")


@dataclass
class RunOptions:
    """The options of one run, each declared once: a field ``hapsim run`` takes from its
    command line carries its flag, help and check (:func:`option`); the parser is generated
    from them (:func:`add_run_arguments`) and :meth:`from_args` builds them back. Taken by
    :func:`hapsim.api.run` and :func:`hapsim.pipeline.runner.run_scene`.

    :meth:`check` validates them and resolves ``transport`` (``"serial"``, ``"pty"``,
    ``"inprocess"`` or ``"sim"``), ``reconnect`` (a bool) and ``plan``.

    Attributes
    ----------
    port : str, optional
        Serial port of a device (hardware or ``hapsim mock``); None: a mock.
    baud : int
        Baud rate for ``port``.
    duration : float, optional
        Run length [s] (> 0); default :data:`hapsim.pipeline.runner.DEFAULT_DURATION`,
        longer for slow loops (the identification window: excitation + 10 periods). 0:
        open-ended, until SIGINT / SIGTERM (``handle_signals``), ``stop``, a safety stop or
        a device end. Telemetry in memory is the identification window plus a ring of
        :data:`hapsim.pipeline.runner.RING_SECONDS` (a run that fits in both is kept whole);
        the rest is only in the journal.
    rate_hz : float, optional
        Rate override [Hz].
    lockstep : bool
        Lockstep mock (one period per FORCE; deterministic).
    host_clocked : bool
        Host's clock instead of the device's (with ``lockstep``: the host paces the
        lockstep device in real time).
    frames : {"auto", "full", "compact"}
        Frames to ask the device for (PROTOCOL.md §4 "Compact frames"): ``"auto"`` asks
        for the compact frames where the full frames' round trip on the line takes more
        than half the period (:func:`firmware_protocol.wants_compact`), ``"compact"``
        whenever the device offers them (a device that does not keeps the full frames),
        ``"full"`` never.
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
        (:class:`~hapsim.emulated.links.SimTransport`: fast, deterministic fault tests).
        Both run hapsim's own mock: with a ``driver`` they are refused (ConfigError).
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
    on_precheck : callable, optional
        Called as ``on_precheck(statement)`` before the run starts when the scene's record
        is predicted not comparable (:func:`hapsim.pipeline.precheck.predict_comparable`:
        a contact that opens within the samples the fit needs); ``statement`` is the
        sentence the report's ``measured.stated_before_run`` holds. The run goes on.
    faults : str, optional
        Fault SPEC for the mock (:mod:`hapsim.emulated.faults`); ``pty`` and ``sim`` only.
    fault_seed : int
        Seed of the fault generator.
    reconnect : bool, optional
        Recover a lost device (default: on in real time, off in lockstep).
    lost_timeout : float, optional
        Silence after which the device is lost [s] (default: the watchdog period, 50 ms:
        the device zeroes its force after one watchdog period without a FORCE, and the
        host sends zero force and STOP then; see :class:`~hapsim.host.loop.LoopConfig`).
    reconnect_attempts : int
        Most HELLO + CONFIG attempts per loss.
    reconnect_time : float
        Most time spent recovering one loss [s].
    telemetry_interval : float
        Time between two telemetry chunks [s].
    driver : str, optional
        A device protocol of :mod:`hapsim.drivers`; None or ``"framed"`` (hapsim's own, the
        default; :meth:`check` stores it as None) speaks the framed protocol. Otherwise
        the loop is host-clocked through a
        :class:`~hapsim.drivers.transport.DriverTransport` on ``port``, or on that
        driver's mock (paced by the host) without a port.
    driver_options : dict, optional
        The driver's device parameters (its constructor's keywords: FireFader
        ``full_scale``, ``metres_per_count``, ``axis``; Haply ``device_id``,
        ``resolution``, ``direction``).
    mock_options : dict, optional
        The driver mock's hardware (:class:`hapsim.emulated.driver_mock.EmbeddedDriverMock`),
        which may differ from what ``driver_options`` believe.
    driver_faults : dict, optional
        Seeded byte loss and corruption on the driver mock's link, both directions
        (:class:`hapsim.emulated.driver_mock.ByteFaults`).
    osc : int, optional
        Serve live changes over OSC on localhost:PORT (0: any free port, printed on
        stderr; :mod:`hapsim.audio.control`: checked, ramped, journaled in the report's
        ``osc``). The measured (k, b) are those of the scene at the start.
    osc_ramp : float
        Ramp time of every OSC change [s] (and of the live view's).
    view : int, optional
        Serve the live view (:mod:`hapsim.view`) on 127.0.0.1:PORT (0: any free port,
        printed on stderr): its changes are the OSC ones (checked, ramped, journaled),
        its stop button ends the run as SIGINT does.
    sound : {"auto", "jack", "sounddevice"}, optional
        Play the scene's ``audio`` live: the frames the loop computes go through a ring to
        the sound server (report: ``sound`` with xruns and ring underruns).
    jack_server : str, optional
        JACK server name.
    plan : FaultPlan
        Set by :meth:`check`: the parsed ``faults``
        (:class:`~hapsim.emulated.faults.FaultPlan`).
    embedded : EmbeddedMock, optional
        The embedded mock already started for this run
        (:func:`hapsim.pipeline.startup.start_embedded_mock`, ``transport`` ``"pty"``);
        closed here whatever happens. Default: started by
        :func:`hapsim.pipeline.runner.connect`.
    loop : {"compiled", "python"}
        Host loop: the compiled hot path (:mod:`hapsim.host.fastloop`; over a pty or a
        serial port, device-clocked, without ``osc``/``sound``/``device.correction``;
        elsewhere the Python loop, and the report's ``loop.python_reason`` says why) or the
        Python reference loop (:class:`~hapsim.host.loop.HostLoop`).

    """

    # Each field that ``hapsim run`` takes from its command line is declared here once,
    # in the order of its help, with its flag, help and check (:func:`option`).
    port: str | None = option(
        None, "--port", "serial port of the device (default: embedded mock on a pty)",
        metavar="PORT")
    baud: int = option(
        115200, "--baud", "baud rate (default 115200; ignored by USB CDC and ptys)",
        metavar="BAUD", type=Number(int, low=1))
    duration: float | None = option(
        None, "--duration", "run length [s] (default 1 s, longer for slow oscillations); 0: "
        "open-ended, until SIGINT/SIGTERM (or a safety stop)",
        metavar="S", type=Number(float, low=0, unit="s"))
    rate_hz: float | None = option(
        None, "--rate", "override the scene's rate [Hz]", metavar="HZ",
        type=Number(float, low=0, open_low=True, unit="Hz"), check=_rate)
    lockstep: bool = option(
        False, "--lockstep", "lockstep mock: one period per FORCE, deterministic",
        action="store_true")
    host_clocked: bool = option(
        False, "--host-clocked", "tick on the host's clock instead of answering each STATE "
        "(with --lockstep: the host paces the lockstep mock in real time)",
        action="store_true")
    frames: str = option(
        "auto", "--frames", "frames to ask the device for: 'auto' (default: compact where "
        "the full frames' round trip on the line takes over half the period), 'compact' "
        "(whenever the device offers them: shorter STATE/FORCE and less of the device's "
        "codec time per tick, float32 on the wire), 'full'",
        choices=("auto", "full", "compact"))
    loop: str = option(
        "compiled", "--loop", "host loop: 'compiled' (the device-clocked hot path in one "
        "numba function that owns the port, without the GIL; a live --osc, --sound or a "
        "device correction keep the Python loop), 'python' (the reference loop: the same "
        "FORCEs bit for bit, to compare) or 'auto' (default: compiled when numba's cache "
        "holds it; otherwise this run uses the Python loop and compiles the other after its "
        "report, for the next runs)",
        choices=("auto", "compiled", "python"), cli_default="auto")
    telemetry: str | None = option(
        None, "--telemetry",
        "write per-sample time, position, force, seq, turnaround, late (.npz/.csv)",
        metavar="FILE")
    allow_unstable: bool = option(
        False, "--allow-unstable",
        "run a loop the analysis finds unstable, under the safety stops", action="store_true")
    rt_priority: int = option(
        10, "--rt-priority", "SCHED_FIFO priority of the loop and the embedded mock where the "
        "OS permits it (default 10; 0: normal scheduling; not with --lockstep, which is paced "
        "by the answers, not the clock). Under load it keeps late ticks rare; the report says "
        "what was obtained", metavar="N", type=Number(int, low=0, high=99))
    seed: int = option(0, "--seed", "mock sensor-noise seed (default 0)",
        type=Number(int, low=0))
    faults: str | None = option(
        None, "--faults", "inject seeded faults in the embedded mock, e.g. "
        "drop=0.01,corrupt=0.005,stall@500:200ms,reset@800 (see below)", metavar="SPEC")
    fault_seed: int = option(
        0, "--fault-seed", "seed of the fault generator (default 0)", metavar="N",
        type=Number(int, low=0))
    reconnect: bool | None = option(
        None, "--no-reconnect",
        "a lost device ends the run (exit 1) instead of being recovered",
        action="store_const", const=False)
    lost_timeout: float | None = option(
        None, "--lost-timeout", "silence after which the device is lost [s] (default: the "
        "watchdog period, 0.05)", metavar="S",
        type=Number(float, low=0, open_low=True, unit="s"))
    reconnect_attempts: int = option(
        8, "--reconnect-attempts", "most reconnect attempts per loss (default 8)",
        metavar="N", type=Number(int, low=0))
    reconnect_time: float = option(
        10.0, "--reconnect-time", "most time spent recovering one loss [s] (default 10)",
        metavar="S", type=Number(float, low=0, unit="s"))
    driver: str | None = option(
        None, "--driver", "device protocol, one of {drivers} (default: the scene's "
        "device.protocol, else framed, hapsim's own); drivers: --help-all", metavar="NAME")
    osc: int | None = option(
        None, "--osc", "take live changes over OSC on localhost:PORT (0: any free port; "
        "addresses: hapsim play --help); each is checked, ramped, journaled",
        metavar="PORT", type=Number(int, low=0, high=65535))
    osc_ramp: float = option(
        0.05, "--osc-ramp", "ramp time of every OSC change [s] (default 0.05)", metavar="S",
        type=Number(float, low=0, unit="s"))
    view: int | None = option(
        None, "--view", "serve a live view (scene, traces, (k, b) grid, changes, stop) "
        "on http://127.0.0.1:PORT (default 8765; 0: any free port); extra 'view'", metavar="PORT", nargs="?", const=8765,
        type=Number(int, low=0, high=65535))
    sound: str | None = option(
        None, "--sound", "play the scene's audio section live (JACK, else PortAudio with "
        "auto); the model stays in the loop, the frames go to the server",
        choices=("auto", "jack", "sounddevice"))
    jack_server: str | None = option(
        None, "--jack-server", "JACK server name (jackd -n NAME)", metavar="NAME")
    # a program's options (no flag)
    transport: str | None = None
    stop: StopFlag | None = None
    handle_signals: bool = True
    on_start: object = None
    on_precheck: object = None
    telemetry_interval: float = 0.05
    driver_options: dict | None = None
    mock_options: dict | None = None
    driver_faults: dict | None = None
    plan: object = None
    embedded: object = None

    @classmethod
    def from_args(cls, args: argparse.Namespace, **changes) -> "RunOptions":
        """The options of a parsed command line (:func:`add_run_arguments`), checked one
        by one (:meth:`check_values`; the whole is checked by :meth:`check`).

        Parameters
        ----------
        args : argparse.Namespace
            Holds one attribute per field of :func:`command_line_fields`, by field name.
        **changes
            Other fields (``on_start``, ``embedded``, ...), or fields the command resolved
            (``driver``, ``loop``).

        Returns
        -------
        RunOptions

        Raises
        ------
        ConfigError
            A bad value, keyed by its flag (``--rate``, ``--faults``, ...).
        """
        values = {f.name: getattr(args, f.name) for f in command_line_fields()}
        return cls(**{**values, **changes}).check_values()

    def check_values(self) -> "RunOptions":
        """Check each command-line field by its declared check, and the fault SPEC.

        Returns
        -------
        RunOptions
            ``self``.

        Raises
        ------
        ConfigError
            A bad value, keyed by its flag; an unknown fault name (with the valid ones).
        """
        for f in command_line_fields():
            meta = f.metadata["cli"]
            value = getattr(self, f.name)
            if value is None:
                continue
            # the kind of value its flag gives (a program may pass anything: before, a
            # list for a number or a number for a path was a TypeError in the run)
            check_kind(meta["flag"], value, "a number" if isinstance(meta["type"], Number)
                       else "True or False" if meta["action"] in (
                           "store_true", "store_false", "store_const") else "a text")
            if isinstance(meta["type"], Number):      # its declared range
                meta["type"].check(value, meta["flag"])
            if meta["check"] is not None:
                meta["check"](value, meta["flag"])
        self._check_program_fields()
        from hapsim.emulated.faults import parse_faults
        parse_faults(self.faults, self.fault_seed)
        return self

    def _check_program_fields(self) -> None:
        """The kinds of a program's options, which have no flag (before: an n-D run took a
        ``transport`` of any word, a 1-D one's ``on_start`` of a word was a TypeError at
        its start, ``telemetry_interval=-1`` and ``mock_options="x"`` ran)."""
        if self.transport is not None and self.transport not in TRANSPORTS:
            raise ConfigError(f"unknown transport {self.transport!r}; valid: "
                              f"{', '.join(TRANSPORTS)}", key="transport")
        if self.stop is not None and not callable(getattr(self.stop, "request", None)):
            raise ConfigError(f"must be a hapsim.host.loop_types.StopFlag, got "
                              f"{self.stop!r}", key="stop")
        check_kind("handle_signals", self.handle_signals, "True or False", required=True)
        for key in ("on_start", "on_precheck"):
            if getattr(self, key) is not None and not callable(getattr(self, key)):
                raise ConfigError(f"must be a function, got {getattr(self, key)!r}", key=key)
        Number(float, low=0, open_low=True, unit="s").check(self.telemetry_interval,
                                                            "telemetry_interval")
        for key in ("driver_options", "mock_options", "driver_faults"):
            check_kind(key, getattr(self, key), "a mapping of options")

    @property
    def protocol(self) -> str:
        """The device's protocol: :attr:`driver`'s name, or ``"framed"`` (hapsim's own,
        spoken by the loop's own transport; :meth:`check` stores it as ``driver=None``)."""
        return self.driver or DEFAULT

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
        self.check_values()
        if self.driver == DEFAULT:
            self.driver = None          # hapsim's own protocol: no driver object, once here
        if self.duration == 0 and self.stop is None and not self.handle_signals:
            raise ConfigError("an open-ended run (duration 0) needs a way to stop it: "
                              "handle_signals or a stop flag", key="--duration")
        if self.transport is None:
            self.transport = "serial" if self.port else "pty"
        tp = self.transport
        if tp == "sim" and self.lockstep:
            raise ConfigError("the sim transport runs the real-time mock on a virtual clock; "
                              "drop --lockstep", key="--lockstep")
        from hapsim.emulated.faults import parse_faults
        self.plan = parse_faults(self.faults, self.fault_seed)
        if not self.plan.empty and tp not in ("pty", "sim"):
            raise ConfigError("faults are injected by the mock: use the embedded mock (no "
                              "--port) or 'hapsim mock --faults' behind --port", key="--faults")
        why = self.plan.lockstep_refusal() if self.lockstep and self.driver is None else None
        if why:
            raise ConfigError(why, key="--faults")
        if self.driver is not None:
            from hapsim.drivers import get_driver
            # unknown name or bad parameters: ConfigError before any work
            get_driver(self.driver, **(self.driver_options or {}))
            if tp in ("inprocess", "sim"):
                raise ConfigError(f"transport {tp!r} runs hapsim's own mock in this process; "
                                  f"the {self.driver} driver talks to its board over a port "
                                  "(its emulated board when no port is given); valid with a "
                                  "driver: pty, serial", key="transport")
            if not self.plan.empty:
                raise ConfigError("faults are injected by hapsim's own mock; a driver's mock "
                                  "has none", key="--faults")
            if self.frames != "auto":           # (before: taken and ignored)
                raise ConfigError(f"the framed protocol's frames; the {self.driver} "
                                  "protocol's records are its board's", key="--frames")
            self.host_clocked = True            # the protocols answer commands: no clock
            # its mock keeps its own time (the wall clock) unless the run asks for
            # lockstep (hapsim.emulated.driver_mock.WALL_CLOCK_MOCKS)
            from hapsim.emulated.driver_mock import WALL_CLOCK_MOCKS
            self.lockstep = self.lockstep or (self.port is None
                                              and self.driver not in WALL_CLOCK_MOCKS)
        check_jack_server(self.jack_server, self.sound)
        default = {f.name: f.default for f in dataclasses.fields(self)}
        check_ramp(self.osc_ramp != default["osc_ramp"], self.osc, self.view, "--osc-ramp")
        if self.fault_seed != default["fault_seed"] and self.plan.empty:
            raise ConfigError("seeds the faults of --faults, and none is given",
                              key="--fault-seed")
        if self.reconnect is False:             # (before: taken and ignored)
            for f in dataclasses.fields(self):
                if f.name in ("reconnect_attempts", "reconnect_time") and \
                        getattr(self, f.name) != f.default:
                    raise ConfigError("how a lost device is recovered; --no-reconnect "
                                      "ends the run at a loss", key=f.metadata["cli"]["flag"])
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


def command_line_fields() -> tuple:
    """The fields of :class:`RunOptions` that ``hapsim run`` takes from its command line,
    in the order of its help.

    Returns
    -------
    tuple of dataclasses.Field
        Each with its declaration in ``metadata["cli"]`` (:func:`option`).
    """
    return tuple(f for f in dataclasses.fields(RunOptions) if "cli" in f.metadata)


def add_run_arguments(parser: argparse.ArgumentParser, after: dict | None = None) -> None:
    """Add one argument per command-line field of :class:`RunOptions` to ``parser``
    (dest: the field's name; flag, type, default, help, choices: its declaration).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        ``hapsim run``'s parser (or a group of it).
    after : dict, optional
        Field name -> ``add(parser)``, called right after that field's argument: where
        the command shows its own options beside the run options they go with.
    """
    after = after or {}
    drivers = None
    for f in command_line_fields():
        meta = f.metadata["cli"]
        text = meta["help"]
        if "{drivers}" in text:
            if drivers is None:
                from hapsim.drivers import DRIVERS
                drivers = ", ".join(DRIVERS)
            text = text.replace("{drivers}", drivers)
        kw = {"dest": f.name, "default": meta["cli_default"], "help": text}
        if meta["action"] is not None:
            kw["action"] = meta["action"]
            if meta["const"] is not None:
                kw["const"] = meta["const"]
        else:
            kw.update({k: meta[k] for k in ("type", "metavar", "choices")
                       if meta[k] is not None})
            if meta.get("nargs") is not None:
                kw.update(nargs=meta["nargs"], const=meta["const"])
        parser.add_argument(meta["flag"], **kw)
        if f.name in after:
            after[f.name](parser)

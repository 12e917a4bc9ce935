"""``hapsim run``: close the THS of a scene on a device (or its mock) and measure it."""

from __future__ import annotations

import argparse
import json
import math
import sys

from hapsim.errors import ConfigError
from hapsim.outputs import json_safe

_DESCRIPTION = """\
Run a scene in real time against a force-feedback device and measure what the hand feels.

The hand + handle mass m, the device's real friction b0, the zero-order hold of the force,
the d samples of delay and the virtual spring K / damper B of the scene together form one
sampled oscillator, the temporary hybrid system (THS; Florens, Voda & Urma). hapsim closes
it through the framed serial protocol, logs every sample, and identifies the oscillation of
the free response (after the excitation has ended) by the matrix pencil method: its
eigenfrequency f0 and damping ratio zeta, i.e. the stiffness k = m (2 pi f0)^2 and damping
b = 2 zeta sqrt(k m) really felt. It prints them beside what the analysis predicted for
this (K, B) and, for links given as 'target: {k, b}', beside what the scene asked for (the
(K, B) are then calibrated to render that target, or the run is refused).

Without --port, the embedded mock device runs in a child process behind a real
pseudo-terminal (real-time: it ticks on the clock; --lockstep: one period per FORCE,
deterministic, measured = predicted to round-off). With --port, the same daemon drives
hardware (or a 'hapsim mock' started elsewhere)."""

_EPILOG = """\
what the numbers mean:
  target      the (k, b) the scene asked for, with its f0 and zeta, and whether it is
              renderable (one row per target link; --json: 'targets', 'target' = the first)
  virtual     the K [N/m], B [N s/m] simulated (calibrated when a target is given)
  predicted   the rendered (k, b): least damped closed-loop pole pair z, s = ln(z)/T,
              k = m |s|^2, b = -2 m Re(s) (b is the whole THS damping, b0 included)
  measured    the same figures identified from the logged positions (matrix pencil of
              the closed-loop order, on the longest stretch of the free response without
              late ticks: a late FORCE is a disturbance, not part of the THS)
  rel. error  (measured - predicted) / predicted; 'vs target': against the target
  loop        rate, ticks, late (device held an older force), missed (STATE gaps),
              turnaround p50/p99/p99.9/max [us] from STATE read to FORCE written,
              low-latency serial mode on/off
timing: STATE n carries x(nT); FORCE n is computed from x[n], x[n-1] and applied over
  [(n+d)T, (n+d+1)T) by the device's zero-order hold.
safety: host-side force clamp; NaN/inf -> zero force and stop; SIGINT/SIGTERM -> zero
  force, STOP, telemetry flushed, exit 0 (from the numba warm-up on: Ctrl-C during
  start-up ends before the device is armed); an unstable scene is refused unless
  --allow-unstable, which runs it under safety stops (force at the limit in half of the
  last 100 samples, position beyond bounds, non-finite values) that end with zero force;
  the scene's 'safety:' section adds position_limit [m], velocity_limit [m/s],
  energy_limit [J] (passivity observer: energy the scene gave the hand beyond what it
  stored at its start; restarted at each recovery) and an optional passivity_controller
  with max_damping [N s/m] that damps that excess.
drivers' devices (--driver): a reply that does not come is a missing sample (counted;
  the next tick asks again), not a lost device; the FireFader .ino disables its force
  after 0.1 s of silence, the Haply board and the Hapkit sketch have NO watchdog and hold
  the last force: hapsim sends zero force first and at every end (docs/drivers.md).
reliability: bad frames are counted and dropped; silence for --lost-timeout (default:
  the 50 ms watchdog period, when a framed device zeroes its force by itself), a port error or
  a device reset (a HELLO after arming: noticed at once) -> zero force, STOP, state
  'lost', then re-open, HELLO, CONFIG with backoff (state 'recovering'; at most
  --reconnect-attempts / --reconnect-time per loss), the scene restarted from its initial
  state at the device's position, force ramped over 50 ms. --telemetry FILE.hst is a
  chunked journal written every 50 ms from a ring buffer by a writer thread (a killed
  daemon loses < 100 ms, and the journal also holds the loss/recovery events and a
  per-sample flags column: late, lost, ramp, clamped; load it with
  hapsim.daemon.telemetry.load); with .npz/.csv the journal is FILE.hst until the end.
open-ended runs: --duration 0 runs until SIGINT/SIGTERM; memory holds the
  identification window at the start and a 4 s ring, the journal holds every sample.
faults (embedded mock): --faults SPEC --fault-seed N, SPEC items NAME=RATE[:DUR] (drop,
  corrupt, garbage, dup, reorder, spike: per device -> host frame; the same names prefixed
  rx. (rx.drop, rx.corrupt, rx.garbage, rx.dup, rx.reorder, rx.spike): per host -> device
  frame, i.e. FORCE, CONFIG, PING, STOP as the device receives them; stall, reset, vanish:
  per tick), NAME@TICK[:DUR] (once at device tick TICK), nohello; DUR like 5ms, 0.3s.
  The same loss/recovery applies with --host-clocked. Example:
  --faults drop=0.01,corrupt=0.005,garbage=0.001,dup=0.002,reorder=0.002,spike=0.001:5ms,
           stall@500:200ms,reset@800,vanish@1200:300ms,rx.drop=0.01,rx.corrupt=0.005
drivers (--driver NAME; without --port: a mock speaking that protocol byte for byte):
  framed     hapsim's own protocol (COBS frames, CRC, sequence numbers, watchdog)
{drivers}
examples:
  hapsim run configs/wall.yaml
  hapsim run configs/firefader.yaml --driver firefader
  hapsim run configs/felt_wall.yaml --lockstep --json
  hapsim run configs/wall.yaml --telemetry wall.npz --duration 2
  hapsim run configs/wall.yaml --auto --lockstep      rate and method from 'hapsim advise'
  hapsim run configs/wall.yaml --port /dev/ttyACM0 --baud 2000000
  hapsim run configs/wall.yaml --faults drop=0.01,reset@800 --telemetry wall.hst
  hapsim run configs/wall.yaml --duration 0 --telemetry session.hst   (Ctrl-C ends it)
exit codes:
  0  ran to the end (or stopped by SIGINT/SIGTERM)
  1  refused (unstable loop, unrenderable target), safety stop, latched device fault, device lost beyond
     recovery (or silent with --no-reconnect)
  2  bad arguments, invalid scene, unknown fault name"""


def register(sub) -> None:
    """Add the ``run`` parser to the CLI.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers action of ``hapsim``'s parser; ``run``'s ``func`` is :func:`run`.
    """
    from hapsim.drivers import DRIVERS, get_driver
    limits = "\n".join("  " + line for name in DRIVERS if name != "framed"
                       for line in get_driver(name).limits.splitlines())
    p = sub.add_parser("run", help="close the THS on a device or the mock and measure the "
                                   "felt stiffness and damping",
                       description=_DESCRIPTION, epilog=_EPILOG.replace("{drivers}", limits),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file with a port and a device")
    p.add_argument("--port", metavar="PORT",
                   help="serial port of the device (default: embedded mock on a pty)")
    p.add_argument("--baud", type=int, default=115200, metavar="BAUD",
                   help="baud rate (default 115200; ignored by USB CDC and ptys)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="run length [s] (default 1 s, longer for slow oscillations); 0: "
                        "open-ended, until SIGINT/SIGTERM (or a safety stop)")
    p.add_argument("--rate", type=float, metavar="HZ", help="override the scene's rate [Hz]")
    p.add_argument("--lockstep", action="store_true",
                   help="lockstep mock: one period per FORCE, deterministic")
    p.add_argument("--host-clocked", action="store_true",
                   help="tick on the host's clock instead of answering each STATE "
                        "(with --lockstep: the host paces the lockstep mock in real time)")
    p.add_argument("--loop", choices=("auto", "compiled", "python"), default="auto",
                   help="host loop: 'compiled' (the device-clocked hot path in one numba "
                        "function that owns the port, without the GIL; a live --osc, --sound "
                        "or a device correction keep the Python loop), 'python' (the "
                        "reference loop: the same FORCEs bit for bit, to compare) or 'auto' "
                        "(default: compiled when numba's cache holds it; otherwise this run "
                        "uses the Python loop and compiles the other after its report, for "
                        "the next runs)")
    p.add_argument("--telemetry", metavar="FILE",
                   help="write per-sample time, position, force, seq, turnaround, late (.npz/.csv)")
    p.add_argument("--allow-unstable", action="store_true",
                   help="run a loop the analysis finds unstable, under the safety stops")
    p.add_argument("--rt-priority", type=int, default=10, metavar="N",
                   help="SCHED_FIFO priority of the loop and the embedded mock where the OS "
                        "permits it (default 10; 0: normal scheduling; not with --lockstep, "
                        "which is paced by the answers, not the clock). Under load it keeps "
                        "late ticks rare; the report says what was obtained")
    p.add_argument("--seed", type=int, default=0, help="mock sensor-noise seed (default 0)")
    p.add_argument("--auto", action="store_true",
                   help="use 'hapsim advise': the lowest rate and cheapest method that keep "
                        "the felt (k, b) within --tolerance (calibrating port links)")
    p.add_argument("--tolerance", type=float, default=0.01, metavar="REL",
                   help="relative tolerance on the felt (k, b) for --auto (default 0.01)")
    p.add_argument("--faults", metavar="SPEC",
                   help="inject seeded faults in the embedded mock, e.g. "
                        "drop=0.01,corrupt=0.005,stall@500:200ms,reset@800 (see below)")
    p.add_argument("--fault-seed", type=int, default=0, metavar="N",
                   help="seed of the fault generator (default 0)")
    p.add_argument("--no-reconnect", action="store_true",
                   help="a lost device ends the run (exit 1) instead of being recovered")
    p.add_argument("--lost-timeout", type=float, metavar="S",
                   help="silence after which the device is lost [s] (default: the watchdog "
                        "period, 0.05)")
    p.add_argument("--reconnect-attempts", type=int, default=8, metavar="N",
                   help="most reconnect attempts per loss (default 8)")
    p.add_argument("--reconnect-time", type=float, default=10.0, metavar="S",
                   help="most time spent recovering one loss [s] (default 10)")
    p.add_argument("--driver", metavar="NAME",
                   help=f"device protocol, one of {', '.join(DRIVERS)} (default: the "
                        "scene's device.protocol, else framed, hapsim's own); a driver runs "
                        "host-clocked (see 'drivers' below)")
    p.add_argument("--device", metavar="FILE.yaml",
                   help="device section from a file (e.g. written by 'hapsim identify "
                        "--out'); replaces the scene's (said on stderr)")
    p.add_argument("--osc", type=int, metavar="PORT",
                   help="take live changes over OSC on localhost:PORT (0: any free port; "
                        "addresses: hapsim play --help); each is checked, ramped, journaled")
    p.add_argument("--osc-ramp", type=float, default=0.05, metavar="S",
                   help="ramp time of every OSC change [s] (default 0.05)")
    p.add_argument("--sound", choices=("auto", "jack", "sounddevice"),
                   help="play the scene's audio section live (JACK, else PortAudio with "
                        "auto); the model stays in the loop, the frames go to the server")
    p.add_argument("--jack-server", metavar="NAME", help="JACK server name (jackd -n NAME)")
    p.add_argument("--amplitude", type=float, metavar="M",
                   help="2-D or 3-D scene (with --lockstep): the excitation amplitude of "
                        "the measured free responses [m] (default 1e-8; the report states "
                        "the linearisation bound at it)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


def _announce(port, n_samples, protocol: str = "the framed protocol", note: str = "") -> None:
    """Tell the user on stderr that the loop starts, in which protocol, and that Ctrl-C
    stops it cleanly.

    Parameters
    ----------
    port : str or None
        The port the loop drives (None: the in-process mock).
    n_samples : int
        Samples to run; 0 for an open-ended run.
    protocol : str
        What :func:`protocol_of` says (``"the framed protocol"``, ``"the firefader
        protocol (the scene's device.protocol)"``, ...).
    note : str
        Appended (which host loop runs, when it is not the one asked for).
    """
    length = f"{n_samples} samples" if n_samples else "an open-ended run"
    print(f"hapsim run: closing the loop on {port or 'the in-process mock'} in {protocol} "
          f"for {length} (SIGINT/SIGTERM stop cleanly){note}",
          file=sys.stderr, flush=True)


def protocol_of(scene, driver: str | None) -> tuple[str, str]:
    """The protocol a run speaks, and where that choice comes from.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The scene (its ``device.protocol``; ``"framed"`` without a device).
    driver : str or None
        ``--driver`` (None when not given).

    Returns
    -------
    name : str
        One of :data:`hapsim.drivers.DRIVERS`.
    said : str
        The name with its source, for the start-up line: ``"the framed protocol"``,
        ``"the firefader protocol (the scene's device.protocol)"``, ``"the haply protocol
        (--driver; the scene's device.protocol is firefader)"``.
    """
    named = scene.device.protocol if scene.device is not None else "framed"
    if driver is None:
        return named, (f"the {named} protocol" + ("" if named == "framed"
                                                   else " (the scene's device.protocol)"))
    if driver != named:
        return driver, (f"the {driver} protocol (--driver; the scene's device.protocol "
                        f"is {named})")
    return driver, f"the {driver} protocol"


def run(args) -> int:
    """Run ``hapsim run``: load the scene, close the loop, print the report.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options of :func:`register` (``scene``, ``port``, ``duration``, ``rate``,
        ``lockstep``, ``telemetry``, ``faults``, ``lost_timeout``, ``json``, ...).

    Returns
    -------
    int
        Exit code: 0 (ran to the end, or stopped by SIGINT/SIGTERM), 1 (safety stop or a
        latched device fault).

    Raises
    ------
    ConfigError
        Bad option values (``--rate``, ``--lost-timeout``, ``--reconnect-*``, ``--faults``,
        ``--auto`` with ``--rate``), an invalid scene (exit 2 from
        :func:`hapsim.cli.main`).
    UnstableConfigError
        Unstable loop without ``--allow-unstable``, or ``--auto`` finding no rate (exit 1).
    DeviceError, ProtocolError
        Port failure, device lost beyond recovery, or a device hapsim cannot drive (exit 1).
    """
    from hapsim.scene import load_scene
    from hapsim.scene_nd import scene_dimension
    if scene_dimension(args.scene) > 1:        # a 2-D or 3-D scene: in lockstep, in-process
        from hapsim.commands.run_nd import run_nd
        return run_nd(args)
    if getattr(args, "amplitude", None) is not None:
        raise ConfigError("takes 2-D or 3-D scenes; a 1-D scene's excitation is its "
                          "excitation section", key="--amplitude")

    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise ConfigError(f"must be a positive number [Hz], got {args.rate}", key="--rate")
    if args.rate is not None:  # the scene's rate range (hapsim.analysis.loop.RATE_RANGE)
        from hapsim.analysis.loop import RATE_RANGE, check_range
        check_range(args.rate, *RATE_RANGE, "--rate", "Hz")
    if args.lost_timeout is not None and not (math.isfinite(args.lost_timeout)
                                              and args.lost_timeout > 0):
        raise ConfigError(f"must be a positive number [s], got {args.lost_timeout}",
                          key="--lost-timeout")
    if args.reconnect_attempts < 0:
        raise ConfigError(f"must be >= 0, got {args.reconnect_attempts}",
                          key="--reconnect-attempts")
    if not (math.isfinite(args.reconnect_time) and args.reconnect_time >= 0):
        raise ConfigError(f"must be a number of seconds >= 0, got {args.reconnect_time}",
                          key="--reconnect-time")
    if args.faults:
        from hapsim.daemon.faults import parse_faults
        parse_faults(args.faults, args.fault_seed)      # unknown names: exit 2 before loading
    scene = load_scene(args.scene)
    if getattr(args, "device", None):
        scene = _replace_device(scene, args.device)
    from hapsim.daemon import startup
    # an empty numba cache: say what is compiled (once the scene is read: a bad scene gets
    # its one-line error alone) before the silence it costs
    startup.reset_announcements()
    startup.announce_compilation(startup.run_compile_parts(scene, compiled_loop=False),
                                 scene=scene)
    advice = None
    if args.auto:
        from hapsim.bench.advise import advise_scene
        from hapsim.errors import UnstableConfigError
        if args.rate is not None:
            raise ConfigError("--auto chooses the rate; drop --rate or --auto", key="--auto")
        advice = advise_scene(scene, args.tolerance)
        if not advice.ok:
            raise UnstableConfigError(f"{scene.path}: no rate and method keep what is felt "
                                      f"within {args.tolerance:g}: {advice.reason}")
        scene = advice.apply(scene)
        print(f"hapsim run --auto: {advice.rate_hz:g} Hz, integrator {advice.integrator}: "
              f"{advice.reason}", file=sys.stderr, flush=True)
    from hapsim.errors import DeviceError, ProtocolError
    args.protocol, said = protocol_of(scene, args.driver)
    note = ""
    args.announce = lambda port, n: _announce(port, n, said, note)
    # an empty numba cache: say what is compiled before the silence it costs, and compile
    # only what this run needs (--loop auto: the compiled loop after the report)
    possible = startup.compiled_loop_possible(scene, framed=args.protocol == "framed",
                                              osc=args.osc, sound=args.sound,
                                              host_clocked=args.host_clocked)
    asked = args.loop
    if asked == "auto":     # a run that cannot use the compiled loop reports why it did not
        args.loop = startup.choose_loop(asked, scene) if possible else "compiled"
    compile_later = asked == "auto" and args.loop == "python"
    startup.announce_compilation(startup.run_compile_parts(
        scene, compiled_loop=args.loop == "compiled" and possible), scene=scene)
    if compile_later:           # said when the loop starts (not before an input error)
        note = ("; the Python host loop this time (the compiled one is not in numba's cache "
                "yet: it is compiled after the report, for the next runs)")
    embedded = None
    if args.port is None and args.protocol == "framed":
        # the mock's child starts now, beside the imports and the warm-up that follow
        from hapsim.daemon.startup import start_embedded_mock
        embedded = start_embedded_mock(scene, rate_hz=args.rate, lockstep=args.lockstep,
                                       seed=args.seed, faults=args.faults,
                                       fault_seed=args.fault_seed,
                                       rt_priority=0 if args.lockstep and not args.host_clocked
                                       else max(args.rt_priority, 0))
    from hapsim.daemon.report import format_report
    try:
        rep = _run(scene, args, embedded)
    except (DeviceError, ProtocolError) as exc:
        rep = getattr(exc, "report", None)
        if rep is None:                 # never started: nothing to report but the error
            raise
        lost = exc
    else:
        lost = None
    code = rep.pop("exit_code")
    if advice is not None:
        rep["advice"] = advice.to_dict()
    if args.json:
        print(json.dumps(json_safe(rep)))
    else:
        print(format_report(rep))
    sys.stdout.flush()
    if lost is not None:                # the report first, then why the run ended
        print(f"hapsim run: {type(lost).__name__}: {lost}", file=sys.stderr, flush=True)
    stopped = str(rep.get("loop", {}).get("stop_reason") or "").startswith("signal")
    if compile_later and lost is None and not stopped:     # not after a Ctrl-C
        _compile_loop_for_next_runs(scene)
    return code


def _compile_loop_for_next_runs(scene) -> None:
    """Compile the compiled host loop for ``scene``'s kernel into numba's cache, after a
    run that used the Python loop because the cache did not hold it (``--loop auto``);
    Ctrl-C leaves it for the next run."""
    import time
    t0 = time.monotonic()
    print("hapsim run: compiling the compiled host loop for the next runs (once) ...",
          file=sys.stderr, flush=True)
    try:
        from hapsim.analysis.targets import apply_targets
        from hapsim.daemon.fastloop import warm_up
        from hapsim.engine import Engine
        warm_up(Engine(apply_targets(scene)[0]))
    except KeyboardInterrupt:
        print("hapsim run: interrupted; the next run compiles it", file=sys.stderr, flush=True)
        return
    print(f"hapsim run: compiled the compiled host loop ({time.monotonic() - t0:.1f} s); the "
          "next runs use it", file=sys.stderr, flush=True)


def _replace_device(scene, path: str):
    """The scene with its device section replaced by the file's (``--device FILE``).

    What the file leaves out and the scene gives is kept: the force limit (``hapsim
    identify --out`` does not measure it), the protocol and, with the same protocol, its
    options (``device.protocol_options``). One line on stderr says what
    was replaced, and by which values.

    Parameters
    ----------
    scene : hapsim.scene.Scene
    path : str
        A device file (:func:`hapsim.device_file.load_device`).

    Returns
    -------
    hapsim.scene.Scene

    Raises
    ------
    ConfigError
        An unreadable or invalid device file (file, line and key named).
    """
    import dataclasses

    from hapsim.device_file import device_keys, load_device
    dev = load_device(path)
    given = device_keys(path)
    old = scene.device
    if old is not None:
        keep = {name: getattr(old, name) for name in ("force_limit", "protocol")
                if name not in given}
        # the device's own parameters go with its protocol: kept when the file names
        # neither them nor another protocol
        if "protocol_options" not in given and keep.get("protocol", dev.protocol) == old.protocol:
            keep["protocol_options"] = old.protocol_options
        dev = dataclasses.replace(dev, **keep)
    changed = [] if old is None else [
        f"{f.name} {_short(getattr(old, f.name))} -> {_short(getattr(dev, f.name))}"
        for f in dataclasses.fields(dev) if getattr(old, f.name) != getattr(dev, f.name)]
    what = (f"{'; '.join(changed)}" if changed else "the same values") if old is not None \
        else "the scene had none"
    print(f"hapsim run: the device of {path} replaces the scene's ({what})",
          file=sys.stderr, flush=True)
    return dataclasses.replace(scene, device=dev)


def _short(value) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def run_options(args, scene, embedded=None):
    """The :class:`~hapsim.daemon.runner.RunOptions` of ``hapsim run``'s command line: the
    one place where an option of the parser becomes an option of the run.

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim run``'s parsed arguments (with ``protocol`` and ``announce`` once
        :func:`run` has chosen them).
    scene : hapsim.scene.Scene
        The scene run (its ``device.protocol`` when ``args`` has no ``protocol``:
        :func:`protocol_of`).
    embedded : EmbeddedMock, optional
        The embedded mock already started for this run.

    Returns
    -------
    RunOptions
        Not yet checked (:func:`~hapsim.daemon.runner.run_scene` checks it).
    """
    from hapsim.daemon.options import RunOptions
    protocol = getattr(args, "protocol", None) or protocol_of(scene, args.driver)[0]
    return RunOptions(port=args.port, baud=args.baud, duration=args.duration,
                      rate_hz=args.rate, lockstep=args.lockstep, host_clocked=args.host_clocked,
                      telemetry=args.telemetry, allow_unstable=args.allow_unstable,
                      seed=args.seed, rt_priority=args.rt_priority,
                      on_start=getattr(args, "announce", _announce),
                      faults=args.faults, fault_seed=args.fault_seed,
                      reconnect=False if args.no_reconnect else None,
                      lost_timeout=args.lost_timeout,
                      reconnect_attempts=args.reconnect_attempts,
                      reconnect_time=args.reconnect_time, osc=args.osc,
                      osc_ramp=args.osc_ramp, sound=args.sound, jack_server=args.jack_server,
                      driver=None if protocol == "framed" else protocol,
                      loop=args.loop, embedded=embedded)


def _run(scene, args, embedded=None) -> dict:
    """:func:`hapsim.daemon.runner.run_scene` with the options of the command line."""
    from hapsim.daemon.runner import run_scene
    return run_scene(scene, run_options(args, scene, embedded))

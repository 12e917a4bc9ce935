"""``hapsim run``: close the THS of a scene on a device (or its mock) and measure it.

A 1-D scene through :func:`hapsim.pipeline.runner.run_scene`; a 2-D or 3-D scene
(:func:`run_nd`): the felt matrices measured and compared with the prediction, and the
linearisation bound. ``--lockstep``: the loop closed in-process; ``--port PORT``: over the
framed protocol with an n-axis device, in real time (late ticks accounted per axis,
:mod:`hapsim.pipeline.felt_port`); neither: the same over the embedded n-D mock (``hapsim mock
--scene SCENE --once``) in a child process behind a pty. ``--driver haply`` and ``--driver
falcon`` on 2-D/3-D scenes: the route the drivers' registry names for them
(:data:`hapsim.drivers.FAMILIES`: :mod:`hapsim.commands.run_haply2`,
:mod:`hapsim.commands.run_falcon`)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from hapsim.drivers import DEFAULT, protocol_of
from hapsim.errors import ConfigError
from hapsim.option_values import Number, declared

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
hardware (or a 'hapsim mock' started elsewhere).

A 2-D or 3-D scene (dimension: 2 or 3; docs/dimensions.md) is measured as a matrix: 2n
free responses of the handle (displaced by --amplitude along each axis, then moving along
each; minus the response from rest) give the felt stiffness and damping MATRICES, printed
beside check's prediction with their largest difference, the linearisation bound at that
amplitude and the verdict (within, differs, or not measurable). --lockstep runs it
in-process, exactly; without it the n-axis mock (the pantograph's or delta's joint-space
dynamics) serves it in real time, late ticks accounted per axis (a port lost is recovered as
in 1-D: --no-reconnect, --reconnect-time, --reconnect-attempts, --lost-timeout; lost for
good, the report of what was recorded, then exit 1); --driver haply speaks the Haply
2DIY's bytes to its emulated board on a pantograph scene.

--driver falcon --firmware FILE closes a delta scene's loop on a Novint Falcon over USB
(pyftdi, pip install 'hapsim[falcon]'): the firmware loaded (the image is yours: hapsim
does not ship Novint's), the legs homed (move the grip in and out), one packet per sample;
--port ftdi://0x0403:0xcb48/1 names a real Falcon (:N the N-th, :SERIAL by serial number);
without --port the emulated Falcon behind an emulated FT232R runs under the same pyftdi
code. It reports the link (replies missing, bytes dropped, readings against the emulated
encoders) and a verdict (ok, degraded); beside it the felt matrices' statement: "not
measurable" where the Falcon's counts are too coarse for the scene (its figures said),
predicted before the loop from the run's own records in lockstep and said on stderr
first (exit 0). Permissions and the udev rule: docs/devices.md."""

#: ``hapsim run --help``: what fits a screen (the rest: ``--help-all``, docs/commands.md).
_SHORT_DESCRIPTION = """\
Run a scene in real time against a force-feedback device (without --port: the embedded
mock behind a pty) and measure the stiffness k and damping b the hand feels, beside what
the analysis predicted for the scene's virtual (K, B); a 2-D or 3-D scene as felt
MATRICES (--driver haply: a Haply 2DIY's bytes). Common options below; every option,
the numbers, faults and drivers: 'hapsim run --help-all' and docs/commands.md."""

_SHORT_EPILOG = """\
examples:
  hapsim run configs/wall.yaml
  hapsim run configs/felt_wall.yaml --lockstep --json
  hapsim run configs/pantograph_wall.yaml --lockstep       2-D: felt matrices
  hapsim run configs/wall.yaml --port /dev/ttyACM0 --telemetry wall.hst
exit codes: 0 ran (or stopped by SIGINT/SIGTERM), 1 refused, safety stop or device
  fault, 2 bad input."""

#: The options ``hapsim run --help`` shows; the others appear with ``--help-all``.
COMMON_OPTIONS = ("--help", "--help-all", "--port", "--duration", "--lockstep", "--rate",
                  "--telemetry", "--driver", "--device", "--amplitude", "--json", "--view")


class _HelpAll(argparse.Action):
    """``--help-all``: the full description, every option and the long epilog, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0,
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        for action in parser._actions:
            if hasattr(action, "full_help"):
                action.help = action.full_help
        parser.description, parser.epilog, parser.usage = parser.full_text
        parser.print_help()
        parser.exit()


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
not measurable, said first: a scene with contacts is predicted with them engaged; before
  the loop starts the closed loop is simulated offline in lockstep (device model and
  engine, the run's samples) and when a contact opens so that no closed stretch of the
  free response is as long as the fit needs, stderr says so with the contact and the
  sample, the run goes on, the report repeats it (measured.stated_before_run) and the
  exit code stays 0 (not a device fault; docs/commands.md, 'Exit codes').
timing: STATE n carries x(nT); FORCE n is computed from x[n], x[n-1] and applied over
  [(n+d)T, (n+d+1)T) by the device's zero-order hold.
safety: host-side force clamp; NaN/inf -> zero force and stop; SIGINT/SIGTERM -> zero
  force, STOP, telemetry flushed, exit 0 (from the numba warm-up on: Ctrl-C during
  start-up ends before the device is armed); an unstable scene is refused unless
  --allow-unstable, which runs it under safety stops (force at the limit in half of the
  last 100 samples, position beyond bounds, non-finite values) that end with zero force
  (a stop on the motion brakes the device to rest first, f = -B v with B = m / 4T, at
  most 0.25 s: loop.brake; docs/reliability.md);
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
  hapsim.host.telemetry.load); with .npz/.csv the journal is FILE.hst until the end.
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
  hapsim run configs/pantograph_wall.yaml --lockstep       2-D: felt matrices, measured = predicted
  hapsim run configs/delta_sphere.yaml                     3-D, the n-axis mock in real time
  hapsim run configs/pantograph_wall.yaml --driver haply   the Haply 2DIY's bytes (emulated board)
  hapsim run configs/delta_sphere.yaml --driver falcon --firmware FILE [--port ftdi://0x0403:0xcb48/1]
  hapsim run configs/wall.yaml --telemetry wall.npz --duration 2
  hapsim run configs/wall.yaml --auto --lockstep      rate and method from 'hapsim advise'
  hapsim run configs/wall.yaml --port /dev/ttyACM0 --baud 2000000
  hapsim run configs/wall.yaml --faults drop=0.01,reset@800 --telemetry wall.hst
  hapsim run configs/wall.yaml --duration 0 --telemetry session.hst   (Ctrl-C ends it)
exit codes:
  0  ran to the end (or stopped by SIGINT/SIGTERM)
  1  refused (unstable loop, unrenderable target), safety stop, latched device fault, device lost beyond
     recovery (or silent with --no-reconnect), a driver's board re-synchronised more than 50 times a
     second of the run (the verdict is then "not measurable", as after a safety stop)
  2  bad arguments, invalid scene, unknown fault name"""


def register(sub) -> None:
    """Add the ``run`` parser to the CLI.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers action of ``hapsim``'s parser; ``run``'s ``func`` is :func:`run`.
    """
    from hapsim.pipeline.options import add_run_arguments
    from hapsim.drivers import FAMILIES
    limits = "\n".join("  " + line for f in FAMILIES if f.dimension == 1
                       for line in f.load().limits.splitlines())
    p = sub.add_parser("run", help="close the THS on a device or the mock and measure the "
                                   "felt stiffness and damping",
                       description=_DESCRIPTION, epilog=_EPILOG.replace("{drivers}", limits),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file with a port and a device")
    # the command's own options (what it does before and after the run), each shown
    # beside the run options it goes with
    def auto(parser):
        parser.add_argument(
            "--auto", action="store_true",
            help="use 'hapsim advise': the lowest rate and cheapest method that keep the "
                 "felt (k, b) within --tolerance (calibrating port links)")
        parser.add_argument(
            "--tolerance", type=Number(float, low=0, open_low=True), default=None,
            metavar="REL",
            help="relative tolerance on the felt (k, b) for --auto (default 0.01; only "
                 "with --auto)")

    def device(parser):
        parser.add_argument(
            "--device", metavar="FILE.yaml",
            help="device section from a file (e.g. written by 'hapsim identify --out'); "
                 "replaces the scene's (said on stderr)")
    # the run's options, each declared once in hapsim.pipeline.options.RunOptions
    add_run_arguments(p, after={"seed": auto, "driver": device})
    p.add_argument("--amplitude", type=declared("run_nd", "amplitude"), metavar="M",
                   help="2-D or 3-D scene: the free responses' amplitude [m] (default "
                        "1e-8; --driver haply: the largest the scene's linear range "
                        "allows; the linearisation bound at the records' motion)")
    p.add_argument("--firmware", metavar="FILE",
                   help="--driver falcon: the Novint firmware image the Falcon loads at "
                        "each power-up (yours: hapsim does not ship it; without --port "
                        "the emulated Falcon takes a stand-in)")
    p.add_argument("--packets", type=Number(int, low=1), metavar="N",
                   help="--driver falcon: packets of the loop, one per sample (default "
                        "1000)")
    p.add_argument("--generation", choices=("gen2", "gen3"),
                   help="--driver haply on a 2-D pantograph scene: the Haply 2DIY's wire "
                        "generation (hAPI hardwareVersion 2 or 3: its motor and encoder "
                        "direction bytes and encoder counts per revolution; default gen3)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--help-all", action=_HelpAll,
                   help="every option, what the report's numbers mean, faults, drivers")
    _shorten_help(p)
    p.set_defaults(func=run)


def _shorten_help(p: argparse.ArgumentParser) -> None:
    """Make ``hapsim run --help`` fit a screen (issue 31: it was 247 lines): the short
    description and examples, the options of :data:`COMMON_OPTIONS` only; ``--help-all``
    puts back the full text (kept on the parser) and every option's help."""
    p.full_text = (p.description, p.epilog, None)
    p.description, p.epilog = _SHORT_DESCRIPTION, _SHORT_EPILOG
    p.usage = "hapsim run [options] SCENE   (every option: hapsim run --help-all)"
    for action in p._actions:
        if action.option_strings and not set(action.option_strings) & set(COMMON_OPTIONS):
            action.full_help = action.help
            action.help = argparse.SUPPRESS


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
        What :func:`hapsim.drivers.protocol_of` says (``"the framed protocol"``, ``"the firefader
        protocol (the scene's device.protocol)"``, ...).
    note : str
        Appended (which host loop runs, when it is not the one asked for).
    """
    length = f"{n_samples} samples" if n_samples else "an open-ended run"
    print(f"hapsim run: closing the loop on {port or 'the in-process mock'} in {protocol} "
          f"for {length} (SIGINT/SIGTERM stop cleanly){note}",
          file=sys.stderr, flush=True)


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
    from hapsim.scene import scene_dimension, scene_has_ports
    if scene_has_ports(args.scene):            # several ports: in lockstep, in-process
        return run_ports(args)
    if scene_dimension(args.scene) > 1:        # a 2-D or 3-D scene: in lockstep, in-process
        return run_nd(args)
    if getattr(args, "amplitude", None) is not None:
        raise ConfigError("takes 2-D or 3-D scenes; a 1-D scene's excitation is its "
                          "excitation section", key="--amplitude")
    _refuse_family_options(args, None)
    if args.tolerance is not None and not args.auto:
        # (before: taken and ignored, the run's verdict not changed by it)
        raise ConfigError("goes with --auto (the felt (k, b) tolerance the rate it chooses "
                          "keeps); a run's verdict states its own uncertainty", key="--tolerance")

    from hapsim.pipeline.options import RunOptions
    opts = RunOptions.from_args(args)       # each option checked (exit 2) before loading
    scene = load_scene(args.scene)
    if getattr(args, "device", None):
        scene = _replace_device(scene, args.device)
    from hapsim.pipeline import startup
    # an empty numba cache: say what is compiled (once the scene is read: a bad scene gets
    # its one-line error alone) before the silence it costs
    startup.reset_announcements()
    startup.announce_compilation(startup.run_compile_parts(scene, compiled_loop=False),
                                 scene=scene)
    advice = None
    if args.auto:
        from hapsim.bench.advise import advise_scene
        from hapsim.errors import UnstableConfigError
        if opts.rate_hz is not None:
            raise ConfigError("--auto chooses the rate; drop --rate or --auto", key="--auto")
        tolerance = 0.01 if args.tolerance is None else args.tolerance
        advice = advise_scene(scene, tolerance)
        if not advice.ok:
            raise UnstableConfigError(f"{scene.path}: no rate and method keep what is felt "
                                      f"within {tolerance:g}: {advice.reason}")
        scene = advice.apply(scene)
        print(f"hapsim run --auto: {advice.rate_hz:g} Hz, integrator {advice.integrator}: "
              f"{advice.reason}", file=sys.stderr, flush=True)
    protocol, said = protocol_of(scene, opts.driver)
    if opts.view is not None:           # said before anything starts: how to install it
        from hapsim.view.server import require_websockets
        require_websockets()
    note = ""
    # an empty numba cache: say what is compiled before the silence it costs, and compile
    # only what this run needs (--loop auto: the compiled loop after the report)
    possible = startup.compiled_loop_possible(scene, framed=protocol == DEFAULT,
                                              osc=opts.osc if opts.view is None else opts.view,
                                              sound=opts.sound,
                                              host_clocked=opts.host_clocked)
    asked = loop = opts.loop
    if asked == "auto":     # a run that cannot use the compiled loop reports why it did not
        loop = startup.choose_loop(asked, scene) if possible else "compiled"
    compile_later = asked == "auto" and loop == "python"
    startup.announce_compilation(startup.run_compile_parts(
        scene, compiled_loop=loop == "compiled" and possible), scene=scene)
    if compile_later:           # said when the loop starts (not before an input error)
        note = ("; the Python host loop this time (the compiled one is not in numba's cache "
                "yet: it is compiled after the report, for the next runs)")
    embedded = None
    if opts.port is None and protocol == DEFAULT:
        # the mock's child starts now, beside the imports and the warm-up that follow
        from hapsim.pipeline.startup import start_embedded_mock
        embedded = start_embedded_mock(scene, rate_hz=opts.rate_hz, lockstep=opts.lockstep,
                                       seed=opts.seed, faults=opts.faults,
                                       fault_seed=opts.fault_seed,
                                       rt_priority=0 if opts.lockstep and not opts.host_clocked
                                       else max(opts.rt_priority, 0))
    from hapsim import api
    # the run itself is the API's (hapsim.api.run): the command announces, then prints
    report = api.run(scene, dataclasses.replace(
        opts, driver=protocol, loop=loop, handle_signals=True, embedded=embedded,
        on_start=lambda port, n: _announce(port, n, said, note),
        on_precheck=lambda s: print(f"hapsim run: {scene.path}: {s}; the run goes on "
                                    f"(exit code 0: not a device fault)",
                                    file=sys.stderr, flush=True)))
    if advice is not None:
        report = report.replace(advice=advice.to_dict())  # keeps exit_code
    print(json.dumps(report.to_dict()) if args.json else report.text())
    sys.stdout.flush()
    if args.json:                       # the human report says them in its text
        for w in report.loop.get("warnings") or []:
            print(f"hapsim run: warning: {w}", file=sys.stderr, flush=True)
    if report.error is not None:        # the report first, then why the run ended
        print(f"hapsim run: {report.error['type']}: {report.error['message']}",
              file=sys.stderr, flush=True)
    stopped = str(report.loop.get("stop_reason") or "").startswith("signal")
    if compile_later and report.error is None and not stopped:     # not after a Ctrl-C
        _compile_loop_for_next_runs(scene)
    return report.exit_code


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
        from hapsim.host.fastloop import warm_up
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


#: ``hapsim run``'s own options (not run options) an n-D scene does not take.
_REFUSED_ND = (("device", "--device"), ("auto", "--auto"), ("tolerance", "--tolerance"))


def _refuse_options_nd(args):
    """Refuse ``hapsim run``'s own options an n-D run does not take, then every run option
    it does not take (:func:`hapsim.pipeline.felt_run.refuse_options`), by its flag.

    Returns
    -------
    hapsim.pipeline.options.RunOptions
        The run options of the command line, checked one by one.
    """
    from hapsim.pipeline.felt_run import refuse_options
    from hapsim.pipeline.options import RunOptions
    for attr, flag in _REFUSED_ND:
        if getattr(args, attr, None) is not None and getattr(args, attr) is not False:
            raise ConfigError(f"a 2-D or 3-D scene does not take {flag} yet (1-D scenes "
                              "only)", key=flag)
    opts = RunOptions.from_args(args)
    refuse_options(opts)
    return opts


def _refuse_family_options(args, fam) -> None:
    """Refuse the options of a registered family (``--firmware``: the Falcon's) given to a
    run of another (``fam``; None: the host loop's).

    Raises
    ------
    ConfigError
        Such an option, by its flag, with the family it goes with.
    """
    from hapsim.drivers import FAMILIES
    for f in FAMILIES:
        for flag in f.options:
            if f is not fam and getattr(args, flag[2:], None) is not None:
                raise ConfigError(f"goes with --driver {f.name} ({f.device})", key=flag)


def run_nd(args) -> int:
    """Measure an n-D scene's felt matrices (``dimension: 2`` or ``3``).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``lockstep``, ``port``, ``amplitude`` [m] (None: 1e-8), ``json``, and
        run's other options (refused when set).

    Returns
    -------
    int
        0 when the loop is stable (the measurement then reported, whatever it finds);
        1 after a safety stop or a device lost for good (the report printed first, then
        the error on stderr).

    Raises
    ------
    ConfigError
        An option the n-D run does not take; a bad amplitude or scene (file, line, key).
    UnstableConfigError
        The check finds the loop unstable and ``--allow-unstable`` is not given (exit 1).
    DeviceError, ProtocolError
        The device failed before its first record: no HELLO, a wrong one, a FAULT
        (exit 1, cli's error line and ``--json`` error object).

    Notes
    -----
    In-process (``--lockstep`` without ``--port``):
    :func:`hapsim.lockstep.measure_felt_lockstep`: 2n free responses of the loop
    (engine, exact ZOH device of the Cartesian mass at rest, delay line) from the handle
    displaced by ``a`` along each axis and moving along each, minus the response from
    rest. Over a port: :func:`hapsim.pipeline.felt_port.measure_felt_port`, the same records
    from the device's hand, each a CONFIG, with the late ticks' known disturbance
    subtracted. Then the felt matrices by vector linear prediction and the inverse
    quadratic eigenvalue problem (:func:`hapsim.analysis.pencil.fit_felt_nd`), against
    :func:`hapsim.analysis.scene_check.check_scene_nd`; the linearisation bound of
    :mod:`hapsim.analysis.linearisation` at ``a``.
    """
    from hapsim.progress import Progress
    opts = _refuse_options_nd(args)
    driver = getattr(args, "driver", None)
    if driver is not None:          # a device whose run is its own: the registry's route
        from hapsim.drivers import family
        fam = family(driver, dimension=2)
        _refuse_family_options(args, fam)
        return fam.runner()(args)
    _refuse_family_options(args, None)
    from hapsim.pipeline.felt_run import measure_scene_nd, scene_for_run
    a, scene = scene_for_run(args.scene, getattr(args, "amplitude", None),
                             getattr(args, "rate_hz", None))
    from hapsim.api import stable_prediction_nd
    stable_prediction_nd(scene, args.allow_unstable, "--allow-unstable")
    n = scene.dimension
    in_process = args.lockstep and not args.port
    label = "run (lockstep)" if in_process else "run (over the port)"
    # (a device that fails before its first record raises: exit 1, cli's error line)
    with Progress(2 * n if in_process else 2 * n + 1, label, unit="records") as bar:
        res, port_info = measure_scene_nd(scene, opts, a, progress=bar.update)
    code = _report_nd(args, scene, a, res, in_process, port_info)
    from hapsim.outputs import say_error_after
    say_error_after("run", res.get("error"))    # the report first, then why it ended
    return code


def _report_nd(args, scene, a: float, res: dict, in_process: bool, port_info) -> int:
    """Print an n-D run's report (text, or ``--json``); return its exit code: 1 after a
    safety stop or a device lost for good, as the 1-D run's (docs/commands.md, 'Exit
    codes'), else 0."""
    n = scene.dimension
    where = "in-process" if in_process else (
        f"over {port_info['port']}" + (" (embedded mock, real time)"
                                       if port_info["embedded"] else ""))
    fit, chk, dev, bound = res["measured"], res["predicted"], res["deviation"], res["bound"]
    from hapsim.api import run_report_nd
    rep = run_report_nd(scene, res, in_process, port_info)
    code = rep.exit_code                # (its rule: hapsim.api.running.run_report_nd)
    if args.json:
        print(json.dumps(rep.to_dict()))
        return code
    o = sys.stdout
    if in_process:
        print(f"{scene.path}: {n}-D scene in lockstep at {scene.rate_hz:g} Hz, in-process "
              f"(engine, exact ZOH device of the Cartesian mass at rest, delay "
              f"{scene.device.delay})", file=o)
    else:
        print(f"{scene.path}: {n}-D scene {where}, {n} axes on the framed protocol "
              f"(device delay {res['delay'][0] if res['delay'] else 'unknown'} ticks from "
              "seq - force_seq)", file=o)
        c = res["counts"]
        print(f"  late ticks: {res['late']} of {sum(res['rows'])} rows used "
              f"(watchdog {res['watchdog']}), their known disturbance's response "
              f"subtracted per axis; host scheduling: {port_info['scheduling']}", file=o)
        print(f"  rows used per start (rest first): {res['rows']} of {res['samples']}; "
              f"CONFIGs {c['configs']}, records cut short at a lost STATE {c['cut']} "
              f"(STATEs missed {c['missed']}, duplicates {c['stale']}, reordered "
              f"{c['reordered']}, bad frames {res['bad_frames']}), device resets "
              f"{c['resets']}, device lost {c['lost']} / recovered {c['recovered']}"
              + (f"; faults injected: {port_info['faults_injected']}"
                 if port_info.get("faults_injected") else ""), file=o)
        if res.get("stop", "end") != "end":
            print(f"  stopped: {res['stop']} (what was recorded by then is reported)",
                  file=o)
        brake = (res.get("safety") or {}).get("brake")
        if brake is not None:
            from hapsim.braking import brake_text
            print(f"  {brake_text(brake)}", file=o)
    print(f"  excitation: {res['records']} free responses of {res['samples']} samples, "
          f"amplitude a = {a:g} m (minus the response from rest)", file=o)
    if not chk.stable:
        grow = chk.render.spectral_radius ** res["samples"]
        print(f"  the loop is UNSTABLE (--allow-unstable): its free responses grow by up to "
              f"{grow:.3g} times over a record, so the amplitude and the bound below hold "
              "at its start only", file=o)

    def mat(name, m, unit):
        if m is None:
            why = ("not measured: see the verdict" if res.get("incomplete")
                   else f"fewer than {n} rendered pairs")
            print(f"  {name}: none ({why})", file=o)
            return
        print(f"  {name} [{unit}]", file=o)
        for row in m:
            print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
    mat("predicted felt stiffness k", chk.render.felt_stiffness, "N/m")
    mat("measured felt stiffness k", fit["felt_stiffness"], "N/m")
    mat("predicted felt damping b", chk.render.felt_damping, "N s/m")
    mat("measured felt damping b", fit["felt_damping"], "N s/m")
    if dev is not None:
        print(f"  measured - predicted (largest entry over the largest predicted): "
              f"k {dev['felt_stiffness']:.2e}, b {dev['felt_damping']:.2e}", file=o)
    bd = bound.to_dict()
    print(f"  linearisation bound at the records' largest excursion {bound.amplitude:.3g} m "
          f"(first order in it; hapsim.analysis.linearisation):", file=o)
    print(f"    device kinematics c_kin = {bound.kinematic:.4g} /m (the Cartesian mass "
          "and the velocity-product terms over a; "
          + ("not in the lockstep device, which holds the mass at rest)" if in_process
             else "carried by a joint-space device, the mock's or a real one)"), file=o)
    print(f"    Euclidean links c_link = {bound.link:.4g} /m"
          + (f" (link {bound.link_name!r})" if bound.link_name else " (none: linear)"),
          file=o)
    if bd["felt_stiffness"] is None:
        print(f"    the excursion reaches the depth of {bound.depth_name!r} "
              f"({bound.depth:.3g} m): "
              "the contact opens, no linear estimate holds", file=o)
    else:
        print(f"    felt stiffness within {bd['felt_stiffness']:.2e}, felt damping within "
              f"{bd['felt_damping']:.2e} (relative) while the excursion < {bound.depth:.3g} m"
              + (f" (depth of {bound.depth_name!r})" if bound.depth_name else ""), file=o)
    from hapsim.pipeline.felt_port import verdict_nd
    v = verdict_nd(res)
    wire = res.get("wire")
    if wire is not None:
        dq = wire["reading_bound_rad"]
        print(f"  device: {port_info.get('device')}", file=o)
        print(f"  the wire's rounding (joint readings within {dq[0]:.2e} / {dq[1]:.2e} rad: "
              f"half a count and a binary32 ulp; torques within {wire['torque_bound_nm']:.2e} "
              "N m: half a PWM step), first-order worst case through the loop and the fit: "
              f"k {wire['felt_stiffness']:.2e}, b {wire['felt_damping']:.2e}; one count at "
              f"the handle {wire['quantum_m']:.2e} m", file=o)
    from hapsim.pipeline.felt_run import print_statements
    print_statements(v, o)
    print(f"  verdict: {v['verdict']}: {v['reason']}", file=o)
    return code


def run_ports(args) -> int:
    """Measure the felt matrices across the ports of a scene with several ports, in
    lockstep (:func:`hapsim.api.running.run_scene_ports`: each port its own device model)
    or, for the FireFader's two faders, in real time
    (:func:`hapsim.pipeline.faders_run.run_faders`).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``lockstep``, ``amplitude`` [m] (None: 1e-8 in lockstep, 4e-3 in real
        time), ``json``, ``allow_unstable`` (in real time also ``port``, ``driver``,
        ``rt_priority``); run's other options refused by flag.

    Returns
    -------
    int
        0 when the loop is stable (the measurement reported, whatever it finds); 1 after
        a safety stop or the board lost in the middle of the run (the report first, then
        the error on stderr).

    Raises
    ------
    ConfigError
        In real time, ports that are not the FireFader's two faders (several boards,
        other protocols); another option a run of several ports does not take, a bad
        amplitude or scene (file, line, key).
    UnstableConfigError
        The coupled loop is unstable without ``--allow-unstable`` (exit 1).
    """
    from hapsim.api.running import run_scene_ports
    from hapsim.pipeline.options import RunOptions
    from hapsim.scene import load_scene_ports
    for attr, flag in _REFUSED_ND:
        if getattr(args, attr, None) is not None and getattr(args, attr) is not False:
            raise ConfigError(f"a scene with several ports does not take {flag} yet",
                              key=flag)
    opts = dataclasses.replace(RunOptions.from_args(args), on_precheck=lambda s: print(
        f"hapsim run: {args.scene}: {s}; the run goes on (exit code 0: not a device fault)",
        file=sys.stderr, flush=True))
    scene = load_scene_ports(args.scene)
    rep = run_scene_ports(scene, opts, getattr(args, "amplitude", None), by="flag")
    code = _report_ports(args, scene, rep)
    from hapsim.outputs import say_error_after
    say_error_after("run", rep.error)   # the report first, then why the run ended
    return code


def _report_ports(args, scene, rep) -> int:
    """Print a run of several ports' report (text, or ``--json``); return its exit code
    (1 after a safety stop or a board lost, else 0: ``rep.exit_code``)."""
    code = getattr(rep, "exit_code", 0)
    if args.json:
        print(json.dumps(rep.to_dict()))
        return code
    o = sys.stdout
    x = rep.extra
    rt = x.get("realtime")
    how = (f"in lockstep at {scene.rate_hz:g} Hz, in-process, each port its own device"
           if rt is None else
           f"in real time at {scene.rate_hz:g} Hz over {rt['port']}, one board for both")
    print(f"{scene.path}: {len(x['ports'])} ports ({', '.join(x['ports'])}) {how} (delays "
          f"{', '.join(f'{d:g}' for d in x['delays'])})", file=o)
    if rt is not None:
        print(f"  loop: stop {rt['stop']}; writes off by more than half a period per "
              f"record {rt['late_ticks']} (latest {rt['latest'] * 1e3:.1f} ms); rows used "
              f"{rt['usable']}; force left on the faders {rt['held_at_end']} N", file=o)
    print(f"  excitation: {rep.records} free responses of {rep.samples} samples, amplitude "
          f"a = {rep.linearisation_bound['amplitude']:g} m (minus the response from rest)",
          file=o)
    for name, m, unit in (("predicted felt stiffness k", rep.predicted["felt_stiffness"],
                           "N/m"),
                          ("measured felt stiffness k", rep.measured["felt_stiffness"], "N/m"),
                          ("predicted felt damping b", rep.predicted["felt_damping"], "N s/m"),
                          ("measured felt damping b", rep.measured["felt_damping"], "N s/m")):
        print(f"  {name} [{unit}]" + ("" if m is not None else ": none"), file=o)
        for row in (m or ()):
            print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
    if rep.deviation is not None:
        print(f"  measured - predicted (largest entry over the largest predicted): "
              f"k {rep.deviation['felt_stiffness']:.2e}, b {rep.deviation['felt_damping']:.2e}"
              f" (round-off allowed {rep.linearisation_bound['roundoff']:.2e}: a linear "
              "loop)", file=o)
    if rt is not None:
        from hapsim.pipeline.felt_run import print_statements
        print_statements(rep.to_dict(), o)
    print(f"  verdict: {rep.verdict}: {rep.reason}", file=o)
    return code

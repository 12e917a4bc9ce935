"""``hapsim mock``: a mock force-feedback device on a new pseudo-terminal, for a scene of any
dimension (a 1-D scene's device, the Hapkit firmware on an emulated board, or a 2-D or
3-D scene's device: :class:`hapsim.emulated.mock.MockDeviceND`)."""

from __future__ import annotations

import argparse
import json
import math
import os
import pty
import sys
import threading
import tty

from hapsim.errors import ConfigError
from hapsim.option_values import Number


def register(sub) -> None:
    """Add the ``mock`` parser to the CLI.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers action of ``hapsim``'s parser; ``mock``'s ``func`` is :func:`run`.
    """
    p = sub.add_parser(
        "mock", help="serve a mock device (exact THS physics) on a new pseudo-terminal",
        description=(
            "Start a mock 1-DoF force-feedback device on a new pseudo-terminal and print its "
            "path as the first line of stdout ('PORT /dev/pts/N'). The mock speaks the "
            "framed protocol exactly like hardware (HELLO, CONFIG, STATE every tick, FORCE, "
            "PING/PONG, watchdog, force clamp, STOP) and integrates m x'' + b0 x' = f "
            "exactly over each period with the force held (zero-order hold), applying the "
            "FORCE answering STATE n at tick n + d. Its device and excitation come from the "
            "scene's 'device' and 'excitation' sections (default: the device of "
            "configs/wall.yaml, m = 0.1 kg, b0 = 0.5 N s/m, d = 1, 10 N, with x0 = 5 mm). "
            "It serves host after host until SIGINT/SIGTERM (Ctrl-C): a run that ends "
            "(STOP), is killed, or closes and reopens the port leaves it disarmed with zero "
            "force, waiting for the next run on the same PORT. --once restores the one-run "
            "device that exits at the first STOP. A 2-D or 3-D scene (dimension: 2 or 3) "
            "serves its device with n axes (HELLO n_axes = n, the joint-space dynamics of "
            "a pantograph or delta) and a hand that starts each CONFIG from the next "
            "identification start (--amplitude); see docs/dimensions.md. A scene whose "
            "device speaks a driver's protocol (device.protocol: firefader, haply, "
            "hapkit-serial), or the FireFader's two faders (devices:), serves that "
            "board's emulation instead, on its own wall clock (docs/devices.md)."),
        epilog=(
            "modes:\n"
            "  real-time (default)  ticks on the monotonic clock at the host's CONFIG rate;\n"
            "                       a late FORCE leaves the last force held (counted)\n"
            "  --lockstep           one period per FORCE: deterministic, any host speed\n"
            "example (two terminals):\n"
            "  $ hapsim mock --scene configs/wall.yaml\n"
            "  PORT /dev/pts/7\n"
            "  $ hapsim run configs/wall.yaml --port /dev/pts/7     # again and again\n"
            "faults (--faults SPEC, seeded by --fault-seed N; see hapsim.emulated.faults):\n"
            "  NAME=RATE[:DUR]   at random, probability per frame sent (drop, corrupt,\n"
            "                    garbage, dup, reorder, spike), per frame received from the\n"
            "                    host (the same prefixed rx.: rx.drop, rx.corrupt,\n"
            "                    rx.garbage, rx.dup, rx.reorder, rx.spike) or per tick\n"
            "                    (stall, reset, vanish)\n"
            "  NAME@TICK[:DUR]   once at device tick TICK; nohello: never answer HELLO\n"
            "  DUR: 5ms, 300us, 0.2s (spike 5 ms, stall 200 ms, vanish 300 ms by default)\n"
            "  e.g. drop=0.01,corrupt=0.005,garbage=0.001,dup=0.002,reorder=0.002,\n"
            "       spike=0.001:5ms,stall@500:200ms,reset@800,vanish@1200:300ms,\n"
            "       rx.drop=0.01,rx.corrupt=0.005\n"
            "  a bad host frame is dropped and counted (report: decoder); a missing FORCE\n"
            "  leaves the last force held (late), the watchdog zeroes it; a FORCE whose\n"
            "  tick has passed (duplicated, reordered, delayed) is ignored (stale)\n"
            "  vanish closes the pty and opens a new one: give --link PATH (a symbolic link\n"
            "  kept pointing at the current pty) and open PATH from the host. With faults,\n"
            "  STOP does not end the mock (a host sends STOP when it loses the device).\n"
            "the real firmware (--firmware):\n"
            "  builds (make: avr-gcc, host cc on libsimavr) what is missing, then runs the\n"
            "  Hapkit 3 reference firmware (firmware_protocol/firmware/hapkit) cycle by cycle\n"
            "  on simavr's ATmega328P with the scene's device as the handle's physics (m, b0,\n"
            "  Coulomb; the hand lets go at x0, v0 at CONFIG and brings it back at STOP)\n"
            "  and prints\n"
            "  'PORT /dev/pts/N'; real-time by default, --lockstep: as fast as the host\n"
            "  answers (the emulated clock waits for each FORCE); on exit it writes --report\n"
            "  (JSON: MCU cycles per tick, force on the pin, frames) or prints it\n"
            "  $ hapsim mock --firmware --scene configs/hapkit.yaml\n"
            "  on a 2-D pantograph scene, --firmware runs the Hapkit pantograph's firmware\n"
            "  on two emulated ATmega328P joined on a TWI bus (docs/pantograph.md), real-time\n"
            "  by default as well, or --lockstep\n"
            "  $ hapsim mock --firmware --scene configs/pantograph_wall.yaml\n"
            "exit codes: 0 stopped by a signal (or, with --once, by STOP); 1 the firmware\n"
            "stopped or could not be built; 2 bad arguments, scene or SPEC."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", metavar="SCENE", help="scene whose device/excitation to model")
    p.add_argument("--lockstep", action="store_true",
                   help="advance one period per FORCE instead of on the clock")
    p.add_argument("--rate", type=Number(float, low=0, open_low=True, unit="Hz"), metavar="HZ",
                   help="native rate announced in HELLO [Hz] (default: the scene's)")
    # --seed, --fault-seed: None when not given (a 2-D/3-D scene's mock refuses them by
    # name); the 1-D mock reads None as 0
    p.add_argument("--seed", type=Number(int, low=0), default=None,
                   help="sensor-noise seed (default 0)")
    p.add_argument("--report", metavar="FILE",
                   help="write what the mock saw (ticks, late, last force, STOP) as JSON on exit")
    p.add_argument("--faults", metavar="SPEC",
                   help="inject seeded faults (see below), e.g. drop=0.01,reset@800")
    p.add_argument("--fault-seed", type=Number(int, low=0), default=None, metavar="N",
                   help="seed of the fault generator (default 0)")
    p.add_argument("--rt-priority", type=Number(int, low=0, high=99), default=None, metavar="N",
                   help="SCHED_FIFO priority of the mock where the OS permits it (default "
                        "in real time 11, one above a run's: a board is a processor of its "
                        "own, no host deschedules it; --firmware 10; --lockstep 0, normal "
                        "scheduling; 1..99). Embedded in 'hapsim run', the mock inherits "
                        "the run's policy instead")
    p.add_argument("--once", action="store_true",
                   help="serve one run only: exit at the host's STOP (without faults) or when "
                        "it closes the port (default: serve run after run until a signal)")
    p.add_argument("--link", metavar="PATH",
                   help="keep a symbolic link PATH to the current pty (needed by vanish)")
    p.add_argument("--firmware", action="store_true",
                   help="run the Hapkit 3 reference firmware on the emulated board (simavr) "
                        "instead of the Python mock (default scene: configs/hapkit.yaml)")
    p.add_argument("--trace", metavar="FILE",
                   help="--firmware: the emulated board writes its event trace to FILE on exit "
                        "(ticks, STATEs, FORCEs read and fed, waits; emulated cycle and "
                        "CLOCK_MONOTONIC; tools/bench_firmware.py reads it)")
    p.add_argument("--spin-us", type=Number(float, low=0, high=1000, unit="us"), default=None,
                   metavar="US",
                   help="--firmware in real time: the longest spin per tick [us] while the "
                        "board waits for the host's FORCE (default 0: none; costs up to US "
                        "us of CPU per tick, and at SCHED_FIFO on a busy machine keeps the "
                        "host off that core)")
    p.add_argument("--tick", choices=("auto", "compiled", "python"), default="auto",
                   help="'auto' (default): 'compiled' above 2 kHz, 'python' at and below "
                        "(2-D/3-D scenes: always 'python'). "
                        "(loading the compiled tick delays the HELLO by 0.5-1 s). "
                        "Real-time ticks in numba ('compiled': same bytes as the "
                        "Python mock, no GIL, sleeps on absolute deadlines; lockstep, faults, "
                        "sensor noise and a compliant grip stay in Python) or in Python "
                        "('python', the reference)")
    p.add_argument("--amplitude", type=Number(float, low=0, open_low=True, unit="m"), metavar="M",
                   help="2-D/3-D scenes: the hand's amplitude a [m] (default 1e-8): at each "
                        "CONFIG it lets the handle go from the next identification start "
                        "(rest, displaced by a along each axis, moving at a/(10 T) along each)")
    p.add_argument("--fd", type=Number(int, low=0),
                   help=argparse.SUPPRESS)    # embedded: pty master fd
    p.add_argument("--spec", help=argparse.SUPPRESS)            # embedded: device JSON
    # the n-D mock and the emulated pantograph refuse the options they do not take: one at
    # its default was not given (argparse's public get_default, read at run time)
    p.set_defaults(func=run, option_default=p.get_default)


def _from_spec(text: str):
    from hapsim.scene import device_from_dict, excitation_from_dict
    spec = json.loads(text)
    return (device_from_dict(spec["device"]), excitation_from_dict(spec["excitation"]),
            spec.get("base_dir"))


def _new_pty(link: str | None, announce: bool) -> tuple[int, int]:
    """A raw pty (master, slave); points ``link`` at it atomically; prints ``PORT``."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    if link:
        tmp = f"{link}.new"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(name, tmp)
        os.replace(tmp, link)
    if announce:
        print(f"PORT {link or name}", flush=True)
    return master, slave


def run(args) -> int:
    """Run ``hapsim mock``: serve a mock device on a new pty (or, embedded in ``hapsim run``,
    on the pty master ``--fd``) until STOP, SIGINT/SIGTERM or the host closing the port.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options of :func:`register` (``scene``, ``lockstep``, ``rate``, ``seed``,
        ``report``, ``faults``, ``fault_seed``, ``rt_priority``, ``once``, ``link``, ``fd``,
        ``spec``).

    Returns
    -------
    int
        0 (the exit code).

    Raises
    ------
    ConfigError
        Bad ``--rt-priority``, ``--rate`` or ``--faults``, a ``vanish`` fault without
        ``--link``, ``--trace`` or ``--spin-us`` without ``--firmware``, or a scene without
        a device section (exit 2 from :func:`hapsim.cli.main`).
    """
    if getattr(args, "report", None):         # (before serving: it failed at the exit, and
        from hapsim.outputs import check_writable      # /dev/full was replaced by a file)
        check_writable(args.report, "--report")
    if args.scene and args.fd is None and args.spec is None:
        from hapsim.scene import scene_dimension
        if scene_dimension(args.scene) == 1:
            # a device that speaks a driver's protocol (the FireFader, a Haply, a Hapkit
            # sketch), or the FireFader's two faders: its emulated board
            from hapsim.commands.mock_board import board_protocol, run_board_mock
            if board_protocol(args.scene) is not None:
                return run_board_mock(args, _new_pty, _given)
    if args.rt_priority is None:
        # a board is a processor of its own, which no host loop deschedules: the Python
        # mock in real time one above a run's default, as a driver's board
        # (hapsim.commands.mock_board.BOARD_RT_PRIORITY); starved at normal scheduling
        # beside busy processes it held its force for tens of ms, which no board does
        # (an identification passed its envelope by 0.015 mm at load ~5)
        # (embedded in hapsim run, --fd, no flag means the run's own 0: inherited)
        from hapsim.commands.mock_board import BOARD_RT_PRIORITY
        args.rt_priority = (0 if args.lockstep or args.fd is not None else
                            10 if args.firmware else BOARD_RT_PRIORITY)
    if args.scene:
        from hapsim.scene import scene_dimension
        if scene_dimension(args.scene) > 1:         # a 2-D or 3-D scene's device (it
            # refuses by name what it does not take: --firmware, --fd, --seed, ...)
            return run_mock_nd(args, _new_pty)
    if getattr(args, "amplitude", None) is not None:
        raise ConfigError("--amplitude is the hand of a 2-D or 3-D scene's mock (the 1-D "
                          "mock takes its excitation from the scene)", key="--amplitude")
    if args.seed is None:
        args.seed = 0
    _fault_seed_alone(args)
    if args.fault_seed is None:
        args.fault_seed = 0
    if args.firmware:
        return _run_firmware(args)
    for flag, given in (("--trace", getattr(args, "trace", None)),
                        ("--spin-us", getattr(args, "spin_us", None))):
        if given:
            raise ConfigError("is an option of the emulated board (--firmware)", key=flag)
    from hapsim.emulated.faults import mock_fault_plan, reopener
    from hapsim.emulated.mock import DEFAULT_DEVICE, DEFAULT_EXCITATION, MockDevice
    from hapsim.emulated.serve import serve_fd
    from hapsim.host.realtime import RealtimePriority

    rt = RealtimePriority(args.rt_priority)       # ConfigError (exit 2) when out of range
    plan = mock_fault_plan(args.faults, args.fault_seed, args.link, args.lockstep)
    reopen = reopener(args.link, _new_pty, announce=args.fd is None)

    rate = 1000.0
    if args.spec:
        device, excitation, base_dir = _from_spec(args.spec)
    elif args.scene:
        from hapsim.scene import load_scene
        scene = load_scene(args.scene)
        if scene.device is None:
            raise ConfigError("the scene has no device section", file=scene.path, key="device")
        device, excitation = scene.device, scene.excitation
        base_dir = os.path.dirname(os.path.abspath(args.scene))
        rate = scene.rate_hz
    else:
        device, excitation, base_dir = DEFAULT_DEVICE, DEFAULT_EXCITATION, None
    if args.rate is not None:
        rate = args.rate
    mock = MockDevice(device, excitation, native_rate_hz=rate, lockstep=args.lockstep,
                      seed=args.seed, base_dir=base_dir)
    if args.fd is not None:
        # embedded in hapsim run: the host owns the terminal; end on EOF/EIO or SIGTERM
        import signal

        from hapsim.spawn import StopFlag
        flag = StopFlag()
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, lambda signum, frame: flag.request(signum))
        # the host sends STOP when it loses the device and then reconnects: the embedded
        # mock ends when the host closes the port (EIO), not on STOP
        from hapsim.emulated.serve import AUTO_COMPILED_HZ
        compiled = args.tick == "compiled" or (args.tick == "auto"
                                               and mock.native_rate_hz > AUTO_COMPILED_HZ)
        if compiled and not args.lockstep and plan is None:
            # numba's loading (hundreds of ms of CPU) before SCHED_FIFO, not under it: a
            # real-time start-up starves every other real-time loop of the machine
            try:
                from hapsim.emulated.serve import warm_up_mock
                from hapsim.pipeline.startup import preload_numba_blas
                preload_numba_blas()
                warm_up_mock()
            except Exception:  # noqa: BLE001 - serve_fd says why and ticks in Python
                pass
        with rt:
            # no HELLO before asked: the host opens the port after this child started,
            # and pyserial's open flushes what is waiting (half a HELLO: a bad frame)
            serve_fd(args.fd, mock, exit_on_stop=False, report_path=args.report, flag=flag,
                     handle_signals=False, plan=plan, reopen=reopen, tick=args.tick,
                     hello=False)
        return 0
    import sys
    master, slave = _new_pty(args.link, announce=True)
    persistent = not getattr(args, "once", False)
    if persistent:
        # the raw settings stay with the pty; with no slave fd of its own the mock sees
        # EIO when a host closes the port (or dies), and then waits for the next one
        os.close(slave)
        slave = None

    served = []

    def host_gone(stats: dict) -> None:
        if stats["ticks"] or stats["saw_stop"]:
            served.append(stats["ticks"])
            how = "after STOP" if stats["saw_stop"] else "without STOP (force zeroed)"
            print(f"hapsim mock: host left {how} ({stats['ticks']} ticks since its last "
                  "CONFIG); waiting for the next run (Ctrl-C ends the mock)",
                  file=sys.stderr, flush=True)

    try:
        with rt:
            if args.rt_priority and not rt.active:
                print(f"hapsim mock: scheduling {rt.note}", file=sys.stderr, flush=True)
            report = serve_fd(master, mock, exit_on_stop=not persistent,
                              report_path=args.report, plan=plan, reopen=reopen,
                              persistent=persistent, on_host_gone=host_gone,
                              tick=args.tick)
        if persistent:
            print(f"hapsim mock: stopped ({report['end']}); {len(served)} host(s) served "
                  f"and gone", file=sys.stderr, flush=True)
    finally:
        for fd in (master, slave):
            try:
                if fd is not None:
                    os.close(fd)
            except OSError:
                pass
    return 0


def _run_firmware(args) -> int:
    """``hapsim mock --firmware``: build what is missing and become the emulated board.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options (``scene``, ``lockstep``, ``report``, ``link``; the Python mock's
        ``faults``, ``rate``, ``fd``, ``spec`` do not apply).

    Returns
    -------
    int
        Does not return on success (the process becomes ``hapkit_board``, which prints
        ``PORT /dev/pts/N``); 1 when the board cannot be built.

    Raises
    ------
    ConfigError
        An option of the Python mock given with --firmware, or a scene without a device.
    """
    import sys

    from hapsim.emulated import hapkit_board as board
    from hapsim.errors import DeviceError
    from hapsim.scene import load_scene

    for name, flag in (("faults", "--faults"), ("rate", "--rate"), ("fd", "--fd"),
                       ("spec", "--spec")):
        if getattr(args, name, None) is not None:
            raise ConfigError("does not apply to --firmware (the firmware takes its rate from "
                              "CONFIG and has no fault injection)", key=flag)
    path = args.scene or board.shipped_scene("hapkit.yaml")
    scene = load_scene(path)
    if scene.device is None:
        raise ConfigError("the scene has no device section", file=scene.path, key="device")
    print("hapsim mock: building the firmware and the emulated board (make) ...",
          file=sys.stderr, flush=True)
    try:
        board.build()
    except DeviceError as exc:
        print(f"hapsim mock: {exc}", file=sys.stderr)
        return 1
    cmd = board.board_command(scene.device, scene.excitation, realtime=not args.lockstep,
                              report=args.report, link=args.link,
                              trace=getattr(args, "trace", None),
                              spin_us=getattr(args, "spin_us", None) or 0.0)
    return _exec_board(cmd, args)


# ---------------------------------------------------- a 2-D or 3-D scene's device
#: The ``hapsim mock`` options (their ``argparse`` destinations) a 2-D or 3-D scene's
#: mock takes; any other one given (not None, not False) is refused by name (exit 2).
#: It has no sensor noise (``--seed`` has nothing to seed); its faults are the 1-D
#: mock's (``--faults``, ``--fault-seed``, ``--link``: :mod:`hapsim.emulated.faults`).
TAKES = frozenset({"scene", "lockstep", "rate", "report", "rt_priority", "once",
                   "amplitude", "tick", "faults", "fault_seed", "link"})
#: ``--tick`` values it takes: its real-time ticks are Python's ("auto" picks them).
TICKS = ("auto", "python")
#: Destinations that are no option of ``hapsim mock`` (the CLI's own).
_NOT_OPTIONS = frozenset({"func", "command", "option_default"})


def _given(args, takes) -> list:
    """The ``(flag, value)`` of every option given (not None, not False, not its default)
    that is not in ``takes``, sorted by destination."""
    default = getattr(args, "option_default", None)   # argparse's get_default of mock
    out = []
    for dest, value in sorted(vars(args).items()):
        if dest in takes or dest in _NOT_OPTIONS or value is None or value is False:
            continue
        if default is not None and value == default(dest):
            continue
        out.append(("--" + dest.replace("_", "-"), value))
    return out


def refuse_untaken(args) -> None:
    """Refuse every ``hapsim mock`` option given that a 2-D or 3-D scene's mock does not
    take (it would be silently ignored otherwise).

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim mock``'s options (an option not given is None or False).

    Raises
    ------
    ConfigError
        Naming the first such option and the ones the n-D mock takes (exit 2). An option
        at its parser default counts as not given.
    """
    takes = ", ".join("--" + d.replace("_", "-") for d in sorted(TAKES))
    for opt, _ in _given(args, TAKES):
        raise ConfigError(f"a 2-D or 3-D scene's mock does not take {opt} (it takes "
                          f"{takes})", key=opt)
    tick = getattr(args, "tick", "auto")
    if tick not in TICKS:
        raise ConfigError(f"a 2-D or 3-D scene's mock ticks in Python: --tick {tick} is not "
                          f"taken (valid: {', '.join(TICKS)})", key="--tick")


def _fault_seed_alone(args) -> None:
    """Refuse ``--fault-seed`` given without ``--faults`` (before: taken and ignored)."""
    if getattr(args, "fault_seed", None) is not None and not getattr(args, "faults", None):
        raise ConfigError("seeds the faults of --faults, and none is given",
                          key="--fault-seed")


def run_mock_nd(args, new_pty) -> int:
    """Serve an n-D scene's device on a new pty until a signal (with ``--once``: until the
    host closes the port; a run sends STOP after every record, so STOP does not end it).

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim mock``'s options (``scene``, ``lockstep``, ``amplitude``, ``rate`` (the
        native rate HELLO announces [Hz]), ``report``, ``once``, ``rt_priority``,
        ``tick``, ``faults``, ``fault_seed``, ``link``).
    new_pty : callable
        ``new_pty(link, announce) -> (master, slave)``: :mod:`hapsim.commands.mock`'s pty
        opener (prints ``PORT /dev/pts/N``).

    Returns
    -------
    int
        0.

    Raises
    ------
    ConfigError
        An option the n-D mock does not take; a scene without a port and device; a bad
        amplitude, rate or fault SPEC; a ``vanish`` fault without ``--link`` (exit 2).
    """
    from hapsim.emulated.faults import mock_fault_plan, reopener
    from hapsim.spawn import StopFlag
    from hapsim.emulated.serve import serve_fd
    from hapsim.emulated.mock import DEFAULT_AMPLITUDE, MockDeviceND
    from hapsim.host.realtime import RealtimePriority
    from hapsim.scene import load_scene_nd
    if getattr(args, "firmware", False):
        return run_pantograph_firmware(args)
    refuse_untaken(args)
    rt = RealtimePriority(args.rt_priority or 0)
    scene = load_scene_nd(args.scene)
    a = DEFAULT_AMPLITUDE if args.amplitude is None else args.amplitude
    rate = getattr(args, "rate", None)
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise ConfigError(f"must be a positive number [Hz], got {rate}", key="--rate")
    # --rate: the native rate HELLO announces; the physics follows each CONFIG's rate
    _fault_seed_alone(args)
    plan = mock_fault_plan(getattr(args, "faults", None), getattr(args, "fault_seed", None),
                           getattr(args, "link", None), bool(args.lockstep))
    mock = MockDeviceND(scene, a, lockstep=args.lockstep, native_rate_hz=rate)
    master, slave = new_pty(getattr(args, "link", None), announce=True)
    # the raw settings stay with the pty; with no slave fd of its own the mock sees EIO
    # when a host closes the port (or dies). A run sends STOP after every record, so STOP
    # cannot end --once: the first host that ran and left does.
    os.close(slave)
    slave = None
    once = getattr(args, "once", False)
    flag = StopFlag()

    def host_gone(stats: dict) -> None:
        if stats["ticks"] or stats["saw_stop"]:
            if once:
                flag.request()
                return
            print(f"hapsim mock: host left ({stats['ticks']} ticks since its last CONFIG, "
                  f"{stats['late']} late); waiting for the next run (Ctrl-C ends the mock)",
                  file=sys.stderr, flush=True)
    try:
        with rt:
            # signal handlers can only be installed from the main thread (tests serve
            # the mock from another one)
            report = serve_fd(master, mock, exit_on_stop=False, report_path=args.report,
                              persistent=True, on_host_gone=host_gone, tick="python",
                              flag=flag, handle_signals=threading.current_thread()
                              is threading.main_thread(), plan=plan,
                              reopen=reopener(getattr(args, "link", None), new_pty,
                                              announce=True))
        print(f"hapsim mock: stopped ({report['end']})", file=sys.stderr, flush=True)
    finally:
        for fd in (master, slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
    return 0


#: What ``hapsim mock --firmware`` takes on a 2-D scene (the emulated Hapkit pantograph).
FIRMWARE_TAKES = frozenset({"scene", "lockstep", "report", "amplitude", "link", "firmware",
                            "spin_us", "rt_priority"})
#: Options given their defaults by ``hapsim mock`` itself (a value, not None): taken at
#: that value only (the board has no tick choice).
_FIRMWARE_DEFAULTS = {"tick": "auto"}
#: The hand's default amplitude on the emulated Hapkit pantograph [m]: its sensors resolve
#: ~1.3e-5 m at the handle (one count, scene-dependent), so 2e-4 m is ~15 counts; within
#: the 0.5 mm depth of configs/pantograph_wall.yaml's wall.
FIRMWARE_AMPLITUDE = 2e-4


def refuse_untaken_firmware(args) -> None:
    """Refuse every ``hapsim mock`` option given that the emulated Hapkit pantograph does
    not take (:data:`FIRMWARE_TAKES`; ``--spin-us`` and a ``--rt-priority`` above 0 only in
    real time).

    Parameters
    ----------
    args : argparse.Namespace

    Raises
    ------
    ConfigError
        Naming the first such option and the ones it takes (exit 2).
    """
    for opt, value in _given(args, FIRMWARE_TAKES):
        dest = opt[2:].replace("-", "_")
        if dest in _FIRMWARE_DEFAULTS and value == _FIRMWARE_DEFAULTS[dest]:
            continue
        raise ConfigError(f"the emulated Hapkit pantograph (--firmware on a 2-D scene) does "
                          f"not take {opt} (it takes --scene, --lockstep, --amplitude, "
                          "--report, --link, and in real time --spin-us, --rt-priority)",
                          key=opt)
    if args.lockstep:
        for opt, v in (("--spin-us", getattr(args, "spin_us", None)),
                       ("--rt-priority", getattr(args, "rt_priority", 0) or None)):
            if v is not None:
                raise ConfigError(f"{opt} is an option of the real-time board: not with "
                                  "--lockstep (the emulated clock waits for each FORCE)",
                                  key=opt)


def run_pantograph_firmware(args) -> int:
    """``hapsim mock --firmware --scene SCENE [--lockstep]`` on a 2-D pantograph scene:
    build what is missing and become the emulated Hapkit pantograph
    (:mod:`hapsim.emulated.pantograph_board`: our firmware on two ATmega328P on one TWI bus),
    which prints ``PORT /dev/pts/N``; in real time (the default: the emulated clock locked
    to the wall clock, SCHED_FIFO at ``--rt-priority``, default 10, where permitted) or in
    lockstep (the emulated clock waits for each FORCE).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``lockstep``, ``amplitude`` [m] (default :data:`FIRMWARE_AMPLITUDE`),
        ``report``, ``link``, ``spin_us`` (real time; default
        :data:`hapsim.emulated.pantograph_board.SPIN_US`), ``rt_priority``.

    Returns
    -------
    int
        Does not return on success (the process becomes the board); 1 when it cannot be
        built.

    Raises
    ------
    ConfigError
        An option it does not take (``--spin-us`` or ``--rt-priority`` with
        ``--lockstep``); not a pantograph scene; a bad amplitude (exit 2).
    """
    from hapsim.emulated import pantograph_board as pb
    from hapsim.errors import DeviceError
    from hapsim.scene import load_scene_nd
    if args.lockstep and args.rt_priority == 0:
        args.rt_priority = None                 # hapsim mock's own lockstep default
    refuse_untaken_firmware(args)
    scene = load_scene_nd(args.scene)
    a = FIRMWARE_AMPLITUDE if args.amplitude is None else args.amplitude
    cmd = pb.board_command(scene, a, report=args.report, link=args.link,
                           realtime=not args.lockstep, spin_us=getattr(args, "spin_us", None))
    print("hapsim mock: building the pantograph firmware and its emulated boards (make) ...",
          file=sys.stderr, flush=True)
    try:
        pb.build()
    except DeviceError as exc:
        print(f"hapsim mock: {exc}", file=sys.stderr)
        return 1
    return _exec_board(cmd, args)


def _exec_board(cmd: list, args) -> int:
    """Become the emulated board's simavr process (``os.execv``): in real time (not
    ``--lockstep``) with ``--rt-priority`` > 0, SCHED_FIFO first (kept across exec: the
    board holds the emulated clock to the wall clock, and other programs must not
    deschedule it), or a note on stderr when it is refused. Returns only if exec does not
    (1)."""
    if not args.lockstep and getattr(args, "rt_priority", 0):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(args.rt_priority)))
        except (AttributeError, OSError) as exc:
            print(f"hapsim mock: normal scheduling (SCHED_FIFO {args.rt_priority} refused: "
                  f"{getattr(exc, 'strerror', None) or exc})", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os.execv(cmd[0], cmd)
    return 1  # not reached

"""``hapsim mock --scene SCENE`` on a 2-D or 3-D scene: its device behind the framed protocol
on a new pseudo-terminal (:class:`hapsim.emulated.mock_nd.MockDeviceND`)."""

from __future__ import annotations

import math
import os
import sys
import threading

from hapsim.errors import ConfigError

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
    from hapsim.host.loop import StopFlag
    from hapsim.emulated.serve import serve_fd
    from hapsim.emulated.mock_nd import DEFAULT_AMPLITUDE, MockDeviceND
    from hapsim.host.realtime import RealtimePriority
    from hapsim.scene_nd import load_scene_nd
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
    plan = mock_fault_plan(getattr(args, "faults", None), getattr(args, "fault_seed", None),
                           getattr(args, "link", None))
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
    from hapsim.scene_nd import load_scene_nd
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
    if not args.lockstep and args.rt_priority:
        # the board holds the emulated clock to the wall clock: SCHED_FIFO (kept across
        # exec) keeps other programs from descheduling it, as the 1-D board
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(args.rt_priority)))
        except (AttributeError, OSError) as exc:
            print(f"hapsim mock: normal scheduling (SCHED_FIFO {args.rt_priority} refused: "
                  f"{getattr(exc, 'strerror', None) or exc})", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os.execv(cmd[0], cmd)
    return 1  # not reached

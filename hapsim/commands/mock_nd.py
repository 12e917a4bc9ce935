"""``hapsim mock --scene SCENE`` on a 2-D or 3-D scene: its device behind the framed protocol
on a new pseudo-terminal (:class:`hapsim.daemon.mock_nd.MockDeviceND`)."""

from __future__ import annotations

import math
import os
import sys
import threading

from hapsim.errors import ConfigError

#: mock options a 2-D or 3-D scene's device does not take yet (refused by name, exit 2)
_REFUSED = (("faults", "--faults"), ("link", "--link"), ("spec", "--spec"))


def run_mock_nd(args, new_pty) -> int:
    """Serve an n-D scene's device on a new pty until a signal (with ``--once``: until the
    host closes the port; a run sends STOP after every record, so STOP does not end it).

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim mock``'s options (``scene``, ``lockstep``, ``amplitude``, ``rate`` (the
        native rate HELLO announces [Hz]), ``report``, ``once``, ``rt_priority``,
        ``tick``).
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
        amplitude or rate (exit 2).
    """
    from hapsim.daemon.loop import StopFlag
    from hapsim.daemon.mock import serve_fd
    from hapsim.daemon.mock_nd import DEFAULT_AMPLITUDE, MockDeviceND
    from hapsim.daemon.realtime import RealtimePriority
    from hapsim.scene_nd import load_scene_nd
    for attr, opt in _REFUSED:
        if getattr(args, attr, None) is not None:
            raise ConfigError(f"a 2-D or 3-D scene's mock does not take {opt} yet",
                              key=opt)
    rt = RealtimePriority(args.rt_priority or 0)
    scene = load_scene_nd(args.scene)
    a = DEFAULT_AMPLITUDE if args.amplitude is None else args.amplitude
    rate = getattr(args, "rate", None)
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise ConfigError(f"must be a positive number [Hz], got {rate}", key="--rate")
    # --rate: the native rate HELLO announces; the physics follows each CONFIG's rate
    mock = MockDeviceND(scene, a, lockstep=args.lockstep, native_rate_hz=rate)
    master, slave = new_pty(None, announce=True)
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
                              is threading.main_thread())
        print(f"hapsim mock: stopped ({report['end']})", file=sys.stderr, flush=True)
    finally:
        for fd in (master, slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
    return 0

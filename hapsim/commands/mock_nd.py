"""``hapsim mock --scene SCENE`` on a 2-D or 3-D scene: its device behind the framed protocol
on a new pseudo-terminal (:class:`hapsim.daemon.mock_nd.MockDeviceND`)."""

from __future__ import annotations

import os
import sys

from hapsim.errors import ConfigError

#: mock options a 2-D or 3-D scene's device does not take yet (refused by name, exit 2)
_REFUSED = (("faults", "--faults"), ("link", "--link"), ("rate", "--rate"),
            ("spec", "--spec"))


def run_mock_nd(args, new_pty) -> int:
    """Serve an n-D scene's device on a new pty until a signal (with ``--once``: until the
    host closes the port; a run sends STOP after every record, so STOP does not end it).

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim mock``'s options (``scene``, ``lockstep``, ``amplitude``, ``report``,
        ``once``, ``rt_priority``, ``tick``).
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
        amplitude (exit 2).
    """
    from hapsim.daemon.mock import serve_fd
    from hapsim.daemon.mock_nd import DEFAULT_AMPLITUDE, MockDeviceND
    from hapsim.daemon.realtime import RealtimePriority
    from hapsim.scene_nd import load_scene_nd
    for attr, opt in _REFUSED:
        if getattr(args, attr, None) is not None:
            raise ConfigError(f"a 2-D or 3-D scene's mock does not take {opt} yet",
                              key=opt)
    rt = RealtimePriority(args.rt_priority)
    scene = load_scene_nd(args.scene)
    a = DEFAULT_AMPLITUDE if args.amplitude is None else args.amplitude
    mock = MockDeviceND(scene, a, lockstep=args.lockstep)
    master, slave = new_pty(None, announce=True)
    persistent = not getattr(args, "once", False)
    if persistent:
        os.close(slave)
        slave = None

    def host_gone(stats: dict) -> None:
        if stats["ticks"] or stats["saw_stop"]:
            print(f"hapsim mock: host left ({stats['ticks']} ticks since its last CONFIG, "
                  f"{stats['late']} late); waiting for the next run (Ctrl-C ends the mock)",
                  file=sys.stderr, flush=True)
    try:
        with rt:
            # a run ends each record with STOP: only the host closing the port ends --once
            report = serve_fd(master, mock, exit_on_stop=False, report_path=args.report,
                              persistent=persistent, on_host_gone=host_gone, tick="python")
        print(f"hapsim mock: stopped ({report['end']})", file=sys.stderr, flush=True)
    finally:
        for fd in (master, slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
    return 0

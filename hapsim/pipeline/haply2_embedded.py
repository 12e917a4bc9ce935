"""The emulated Haply 2DIY board in a child process behind an emulated link (a
pseudo-terminal in lockstep), for the
real-time loop (:mod:`hapsim.pipeline.haply2_record`) to drive as it would a real board:
:class:`Embedded2DIY` starts it, :func:`main` is the child's entry
(``python -m hapsim.pipeline.haply2_embedded``), serving
:class:`hapsim.emulated.haply2_board.Haply2DIYBoard` with
:func:`hapsim.emulated.driver_mock.serve`.
"""

from __future__ import annotations

import math
import sys

from hapsim.emulated.haply2_board import Haply2DIYBoard
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.errors import ConfigError
from hapsim.outputs import write_json
from hapsim.spawn import PtyChild

__all__ = ["Embedded2DIY", "main"]


class Embedded2DIY(PtyChild):
    """The emulated 2DIY board (:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`) in a
    child process on an emulated link on the wall clock (``emulated://NAME``: each host
    write taken at its kernel stamp, :mod:`hapsim.emulated.stamped_link`) or on the master
    side of a new pty in lockstep, served by
    :func:`hapsim.emulated.driver_mock.serve` on its own clock (the wall clock: the joints move in
    real time, a set-up takes its encoders' waits) or, named, in lockstep (one period per
    write, replies at once).

    Parameters
    ----------
    scene_path : str
        The 2-D pantograph scene's file.
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m].
    cpr : float, optional
        The emulated encoders' counts per revolution (default the generation's).
    slow_every : int, optional
        Every ``slow_every``-th write's reply waits ``slow_s`` [s] (a slow board; 0: none).
    slow_s : float, optional
    rate_hz : float, optional
        The loop's rate [Hz] (default the scene file's): the plant's period.
    wiring : ((int, int), (int, int)), optional
        The emulated board's wiring (:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`).
    clock : {"wall", "lockstep"}
        The emulated board's clock (:class:`~hapsim.emulated.haply2_board.Haply2DIYBoard`):
        its own time (the default) or one period per write (named, for deterministic
        tests).
    rt_priority : int, optional
        ``SCHED_FIFO`` priority the board's process takes once its start-up is done (its
        imports and its compiled plant loaded: a start-up under ``SCHED_FIFO`` starves
        the machine), where the OS permits it (:class:`hapsim.host.realtime.
        RealtimePriority`); 0 (the default): normal scheduling. A real board's
        microcontroller is never descheduled: on a loaded host the emulated one is not
        either.

    Attributes
    ----------
    port : str
        The port to open: the link's URL, or the pty's slave path in lockstep.
    clock : str
        The board's clock (what the host's loop reads: a stall on a board with its own
        clock costs a record).
    """

    def __init__(self, scene_path: str, generation: str = "gen3", *, amplitude: float,
                 cpr: float | None = None, slow_every: int = 0, slow_s: float = 0.0,
                 rate_hz: float | None = None, wiring=((1, 1), (1, 1)),
                 clock: str = "wall", rt_priority: int = 0) -> None:
        if clock not in ("wall", "lockstep"):
            raise ConfigError(f"unknown clock {clock!r}; valid: wall, lockstep", key="clock")
        self.clock = clock
        from hapsim.emulated.driver_mock import WALL_LINK
        link = WALL_LINK if clock == "wall" else "pty"
        master = (self.open_pty("hapsim-2diy-") if link == "pty"
                  else self.open_link("hapsim-2diy-"))
        where = "--fd" if link == "pty" else "--listen"
        self.start([sys.executable, "-m", "hapsim.pipeline.haply2_embedded", where, str(master),
                    "--scene", str(scene_path), "--generation", generation, "--amplitude",
                    repr(float(amplitude)), "--cpr", repr(float(cpr or 0.0)), "--report",
                    self.report_path, "--slow-every", str(int(slow_every)), "--slow-s",
                    repr(float(slow_s)), "--rate", repr(float(rate_hz or 0.0)),
                    "--wiring", ",".join(str(int(v)) for jw in wiring for v in jw),
                    "--clock", clock, "--rt-priority", str(int(rt_priority))], master)


class _SlowBoard(Haply2DIYBoard):
    """A board whose every ``slow_every``-th reply waits ``slow_s`` [s] (what
    :func:`hapsim.emulated.driver_mock.serve` reads as ``reply_delay_s`` after each write)."""

    slow_every = 0
    slow_s = 0.0

    @property
    def reply_delay_s(self) -> float:
        k = self.slow_every
        return self.slow_s if k and self.writes and self.writes % k == 0 else 0.0


def main(argv=None) -> int:
    """Child-process entry: ``python -m hapsim.pipeline.haply2_embedded --fd N --scene PATH
    --generation G --amplitude A [--cpr C] [--report FILE]``: serve the emulated board
    until the host closes the port or SIGTERM; the serving report as JSON (``--listen N``
    instead of ``--fd``: an emulated link's listening socket,
    :mod:`hapsim.emulated.stamped_link`).

    Parameters
    ----------
    argv : list of str, optional
        The arguments (default ``sys.argv[1:]``); besides those above the test options
        ``--slow-every``, ``--slow-s``, ``--rate`` [Hz], ``--wiring``, ``--clock`` and
        ``--rt-priority``.

    Returns
    -------
    int
        0 (also when stopped before the link's connection came).

    Raises
    ------
    SystemExit
        Bad arguments (argparse, status 2).
    ConfigError
        The scene cannot be read.
    """
    import argparse
    import signal

    from hapsim.emulated.driver_mock import serve
    from hapsim.scene import load_scene_nd
    p = argparse.ArgumentParser(prog="hapsim.pipeline.haply2_embedded")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--fd", type=int)
    where.add_argument("--listen", type=int)
    p.add_argument("--scene", required=True)
    p.add_argument("--generation", default="gen3")
    p.add_argument("--amplitude", type=float, required=True)
    p.add_argument("--cpr", type=float, default=0.0)
    p.add_argument("--report")
    p.add_argument("--slow-every", type=int, default=0)
    p.add_argument("--slow-s", type=float, default=0.0)
    p.add_argument("--rate", type=float, default=0.0)
    p.add_argument("--wiring", default="1,1,1,1")
    p.add_argument("--clock", choices=("wall", "lockstep"), default="wall")
    p.add_argument("--rt-priority", type=int, default=0)
    a = p.parse_args(argv)
    w = [int(v) for v in a.wiring.split(",")]
    scene = load_scene_nd(a.scene)
    if a.rate:
        import dataclasses
        scene = dataclasses.replace(scene, rate_hz=a.rate)
    board = _SlowBoard(scene, a.generation, cpr=a.cpr or None, amplitude=a.amplitude,
                       wiring=(tuple(w[:2]), tuple(w[2:])), clock=a.clock)
    board.slow_every, board.slow_s = a.slow_every, a.slow_s
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    from hapsim.host.realtime import RealtimePriority
    if a.clock == "wall" and a.rt_priority:
        # the compiled plant loaded before SCHED_FIFO (a throwaway board armed and written
        # once): its first call, a load from numba's cache or a compilation, would starve
        # the machine under it
        warm, drv = Haply2DIYBoard(scene, a.generation, clock="wall"), Haply2DIY(a.generation)
        warm.feed(drv.arm_bytes([math.degrees(v) for v in scene.device.joints]), 0.0)
        warm.feed(drv.write_bytes((0.0, 0.0)), scene.period)
    # SCHED_FIFO once the start-up is done (the board made, its plant compiled): a board's
    # microcontroller is never descheduled; serve waits in select, it does not spin
    fd, reader = a.fd, None
    if a.listen is not None:
        from hapsim.emulated.stamped_link import connection
        conn, reader = connection(a.listen, stop=lambda: flag["stop"])
        fd = None if conn is None else conn.fileno()
    if fd is None:
        return 0                            # (stopped before the port was opened)
    with RealtimePriority(a.rt_priority if a.clock == "wall" else 0) as rt:
        rep = serve(fd, board, stop=lambda: flag["stop"], stamped=reader)
    rep["scheduling"] = rt.note
    if a.report:
        write_json(a.report, rep)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``hapsim mock --scene SCENE`` for a scene whose device speaks a driver's protocol: the
emulated board of that device (its firmware's loop, on its own wall clock) served on a
new pseudo-terminal, for ``hapsim run SCENE --port PTY`` as with the hardware.

A scene's ``device.protocol`` (``firefader``, ``hapkit-serial``) names the board; a scene
with several ports (``devices:``) is served when it is the FireFader's two faders on one
board (:func:`hapsim.pipeline.faders_run.faders_refusal`), fader B its second device,
with the hand of ``hapsim run``'s records (the run's amplitude, ``--amplitude``). The
board is the one ``hapsim run`` embeds when no port is given
(:mod:`hapsim.emulated.driver_mock`, the registry's ``mock`` of each family), built from
the driver's own description of the hardware (``mock_hardware``) and the scene's
``device.protocol_options``. The FireFader and the Hapkit are Arduinos, which reset
when a host opens their port (the USB-serial bridge's DTR line pulses the reset pin): each host meets a
board fresh from its reset, the scene's excitation (or the faders' hand) at its start
(:class:`BoardPerHost`; the Haply M3, a SAMD21 on native USB, does not reset then, but
its host's set-up restarts its encoders: it is reset too, so each host's run starts
from the excitation, as the embedded board's does). A board whose set-up takes
something from the scene's excitation (the Haply M3's encoder restarts at the offset the
host's set-up sends: ``embedded_options`` of its driver) is served only when the scene's
``device.protocol_options`` say it, so that a host on the port arms it there; otherwise
it is refused with the option to give. It runs
until SIGINT/SIGTERM; ``--lockstep`` (named) advances one period per command instead of
on the clock.
"""

from __future__ import annotations

import math
import os
import signal
import sys

from hapsim.errors import ConfigError

__all__ = ["board_protocol", "run_board_mock", "BoardPerHost", "BOARD_TAKES",
           "BOARD_RT_PRIORITY"]

#: ``hapsim mock`` options a driver's board takes.
BOARD_TAKES = frozenset({"scene", "lockstep", "seed", "report", "link", "amplitude",
                         "rt_priority"})

#: The board's ``SCHED_FIFO`` priority when ``--rt-priority`` is not given: one above
#: ``hapsim run``'s default (10), as the embedded board takes one above its run's
#: (:func:`hapsim.emulated.driver_mock._above_the_hosts`): a board is a processor of its
#: own, which no host loop deschedules.
BOARD_RT_PRIORITY = 11


def board_protocol(path) -> str | None:
    """The driver protocol of a 1-D scene's device, or ``"firefader"`` for a scene with
    several ports; None for hapsim's own framed protocol (the framed mock's).

    Parameters
    ----------
    path : str or os.PathLike
        A 1-D scene file (readable: the caller checked its dimension).

    Returns
    -------
    str or None

    Raises
    ------
    ConfigError
        The scene's own errors (file, line, key).
    """
    from hapsim.drivers import DEFAULT
    from hapsim.scene import load_scene, load_scene_ports, scene_has_ports
    if scene_has_ports(path):
        protocols = {d.protocol for _, d in load_scene_ports(path).devices}
        return protocols.pop() if len(protocols) == 1 else "several"
    p = load_scene(path).device
    return None if p is None or p.protocol == DEFAULT else p.protocol


def _refuse_untaken(args, given) -> None:
    """Refuse, by flag, the options a board's mock does not take."""
    takes = ", ".join("--" + d.replace("_", "-") for d in sorted(BOARD_TAKES))
    for opt, _ in given(args, BOARD_TAKES):
        raise ConfigError(f"an emulated driver's board (a scene whose device.protocol is a "
                          f"driver's) does not take {opt} (it takes {takes})", key=opt)


def _board(args):
    """How to build the emulated board, and what is said of it: ``(make, rate_hz,
    what)``, ``make()`` a board fresh from its reset."""
    from hapsim.drivers import family, get_driver
    from hapsim.emulated.driver_mock import MOCKS, WALL_CLOCK_MOCKS
    from hapsim.scene import load_scene, load_scene_ports, scene_has_ports
    clock = "lockstep" if args.lockstep else "wall"
    if scene_has_ports(args.scene):
        from hapsim.lockstep import excitation_starts
        from hapsim.pipeline.faders_run import FADER_AMPLITUDE, WORKSPACE_M, faders_refusal
        from hapsim.pipeline.options import RunOptions
        from hapsim.scene import Excitation
        scene = load_scene_ports(args.scene)
        why = faders_refusal(scene, RunOptions())
        if why is not None:
            raise ConfigError(f"no emulated board for these ports: {why}", file=scene.path,
                              key="devices")
        a = FADER_AMPLITUDE if args.amplitude is None else float(args.amplitude)
        if not a <= WORKSPACE_M / 4:
            raise ConfigError(f"must be a positive length up to {WORKSPACE_M / 4:g} m (a "
                              f"quarter of the faders' workspace), got {a:g}",
                              key="--amplitude")
        starts = excitation_starts(2, a, scene.period)
        (_, da), (_, db) = scene.devices
        drv = get_driver("firefader", **(da.protocol_options or {}))
        opts = {**drv.mock_hardware(), "clock": clock, "device_b": db,
                "hand": [(float(x0[0]), float(x0[1]), float(v0[0]), float(v0[1]))
                         for x0, v0 in starts]}
        return (lambda: MOCKS["firefader"](da, scene.rate_hz, Excitation(),
                                           seed=args.seed or 0, **opts)), scene.rate_hz, \
            (f"the FireFader's two faders ({', '.join(scene.ports)}) on one board, the "
             f"hand at a = {a:g} m")
    if args.amplitude is not None:
        raise ConfigError("a 1-D board's hand is the scene's excitation section (--amplitude "
                          "is a 2-D/3-D scene's or two faders')", key="--amplitude")
    scene = load_scene(args.scene)
    d = scene.device
    if d.protocol not in MOCKS:
        raise ConfigError(f"no emulated board for device.protocol {d.protocol!r}; valid: "
                          f"{', '.join(MOCKS)}", file=scene.path, key="device.protocol")
    given = dict(d.protocol_options or {})
    arm = family(d.protocol).load().embedded_options(given, scene.excitation.x0)
    if arm != given:
        # the board's set-up takes something from the excitation that a host on a port
        # does not send unless the scene says it (the Haply's encoder offset)
        # (a float in full, its shortest round trip: the check below takes the value
        # itself, and the message's 11.4592 of a 0.2 rad start was refused again)
        missing = ", ".join(f"{k}: {v!r}" if isinstance(v, float) else f"{k}: {v}"
                            for k, v in arm.items() if given.get(k) != v)
        raise ConfigError(f"the {d.protocol} board is armed where a host's set-up puts it: "
                          f"a host on its port arms it at the scene's excitation only with "
                          f"device.protocol_options {{{missing}}} (hapsim run embeds it so "
                          "without --port)", file=scene.path, key="device.protocol_options")
    drv = get_driver(d.protocol, **given)
    opts = drv.mock_hardware()
    if d.protocol in WALL_CLOCK_MOCKS:
        opts["clock"] = clock
    elif not args.lockstep:
        raise ConfigError(f"the {d.protocol} board's emulation runs in lockstep only (one "
                          "period per command): give --lockstep", key="--lockstep")
    return (lambda: MOCKS[d.protocol](d, scene.rate_hz, scene.excitation,
                                      seed=args.seed or 0, **opts)), scene.rate_hz, \
        f"the {d.protocol} board"


def run_board_mock(args, new_pty, given) -> int:
    """Serve the emulated board of the scene's device on a new pty until a signal.

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim mock``'s options: ``scene``, ``lockstep``, ``seed``, ``report``,
        ``link``, ``amplitude`` (two faders: the hand's ``a`` [m]), ``rt_priority``
        (None: :data:`BOARD_RT_PRIORITY`); any other refused.
    new_pty : callable
        ``new_pty(link, announce)`` -> ``(master, slave)``: opens the pty and prints
        ``PORT /dev/pts/N`` (:func:`hapsim.commands.mock._new_pty`).
    given : callable
        ``given(args, takes)`` -> the options given that are not in ``takes``.

    Returns
    -------
    int
        0 (stopped by a signal).

    Raises
    ------
    ConfigError
        An option not taken, a device protocol without an emulated board, ports that are
        not one FireFader's two faders, a bad amplitude (exit 2).
    """
    from hapsim.emulated.driver_mock import serve
    from hapsim.outputs import write_json
    _refuse_untaken(args, given)
    import termios

    from hapsim.host.realtime import RealtimePriority
    rt = RealtimePriority(BOARD_RT_PRIORITY if args.rt_priority is None
                          else args.rt_priority)
    make, rate, what = _board(args)
    master, slave = new_pty(args.link, announce=True)
    # a reset drops what the last host left unread (the old board's last replies)
    dev = BoardPerHost(make, on_reset=lambda: termios.tcflush(master, termios.TCIOFLUSH))
    clock = "lockstep (one period per command)" if args.lockstep else "its own wall clock"
    print(f"hapsim mock: {what}, emulated from its firmware, on {clock} at {rate:g} Hz; "
          f"reset after each host, as an Arduino is when a host opens its port; "
          f"it serves host after host until Ctrl-C",
          file=sys.stderr, flush=True)
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    try:
        # the slave stays open here: a host closing the port is no end of the board
        with rt:
            if not rt.active and rt.priority:
                print(f"hapsim mock: scheduling {rt.note} (a host loop at SCHED_FIFO may "
                      "starve the board: its records then come late or not at all)",
                      file=sys.stderr, flush=True)
            rep = serve(master, dev, stop=lambda: flag["stop"],
                        poll=0.02 if getattr(dev, "firmware", "") != "pde" else 1.0 / rate)
    finally:
        for fd in (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass
    if args.report:
        write_json(args.report, rep)
    print(f"hapsim mock: stopped; {dev.hosts} host(s) served, the last one's "
          f"{rep.get('packets', 0)} commands applied",
          file=sys.stderr, flush=True)
    return 0


class BoardPerHost:
    """An emulated Arduino board served to host after host: a host gone (its bytes
    silent :data:`NEW_HOST_S`), the board is reset, fresh as after a reset, its clock
    starting there; the next host meets it as the first host met the board that was
    started with the mock.

    Parameters
    ----------
    make : callable
        ``make()`` -> a board (:mod:`hapsim.emulated.driver_mock`'s ``MOCKS``), fresh.
    on_reset : callable, optional
        Called at each reset (the mock drops the link's unread bytes).

    Attributes
    ----------
    hosts : int
        Hosts served.

    Notes
    -----
    Every other attribute is the current board's (what :func:`hapsim.emulated.
    driver_mock.serve` reads of it). A real board resets when the next host opens its
    port (the bridge's DTR pulse), not when the last one left; the emulation resets it
    at the silence instead, so that its start-up (the excitation's release, the
    bootloader) is over when the host's first bytes come, as for the board the mock
    started with.
    """

    #: A silence this long after a host's bytes ends that host [s]: more than twice a
    #: run's longest pause (the two faders' 0.4 s between records).
    NEW_HOST_S = 1.0

    def __init__(self, make, on_reset=None) -> None:
        self._make = make
        self._on_reset = on_reset
        self._dev = make()
        self._served = None                   # the board the last host had
        self._born = 0.0                      # the board's reset, serving's time [s]
        self._last = None                     # the last host bytes [s]
        self._fresh = True                    # no host bytes since the reset
        self.hosts = 0

    def __getattr__(self, name):
        # a fresh board's counters are nobody's yet: the last host's board answers
        dev = self._served if self._fresh and self._served is not None else self._dev
        return getattr(dev, name)

    @property
    def ready_at(self) -> float:
        """When the board's last pass ends, on serving's clock [s] (the board's own clock
        starts at its reset: :func:`hapsim.emulated.driver_mock.serve` answers then)."""
        return self._dev.ready_at + self._born

    def _reset(self, at: float) -> None:
        self._served = self._dev
        self._dev, self._born, self._fresh = self._make(), at, True
        if self._on_reset is not None:
            self._on_reset()

    def feed(self, data: bytes, now: float = math.inf, writes=None) -> bytes:
        """The board's :meth:`feed`, on its clock since its reset (``now`` [s] since
        serving began).

        Parameters
        ----------
        data : bytes
            The host's bytes (empty: none came).
        now : float
            Their time since serving began [s] (``inf``: lockstep, no time).
        writes : list of bytes, optional
            ``data`` split into the host's writes, passed on to a board that takes them.

        Returns
        -------
        bytes
            The board's answer.
        """
        if (data and not self._fresh and self._last is not None
                and now - self._last >= self.NEW_HOST_S):
            self._reset(now)                  # (a board on commands: no idle saw it)
        if data:
            self.hosts += self._fresh
            self._fresh, self._last = False, now
        kw = {} if writes is None else {"writes": writes}
        return self._dev.feed(data, now - self._born, **kw)

    def idle(self, silent_s: float) -> bytes:
        """The board's :meth:`idle`; a host silent :data:`NEW_HOST_S` is gone: reset.

        Parameters
        ----------
        silent_s : float
            Time since the host's last bytes [s].

        Returns
        -------
        bytes
            What the board writes meanwhile.
        """
        if self._last is not None and not self._fresh and silent_s >= self.NEW_HOST_S:
            self._reset(self._last + silent_s)
        if self._fresh:
            # no host since the reset: the board's silence is the time since it
            return self._dev.idle((self._last or 0.0) + silent_s - self._born)
        return self._dev.idle(silent_s)

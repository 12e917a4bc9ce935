"""Mocks of the driver protocols' devices, byte for byte, on a pseudo-terminal.

The physics is the mock device's (:class:`hapsim.emulated.mock.MockPhysics`: exact ZOH,
optional Coulomb friction, noise); the bytes are the device's protocol. The device answers
each host packet: it applies the force of the packet ``d`` packets back (the scene's
``device.delay``; zero before that), advances one period, and replies with one record of
the new position -- so the host's clock paces it (the protocols are host-clocked). A
packet that does not decode is dropped (the force last applied is held). What a silence
does is each firmware's own rule (the FireFader ``.ino`` disables its force after 0.1 s;
the Haply board and the Hapkit sketch have no watchdog and hold it). Seeded byte loss and
corruption in either direction (:class:`ByteFaults`) test the host against a lossy link.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import sys
import time
from collections import deque

from hapsim.drivers import FAMILIES
from hapsim.emulated.actuated import Actuated, WallClock
from hapsim.emulated.firefader_board import FireFaderDevice
from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice
from hapsim.emulated.haply_board import HaplyDevice
from hapsim.errors import HapsimError
from hapsim.outputs import write_json
from hapsim.spawn import PtyChild

__all__ = ["FireFaderDevice", "HaplyDevice", "HapkitSerialDevice", "ByteFaults", "serve",
           "WallClock", "MOCKS", "WALL_CLOCK_MOCKS",
           "EmbeddedDriverMock", "board_options", "build_board", "firefader_offline_loop", "main"]

#: The emulated device of each 1-D driver family, by its name (the registry's
#: :attr:`hapsim.drivers.Family.mock`).
MOCKS = {f.name: f.load_mock() for f in FAMILIES if f.dimension == 1 and f.mock}

#: The drivers whose mock keeps its own time (``clock="wall"``, an
#: :class:`~hapsim.emulated.actuated.Actuated` board's default) unless a run asks for
#: lockstep by name (``--lockstep``).
WALL_CLOCK_MOCKS = tuple(name for name, cls in MOCKS.items() if issubclass(cls, Actuated))

#: The link of an embedded driver mock on the wall clock (:class:`EmbeddedDriverMock`'s
#: ``link`` when none is given): ``"emulated"``, each host write taken at its kernel stamp
#: (:mod:`hapsim.emulated.stamped_link`); ``"pty"`` for a before/after measurement
#: (``tools/driver_timing.py --link pty``).
WALL_LINK = "emulated"


class ByteFaults:
    """Seeded byte faults on a driver mock's link, in both directions.

    Parameters
    ----------
    spec : dict, optional
        Probabilities per byte: ``drop_rx`` / ``corrupt_rx`` (host -> device: a byte lost,
        or one bit of it flipped), ``drop_tx`` / ``corrupt_tx`` (device -> host); ``seed``.

    Attributes
    ----------
    counts : dict
        Bytes dropped and corrupted per direction.
    """

    KEYS = ("drop_rx", "corrupt_rx", "drop_tx", "corrupt_tx")

    def __init__(self, spec: dict | None = None) -> None:
        import numpy as np
        spec = dict(spec or {})
        self.p = {k: float(spec.get(k, 0.0)) for k in self.KEYS}
        self.on = any(self.p.values())
        self._rng = np.random.default_rng(int(spec.get("seed", 0)))
        self.counts = {k: 0 for k in self.KEYS}

    def _apply(self, data: bytes, drop: str, corrupt: str) -> bytes:
        if not self.on or not data:
            return data
        n = len(data)
        pd, pc = self.p[drop], self.p[corrupt]
        u = self._rng.random(n)
        bits = self._rng.integers(0, 8, n)
        out = bytearray()
        for k, b in enumerate(data):
            if u[k] < pd:
                self.counts[drop] += 1
                continue
            if u[k] < pd + pc:
                self.counts[corrupt] += 1
                b ^= 1 << int(bits[k])
            out.append(b)
        return bytes(out)

    def rx(self, data: bytes) -> bytes:
        """Host -> device bytes, after the faults.

        Parameters
        ----------
        data : bytes
            The host's bytes.

        Returns
        -------
        bytes
            ``data`` with bytes dropped (``drop_rx``) or one bit flipped (``corrupt_rx``),
            counted in :attr:`counts`; ``data`` itself with no faults set.
        """
        return self._apply(data, "drop_rx", "corrupt_rx")

    def tx(self, data: bytes) -> bytes:
        """Device -> host bytes, after the faults.

        Parameters
        ----------
        data : bytes
            The device's bytes.

        Returns
        -------
        bytes
            ``data`` with bytes dropped (``drop_tx``) or one bit flipped (``corrupt_tx``),
            counted in :attr:`counts`; ``data`` itself with no faults set.
        """
        return self._apply(data, "drop_tx", "corrupt_tx")


def _take(dev, data: bytes, now: float, fl, streams: bool, listens: bool, later: deque,
          t0: float) -> bytes:
    """:func:`serve`'s handling of one read of the host's bytes, come at the board's time
    ``now`` [s]: fed to ``dev`` through the link's faults, its answer returned to be
    written now, or queued in ``later`` for its time (a board that listens while it
    answers), or written after a sleep to its time."""
    split = getattr(dev, "host_writes", None)
    if split is not None and not streams:
        # the link's faults per host write: a write is one host tick whatever the
        # faults leave of it (the device's time goes on)
        ws = [fl.rx(w) for w in split(data)]
        got = dev.feed(b"".join(ws), now, writes=ws)
    else:
        got = dev.feed(fl.rx(data), now)
    if got and dev.reply_delay_s > 0:
        # the device's pass and its answer's wire time (the host's bytes that come
        # meanwhile wait for the next pass)
        wait = t0 + now + dev.reply_delay_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
    if got and listens:
        later.append((t0 + dev.ready_at, got))
        return b""
    if got and getattr(dev, "wall", None) is not None and hasattr(dev, "ready_at"):
        # a board on its own clock answers when its pass has run (after a set-up's
        # wait, later than the bytes came)
        wait = t0 + dev.ready_at - time.monotonic()
        if wait > 0:
            time.sleep(wait)
    return got


def serve(fd: int, dev, *, stop=None, faults: dict | None = None,
          poll: float = 0.02, handled=None, stamped=None) -> dict:
    """Serve ``dev`` on a byte stream until EOF (host closed) or ``stop()`` is true.

    Parameters
    ----------
    fd : int
        Master side of the pty, or the emulated link's socket (``stamped``).
    dev : FireFaderDevice, HaplyDevice or HapkitSerialDevice
        The device (``feed(bytes, now) -> bytes``, ``idle(silent_s) -> bytes``,
        ``decoder.stats``). What a silent host does to the force is the device's own rule
        (``idle``): the FireFader ``.ino`` disables it after 0.1 s, the Haply board and the
        Hapkit sketch hold it (no watchdog).
    stop : callable, optional
        Polled; serving ends when it returns True.
    faults : dict, optional
        :class:`ByteFaults` spec (seeded byte loss and corruption, both directions); also
        the test hook ``slow`` / ``slow_s``: each answer, with that probability (its own
        seeded draw, so the bytes lost are the same), is written ``slow_s`` [s] late, as
        a mock process on a loaded host is (a starved reader: nothing is read meanwhile,
        and on the emulated link the writes that came meanwhile are taken at its end);
        ``slow_s`` may be a pair ``[lo, hi]``: each such silence drawn uniformly in it
        (``tools/driver_timing.py --starve``). The silences are counted in the result's
        ``starved`` (their number and their longest [s]).
    poll : float
        Wait for bytes before ``idle`` is called [s].
    handled : hapsim.spawn.HandledBytes, optional
        A lockstep mock's account of the bytes it has handled, published after each read
        is answered (the host tells a slow mock from a lost packet by it, not by time).
    stamped : hapsim.emulated.stamped_link.StampedReader, optional
        The emulated link's reader of ``fd``: each host write is taken at the time the
        kernel stamped it with, not when this process read it (its wake-up's lateness,
        which a board on its own processor does not have; :mod:`hapsim.emulated.
        stamped_link`). Without it, the bytes of a read are taken at the read's time.

    Returns
    -------
    dict
        ``packets`` (force commands applied), ``decoder`` counters, ``faults`` (bytes
        dropped and corrupted per direction), ``held_at_end`` [N] (the force the device
        is left holding when the host is gone, its delay queue applied), and the keys of
        :class:`hapsim.emulated.mock.MockStats` the run report prints (``ticks`` = packets,
        ``late``, ``overruns`` and ``watchdog_trips`` 0: the device is paced by the packets
        and has no watchdog; ``clamped``; ``last_applied`` [N]; ``saw_stop``: the last
        packet commanded zero force, which is all a STOP is in these protocols).
    """
    os.set_blocking(fd, False)
    fl = ByteFaults(faults)
    slow_p = float((faults or {}).get("slow", 0.0))
    slow_s = (faults or {}).get("slow_s", 0.0)
    slow_lo, slow_hi = ((float(slow_s[0]), float(slow_s[1])) if isinstance(slow_s, (list, tuple))
                        else (float(slow_s),) * 2)
    starved = {"silences": 0, "longest_s": 0.0}
    if slow_p > 0:
        import numpy as np
        slow_rng = np.random.default_rng([int((faults or {}).get("seed", 0)), 1])
    n_read = n_written = 0
    t0 = last = t_idle = time.monotonic()
    streams = getattr(dev, "firmware", "") == "pde"
    # a board whose receiver takes bytes while its loop works (the sketch's UART
    # interrupt fills a ring buffer): its answers wait here for their time while this
    # loop goes on reading, so a byte that comes meanwhile is stamped when it came
    # (the others' are written after a sleep to their time, nothing read meanwhile)
    listens = (getattr(dev, "listens_while_answering", False)
               and getattr(dev, "wall", None) is not None)
    later: deque = deque()                      # (when [monotonic s], answer bytes)
    gap = 0.0                                   # how late it took bytes, at most [s]
    deaf_until = 0.0                            # the test hook's silence's end [monotonic s]
    t_loop = time.monotonic()
    # the latest time the port is known to have held no byte unread [monotonic s]: a byte
    # read later came after it, so a read stamped ``now`` took it at most ``now - t_empty``
    # late (bytes come while a pass works, or while this thread waits for the GIL or the
    # CPU after its select or its read, as well as while it is not woken)
    t_empty = t_loop
    while not (stop and stop()):
        wait_s = poll if not later else min(poll, max(later[0][0] - time.monotonic(), 0.0))
        r, _, _ = select.select([fd], [], [], wait_s)
        t_sel = time.monotonic()
        # (beyond select's own wait: an emulator starved by the machine takes its bytes
        # that much late, which a board on its own processor never does)
        gap = max(gap, t_sel - t_loop - (0.0 if r else wait_s))
        if not r:
            # (empty when select timed out, at its deadline or later)
            t_empty = max(t_empty, t_loop + wait_s)
        out = b""
        if streams and time.monotonic() - t_idle >= poll:
            t_idle = time.monotonic()           # a streaming firmware's pass, asked or not
            out = dev.idle(t_idle - last)
        if not r:
            if not streams and getattr(dev, "clock", "wall") == "wall":
                # (a lockstep device's time is the commands: a silence of the wall clock
                # is a slow host, not the device's; it counts silent ticks itself)
                t_now = time.monotonic()
                if stamped is None or not select.select([fd], [], [], 0)[0]:
                    # (on a stamped link a write come since select timed out, while this
                    # thread waited for the CPU, is read first: the board takes it at
                    # its stamp, its time not run on past it by the silence)
                    out = dev.idle(t_now - last)
                if out and listens:
                    later.append((t0 + dev.ready_at, out))
                    out = b""
        else:
            if stamped is not None:
                try:
                    reads = stamped.read()      # (each host write at its own time)
                except OSError:
                    break
            else:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                reads = [(data, time.monotonic())]
                gap = max(gap, max(reads[0][1], deaf_until) - t_empty)
                if len(data) < 4096:
                    t_empty = t_sel         # (what this read left came after it began)
            for data, now in reads:
                now = max(now, deaf_until)
                n_read += len(data)
                last = now
                out += _take(dev, data, now - t0, fl, streams, listens, later, t0)
            if stamped is not None and stamped.eof:
                break
        while later and later[0][0] <= time.monotonic():
            out += later.popleft()[1]
        out = fl.tx(out)
        if out and slow_p > 0 and slow_rng.random() < slow_p:
            # the test hook: a slow mock process (its uniform draw only for a range, so a
            # fixed slow_s keeps the draws it had)
            s = slow_lo if slow_hi == slow_lo else float(slow_rng.uniform(slow_lo, slow_hi))
            starved["silences"] += 1
            starved["longest_s"] = max(starved["longest_s"], s)
            time.sleep(s)
            deaf_until = time.monotonic()       # (nothing read meanwhile, stamped or not)
        while out:
            try:
                k = os.write(fd, out)
            except BlockingIOError:             # the host reads later: wait for room
                if stop and stop():
                    out = None
                    break
                select.select([], [fd], [], poll)
                continue
            except OSError:
                out = None
                break
            n_written += k
            out = out[k:]
        if out is None:
            break
        if handled is not None:
            handled.publish(n_read, n_written)
        t_loop = time.monotonic()
    n = dev.commands()
    extra = {}
    for k in ("merged", "passes", "firmware", "host_ticks", "frame_walk", "tick_arrivals",
              "held_b_at_end"):
        if hasattr(dev, k):
            extra[k] = getattr(dev, k)
    if getattr(dev, "enables", None):
        extra["enable"] = dev.enables[-1]       # at the last pass (not after the host left)
        extra["passes_at_full_enable"] = sum(e == 129 for e in dev.enables)
    return {"packets": n, "decoder": dict(dev.decoder.stats), "faults": dict(fl.counts),
            "watchdog_trips": 0, "watchdog_at": [], "held_at_end": dev.settles_on(),
            "clock": getattr(dev, "clock", "lockstep"),
            "true_excursion": (dev.wall.excursion if getattr(dev, "wall", None) is not None
                               else None),
            # at most how late the serving loop took the host's bytes [s] (a pty's: the
            # time since the port was last known empty; also the longest time the loop
            # did not run beyond its poll): what the emulator itself was late by (the
            # machine's load), not the board
            "longest_gap_s": gap,
            # the longest non-zero force held with no command taking effect [s]
            "longest_hold_s": (getattr(dev.wall, "longest_hold", None)
                               if getattr(dev, "wall", None) is not None else None),
            "ticks": n, "late": 0, "overruns": 0, "clamped": dev.clamped,
            "last_applied": dev.held, "saw_stop": bool(n and dev.last_command == 0),
            **({"starved": starved} if slow_p > 0 else {}),
            # the emulated link: host writes taken at their kernel stamps, and any not
            **({"link": {"stamped": stamped.stamped, "unstamped": stamped.unstamped}}
               if stamped is not None else {}), **extra}


def firefader_offline_loop(scene, n: int = 900, *, lost=(), silence_at=None,
                           silence: float = 0.2, rx_drop=None):
    """The FireFader THS closed offline through hapsim's engine and the firmware's own loop
    (:class:`FireFaderDevice` with ``clock="lockstep"``, by name): deterministic, no pty, no
    real time.

    The host loop's arithmetic: row ``k`` is the record answering command ``k``, the force
    computed from it goes out with command ``k + 1``; a record that never came is stepped
    through with the position extrapolated from the last two records (``FLAG_ESTIMATED``),
    as :meth:`hapsim.drivers.transport.DriverTransport.estimate` does.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A scene with a device (its rate, delay, force limit and excitation).
    n : int
        Rows [samples].
    lost : iterable of int
        Rows whose record never came (device -> host loss).
    silence_at : int, optional
        The host is silent ``silence`` [s] before the command that follows that row.
    silence : float
        [s].
    rx_drop : dict of int to int, optional
        ``{row: byte}``: the packet sent after that row loses that byte (0 the start, 1
        fader A's, 2 fader B's) on its way to the firmware, which parses what is left (a
        row whose record then never comes is estimated).

    Returns
    -------
    tuple
        ``(columns, driver, applied)``: telemetry columns (``time`` [s], ``position`` [m],
        ``force`` [N], ``seq``, ``flags``, ``late``, ``force_seq``, ``status``), shape
        (n,); the :class:`hapsim.drivers.firefader.FireFader` (its ``loop_delay`` set);
        the force the mock applied over each row's period [N], shape (n,).
    """
    import numpy as np

    from hapsim.drivers.base import FLAG_ESTIMATED
    from hapsim.drivers.firefader import CENTRE, FireFader, RecordDecoder
    from hapsim.engine import Engine
    sc = scene
    drv = FireFader()
    drv.loop_delay = int(sc.device.delay)       # whole passes (the fraction: the physics)
    dev = FireFaderDevice(sc.device, sc.rate_hz, sc.excitation, clock="lockstep")
    for _ in range(drv.arming_records):
        dev.feed(drv.encode_force(0.0))
    eng = Engine(sc)
    T = sc.period
    dec = RecordDecoder()

    def record(b):
        r = dec.feed(b)
        return (r[-1][0] - CENTRE) * drv.position_scale if r else None

    x = record(dev.feed(drv.encode_force(0.0)))
    n0 = len(dev.applied)
    cols = {k: np.zeros(n) for k in ("time", "position", "force")}
    flags = np.zeros(n, np.uint8)
    xs, ss = [x, x], [-1, 0]
    lost = set(lost)
    t = 0.0
    rx_drop = dict(rx_drop or {})
    for k in range(n):
        cols["time"][k] = t
        if k in lost or x is None:
            lost.add(k)
            flags[k] = FLAG_ESTIMATED
            x_k = xs[-1] + (xs[-1] - xs[-2]) / (ss[-1] - ss[-2]) * (k - ss[-1])
        else:
            x_k = x
            xs.append(x)
            ss.append(k)
        cols["position"][k] = x_k
        f = min(max(eng.port_step(x_k), -sc.device.force_limit), sc.device.force_limit)
        cols["force"][k] = drv.applied_force(f)
        t += T
        if k == silence_at:
            dev.idle(silence)
            t += silence
        pk = drv.encode_force(f)
        if k in rx_drop:
            j = rx_drop[k]
            pk = pk[:j] + pk[j + 1:]
        x = record(dev.feed(pk, writes=[b"", pk]))      # one host write, one tick
    cols.update(seq=np.arange(n), flags=flags, late=np.zeros(n, np.uint8),
                force_seq=np.arange(n) - int(sc.device.delay), status=np.zeros(n, np.uint16))
    # the pass of command k + 1 moves the fader over row k's period
    return cols, drv, np.array(dev.applied[n0:n0 + n])




def _above_the_hosts() -> None:
    """A board is a processor of its own: no host loop deschedules it. The board's process
    inherits the run's ``SCHED_FIFO`` priority (``hapsim run --rt-priority``, taken before
    it starts); once its imports are done it takes one priority more, so that no host loop
    at the run's priority -- this run's or another's on the same machine -- delays its
    ticks. At the same priority, beside a second run's real-time loop and two CPU-bound
    processes (the suite's workers), the Hapkit sketch's model was descheduled 0.5-3 ms
    and took a command a tick late, which no real board does and no host can know (a
    "differs" in a fresh-clone CI run). Nothing where the process runs under normal
    scheduling (it asks for nothing it was not given)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:
            return
        prio = os.sched_getparam(0).sched_priority + 1
        if prio <= os.sched_get_priority_max(os.SCHED_FIFO):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (AttributeError, OSError):        # no such scheduler here, or not permitted
        pass


def board_options(driver: str, numeric: bool = False) -> list:
    """The options a driver's board model takes (its constructor's keywords, ``seed``
    apart), sorted.

    Parameters
    ----------
    driver : str
        A key of :data:`MOCKS`.
    numeric : bool
        Only its numbers and flags (what ``--mock-option KEY=VALUE`` can give), not the
        clock, the second fader's device or the hand.

    Returns
    -------
    list of str
    """
    import inspect
    params = inspect.signature(MOCKS[driver].__init__).parameters
    return sorted(n for n, p in params.items() if p.kind is p.KEYWORD_ONLY and n != "seed"
                  and (not numeric or (n not in ("clock", "device_b", "hand") and any(
                      t in str(p.annotation) for t in ("float", "int", "bool")))))


def build_board(driver: str, device, excitation, rate_hz: float, *, seed: int = 0,
                options: dict | None = None):
    """The board model a driver mock serves (one of :data:`MOCKS`), built from its options.

    Parameters
    ----------
    driver : str
        Driver name (a key of :data:`MOCKS`).
    device, excitation
        What the board drives (:class:`hapsim.scene.Device`,
        :class:`~hapsim.scene.Excitation`).
    rate_hz : float
        Host rate [Hz].
    seed : int
        Sensor-noise seed.
    options : dict, optional
        The board's own keywords, as JSON carries them (a ``device_b`` as a dict: the
        FireFader's fader B, read as a device section).

    Returns
    -------
    hapsim.emulated.actuated.Actuated
        The board (:class:`~hapsim.emulated.firefader_board.FireFaderDevice`,
        :class:`~hapsim.emulated.haply_board.HaplyDevice` or
        :class:`~hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`).

    Raises
    ------
    hapsim.errors.ConfigError
        A driver with no board model, an option the board does not take (the valid ones
        named), or one out of its range (the board's check, its key named).
    """
    from hapsim.errors import ConfigError
    from hapsim.scene import device_from_dict
    if driver not in MOCKS:
        raise ConfigError(f"no mock for driver {driver!r}; valid: {', '.join(MOCKS)}",
                          key="--driver")
    opt = dict(options or {})
    valid = board_options(driver)
    bad = sorted(set(opt) - set(valid))
    if bad:
        raise ConfigError(f"{', '.join(bad)}: not an option of the {driver} board's model; "
                          f"valid: {', '.join(valid)}", key="options")
    if isinstance(opt.get("device_b"), dict):
        # a second handle's device (the FireFader's fader B), as the first one's
        opt["device_b"] = device_from_dict(opt["device_b"])
    return MOCKS[driver](device, rate_hz, excitation, seed=seed, **opt)


def main(argv=None) -> int:
    """Child-process entry: ``python -m hapsim.emulated.driver_mock --fd N --spec JSON --rate R``
    (``--fd``: a pty's master; ``--listen``: an emulated link's listening socket instead,
    :mod:`hapsim.emulated.stamped_link`).

    Parameters
    ----------
    argv : list of str, optional
        The arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0 once served or stopped (the report written to ``--report``
        when the port opened), 2 when the board cannot be built (one line on stderr).

    Raises
    ------
    SystemExit
        Bad arguments (argparse, status 2).
    ValueError
        ``--spec`` or ``--faults`` not JSON.
    """
    import argparse

    from hapsim.scene import device_from_dict, excitation_from_dict
    p = argparse.ArgumentParser(prog="hapsim.emulated.driver_mock")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--fd", type=int)
    where.add_argument("--listen", type=int)
    p.add_argument("--spec", required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--report")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--options", default="{}")
    p.add_argument("--faults", default="{}")
    p.add_argument("--handled")
    a = p.parse_args(argv)
    spec = json.loads(a.spec)
    try:
        dev = build_board(spec["driver"], device_from_dict(spec["device"]),
                          excitation_from_dict(spec["excitation"]), a.rate, seed=a.seed,
                          options=json.loads(a.options))
    except (HapsimError, TypeError, ValueError) as exc:
        # said in one line where the host's terminal shows it (the host then finds its
        # port closed), not as a traceback
        print(f"hapsim: the emulated {spec['driver']} board cannot start: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        return 2
    _above_the_hosts()
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    from hapsim.spawn import HandledBytes
    fd, reader = a.fd, None
    if a.listen is not None:
        from hapsim.emulated.stamped_link import connection
        conn, reader = connection(a.listen, stop=lambda: flag["stop"])
        fd = None if conn is None else conn.fileno()
    rep = (serve(fd, dev, stop=lambda: flag["stop"], faults=json.loads(a.faults),
                 poll=0.02 if getattr(dev, "firmware", "") != "pde" else 1.0 / a.rate,
                 handled=HandledBytes(a.handled) if a.handled else None, stamped=reader)
           if fd is not None else None)
    if a.report and rep is not None:            # (None: stopped before the port opened)
        write_json(a.report, rep)
    return 0


class EmbeddedDriverMock(PtyChild):
    """A driver mock in a child process, on the master side of a new pty or on an emulated
    link (``link``).

    Parameters
    ----------
    driver : str
        Driver name (``"firefader"``).
    device, excitation
        What the mock models (:class:`hapsim.scene.Device`, :class:`~hapsim.scene.Excitation`).
    rate_hz : float
        Host rate [Hz] (one period per packet).
    seed : int
        Sensor-noise seed.
    options : dict, optional
        The mock device's own keywords (:class:`FireFaderDevice`: ``full_scale``,
        ``metres_per_count``, ``firmware``, ``touch``, ``boot_s``; :class:`HaplyDevice`:
        ``cpr``, ``motor_sign``): the hardware, which the host's driver may describe wrongly.
    faults : dict, optional
        :class:`ByteFaults` spec (and :func:`serve`'s ``slow`` hook).
    link : {"emulated", "pty"}, optional
        ``"emulated"`` (the default on the wall clock, :data:`WALL_LINK`): a Unix packet socket
        (``emulated://NAME``, :mod:`hapsim.drivers.urlhandler`) whose writes the board takes
        at the times the kernel stamped them with, as a board on its own processor takes
        its bytes when they come (:mod:`hapsim.emulated.stamped_link`); ``"pty"`` (the
        default in lockstep, whose time is the commands'): a pseudo-terminal, its bytes
        taken when the child reads them.

    Raises
    ------
    hapsim.errors.ConfigError
        A driver with no mock, an option out of the board's range (:func:`build_board`),
        or another ``link``.

    Attributes
    ----------
    port : str
        The port to open: the pty's slave path, or the link's URL.
    handled : hapsim.spawn.HandledBytes or None
        A lockstep mock's account of the bytes it has handled
        (``options["clock"]`` ``"lockstep"``, the default): for
        :class:`hapsim.drivers.transport.DriverTransport`; None on the wall clock.
    """

    handled = None

    def __init__(self, driver: str, device, excitation, rate_hz: float, *, seed: int = 0,
                 options: dict | None = None, faults: dict | None = None,
                 link: str | None = None) -> None:
        import dataclasses

        from hapsim.errors import ConfigError
        # the board's options checked here, by building it once, where the caller gets
        # the error with its key (in the child, a bad one stopped the board at its start
        # and the host found only a silent port)
        build_board(driver, device, excitation, rate_hz, seed=seed, options=options)
        lockstep = (options or {}).get("clock", "lockstep") == "lockstep"
        link = ("pty" if lockstep else WALL_LINK) if link is None else link
        if link not in ("emulated", "pty"):
            raise ConfigError(f"must be 'emulated' or 'pty', got {link!r}", key="link")
        master = (self.open_pty("hapsim-drvmock-") if link == "pty"
                  else self.open_link("hapsim-drvmock-"))
        spec = {"device": dataclasses.asdict(device), "excitation": dataclasses.asdict(excitation),
                "driver": driver}
        if not math.isfinite(spec["device"]["force_limit"]):
            spec["device"]["force_limit"] = None
        extra = []
        if lockstep:
            from hapsim.spawn import HandledBytes
            self.handled = HandledBytes.create()
            extra = ["--handled", self.handled.path]
        where = "--fd" if link == "pty" else "--listen"
        self.start([sys.executable, "-m", "hapsim.emulated.driver_mock", where, str(master), "--spec",
                    json.dumps(spec), "--rate", repr(float(rate_hz)), "--report",
                    self.report_path, "--seed", str(seed), "--options",
                    json.dumps(options or {}), "--faults", json.dumps(faults or {})]
                   + extra, master)

    def close(self) -> None:
        """As :meth:`hapsim.spawn.PtyChild.close`, and the handled account removed."""
        super().close()
        if self.handled is not None:
            self.handled.close(unlink=True)


if __name__ == "__main__":
    sys.exit(main())

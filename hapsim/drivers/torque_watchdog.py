"""The host's watchdog for a board that has none: zero force after a silence of the host.

A board whose firmware holds its last force until a write changes it (the Haply M3,
firmware V1.5: no watchdog; the Hapkit serial sketch: no silence rule) holds whatever the
host last wrote while the host does not run: a descheduled process, a page fault, a
garbage collection, a ``SIGSTOP``. The host loop cannot act while it does not run, so
:class:`TorqueWatchdog` runs beside it as its own small process (standard library only,
started in ~25 ms, asleep between checks, at a real-time priority above the loop's where
the OS permits it): when the host's last write left a non-zero force and the host has not
written for ``bound_s`` while armed (stalled, or running without writing), it writes the
driver's zero-force command to the port itself, once per silence. The port is a device
file it opens by path (a serial board), or a file of the host's it inherits (:data:`_SINKS`):
the Falcon's USB device file, libusb's own (its claim of the interface is that file's, so
the kernel takes the watchdog's bulk transfer), or the emulated FT232R's side channel,
each write stamped with its time.

No lock: the host, before each of its own writes, stamps a write under way on the shared
page and then takes the count of the watchdog's writes (:meth:`TorqueWatchdog.write`
returns them; before its reads too, :meth:`TorqueWatchdog.take`); after it, the write's
start, from which the silence counts. The watchdog checks both just before it writes
(waiting a check for a write under way, no longer), and counts a write *before* making
it: one counted when the host takes the count is taken as before the host's next write,
one counted later as after it. The order can be wrong only for a write counted between
the watchdog's last check and its first byte while the host wrote first (microseconds),
or for a host stopped inside its write longer than a check. (Counted after the syscall,
the window held the whole write.) A write the port refused is counted all the same and
tried again at the next check: a missing sample to the host, the conservative side. (A
lock around the host's write would let a host descheduled inside it hold the watchdog
off.) The host accounts the board's answers to the watchdog's writes
(:class:`hapsim.drivers.transport.DriverTransport`: each is a command of its own,
answered and dropped, a gap in ``seq``).

A write goes out whole: a command cut short would leave the board's parser inside it. A
port that takes part of a write and then no more for a second (a hung device) keeps the
rest, which is finished before anything else is written, never written again from its
start. The watchdog runs in a session of its own, so a terminal's Ctrl-C, Ctrl-Z or hang-up
meant for the host (its process group) neither stops nor kills it, and it ignores those
signals besides; ``SIGTERM`` ends its loop after the write in hand, never inside it.

The stated bound: a board is left holding a force without a write for at most ``bound_s``
plus the watchdog's check interval (``bound_s / 4``) plus its own wake-up latency, which
it measures (``longest_s``: the longest host silence up to the end of one of its writes,
which a watchdog preempted between its check and its write lengthens). For a board
without framing (``robust``), whose parser may have lost its place in the last bytes
before the host fell silent, with no evidence read yet to say so, the zero command may
reach no motor: the silence's second write, at :data:`ROBUST_AFTER` bounds, is the robust
one, at the last angle the host published (:meth:`TorqueWatchdog.angle`; a host publishes
one once its link has shown it loses bytes), so that such a board holds its force for at
most ``ROBUST_AFTER`` bounds plus a check and the latency. A robust write may also carry
no value (``robust=(data, None)``: the Haply 2DIY's re-arming at its fixed arming
offsets, two encoders; its host follows it with a re-arming of its own,
:mod:`hapsim.pipeline.haply2_record`): the host then says its link is lossy with
:meth:`TorqueWatchdog.lossy`.
The watchdog quits when its parent does: at once when the host had closed it or left no
force held, after one write when the host died (killed, crashed) armed with a force held
not yet answered, or answered by the zero command alone (a host stopped, then killed):
the robust one whenever there is one (no host is left to account a set-up, and the host
may have died in the very bytes that lost the board its place, before any evidence: a
2DIY whose parser lost its motors' addresses held a dead host's torque after its zero
command, tests/test_haply2_watchdog.py), else the zero command.

Layout of the shared page: native int64 fields, see ``_F``.
"""

from __future__ import annotations

import mmap
import os
import struct
import subprocess
import sys
import tempfile
import time

__all__ = ["TorqueWatchdog", "start_watchdog", "watchdog_report", "watchdog_text"]

#: Fields of the shared page (int64 each): the host's last write (monotonic ns), armed,
#: the time of the watchdog's last write (monotonic ns), the host write it answered, quit,
#: the longest silence seen before a write [ns], ready (1: running, < 0: -errno at start),
#: real-time priority granted (0: none), holding (the host's last write left a non-zero
#: force; written by the host alone: the watchdog marks a silence it answered by
#: ``fired_for``, the host write it followed, so that it never clears a hold the host set
#: just after its check), failed (writes the port refused, each tried again), suspect
#: (written by the host, one word: 0, the board in step, or ``1 << 32 | bits``, the board
#: may have lost its place and the robust write goes instead of the zero command,
#: carrying the float32 of those bits), counts (one word: ``fired << 32 | robust``, the
#: writes made and the robust ones among them, read by the host in one load), wrote_bits
#: (the float32 bits the last robust write carried), angle (written by the host: 0, or
#: ``1 << 32 | bits``, its last angle read, which a long silence's robust write carries)
#: robust_for (the host write whose silence had its robust write), overslept_ns (its
#: largest wake-up past a check's end) and acted_ns (its longest time from a wake-up to
#: the write it then made: its own descheduling after waking, a dying host's write too),
#: dying_ns (when it began its write for a host that died armed: 0 before), writing (the
#: host's time as it takes the count before a write, 0 once written).
_F = {k: i for i, k in enumerate(("beat", "armed", "fired_ns", "fired_for", "quit",
                                  "longest_ns", "ready", "rt", "holding", "failed",
                                  "suspect", "counts", "wrote_bits", "angle",
                                  "robust_for", "overslept_ns", "acted_ns", "dying_ns",
                                  "writing"))}
_SIZE = 8 * len(_F)
_F32 = struct.Struct("<f")
#: The sinks a watchdog writes to besides a device file it opens by path, each an
#: inherited file descriptor: ``usbfs`` (a USB device's file under ``/dev/bus/usb``,
#: libusb's own, and the bulk OUT endpoint: the Falcon's FT232R), ``stamped`` (a pipe to
#: an emulated chip, each write after its monotonic time [ns], 8 bytes little endian:
#: :meth:`hapsim.emulated.ftdi_usb.VirtualFT232R.side_channel`), ``packet`` (an emulated
#: link's socket, :mod:`hapsim.drivers.urlhandler`: a packet a write, kernel-stamped).
_SINKS = ("usbfs", "stamped", "packet")
#: The usbfs transfer's timeout [ms]: a full-speed bulk OUT of one packet takes one
#: frame (1 ms); a chip that NAKs longer (its FIFO full) is not waited for.
USBFS_TIMEOUT_MS = 10
#: How long the host waits for the watchdog process to start [s].
START_TIMEOUT_S = 3.0
#: A silence's robust write, for a board without framing, comes at this many bounds of
#: silence (module notes): after the zero command, at the first bound, had two bounds to
#: be answered by a record the host would have read had it run.
ROBUST_AFTER = 3
#: How long a write that a port took part of waits for the port to take the rest [s]
#: before the watchdog keeps it for its next checks (module notes).
REST_S = 1.0


class _Page:
    """The shared page: int64 fields by name, each read and written whole.

    Through a ``memoryview`` cast to the native ``q``: an item is copied as one aligned
    8-byte word. (``struct.pack_into("<q", ...)`` writes its bytes one at a time, and the
    other process once read a time stamp half written: a silence of 83,344 s, and a zero
    write no silence called for.)
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.mm = mmap.mmap(fd, _SIZE)
        self.v = memoryview(self.mm).cast("q")

    def get(self, k: str) -> int:
        return self.v[_F[k]]

    def set(self, k: str, v: int) -> None:
        self.v[_F[k]] = int(v)


class TorqueWatchdog:
    """The host's side of the watchdog process (module notes).

    Parameters
    ----------
    port : str
        The port's path (a device file: ``/dev/ttyACM0``, a pseudo-terminal).
    zero : bytes
        The driver's zero-force command (one write, answered by one record).
    bound_s : float
        Host silence after which the watchdog writes ``zero`` [s], > 0.
    rt_priority : int
        ``SCHED_FIFO`` priority the watchdog asks for (0: none); refused quietly where
        the OS does not permit it (:attr:`rt` says what it got).
    sink : tuple, optional
        Instead of opening ``port`` (then only named in messages): ``(kind, fd, *args)``,
        a file descriptor of this process the watchdog inherits and writes to,
        ``("usbfs", fd, endpoint)``, ``("stamped", fd)`` or ``("packet", fd)`` (an
        emulated link's socket, :mod:`hapsim.drivers.urlhandler`; :data:`_SINKS`).
    robust : (bytes, int or None), optional
        For a board without framing: ``(data, index)``, the write that zeroes the force
        whatever the board's parser is inside (the driver's ``stop_bytes``: zero writes
        around a set-up), written instead of ``zero`` while the host says the board may
        have lost its place (:meth:`suspect`), with the float32 at ``index`` (little
        endian: the set-up's encoder offset) replaced by the host's value
        (:meth:`suspect`'s ``value``). ``zero`` reaches no motor on a board whose parser
        lost the motor's address (a reset read out of a torque's bytes): 1.5 % of the
        parser's states under 1 byte in 200 lost (tests/test_host_watchdog.py).
        ``index`` None: the write carries no value, written as it is (the 2DIY's
        re-arming at its arming offsets; :meth:`lossy` instead of :meth:`angle`).

    Attributes
    ----------
    bound_s : float
    check_s : float
        The watchdog's check interval [s] (``bound_s / 4``).
    robust : bool
        It has a robust write.

    Raises
    ------
    ValueError
        ``bound_s`` not positive, an unknown sink, a robust write's index outside it.
    OSError
        The watchdog process did not start (its reason: it could not open ``port``, or
        did not answer within :data:`START_TIMEOUT_S`); nothing is left running.
    """

    def __init__(self, port: str, zero: bytes, bound_s: float, rt_priority: int = 11, *,
                 sink: tuple | None = None, robust: tuple | None = None) -> None:
        if not bound_s > 0:
            raise ValueError(f"bound_s must be > 0, got {bound_s!r}")
        if (robust is not None and robust[1] is not None
                and not 0 <= int(robust[1]) <= len(robust[0]) - 4):
            raise ValueError(f"the robust write's value index {robust[1]!r} is not within "
                             f"its {len(robust[0])} bytes")
        target, fds = port, ()
        if sink is not None:
            kind, fd_sink = sink[0], int(sink[1])
            if kind not in _SINKS:
                raise ValueError(f"unknown sink {kind!r}; valid: {', '.join(_SINKS)}")
            target = ":".join(["fd", str(fd_sink), kind, *map(str, sink[2:])])
            fds = (fd_sink,)
        self.bound_s = float(bound_s)
        self.check_s = self.bound_s / 4
        #: Whether it has a robust write (``robust`` given).
        self.robust = robust is not None
        self._taken = 0
        self._robust_taken = 0
        self._robust_new = 0
        self._wrote = 0.0
        base = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, path = tempfile.mkstemp(prefix="hapsim-watchdog-", dir=base)
        try:
            os.write(fd, b"\0" * _SIZE)
            self._page = _Page(fd)
            self._proc = subprocess.Popen(
                [sys.executable, "-I", "-S", os.path.abspath(__file__), path, target,
                 zero.hex(), str(int(self.bound_s * 1e9)), str(os.getpid()),
                 str(int(rt_priority)), robust[0].hex() if robust else "",
                 str(int(robust[1])) if robust and robust[1] is not None else "-1"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL, close_fds=True, pass_fds=fds,
                start_new_session=True)     # (a terminal's signals are the host's)
            end = time.monotonic() + START_TIMEOUT_S
            while self._page.get("ready") == 0 and time.monotonic() < end:
                if self._proc.poll() is not None:
                    break
                time.sleep(1e-3)
            ready = self._page.get("ready")
            if ready != 1:
                self._kill()
                why = (os.strerror(-ready) if ready < 0 else
                       "it did not start in time" if self._proc.returncode is None else
                       f"it exited with {self._proc.returncode}")
                raise OSError(f"the host watchdog could not take {port}: {why}")
        except BaseException:
            # (nothing left running or open by a watchdog not started: Ctrl-C here too)
            if getattr(self, "_proc", None) is not None and self._proc.returncode is None:
                self._kill()
            os.close(fd)
            raise
        finally:
            os.unlink(path)                 # both ends hold it open: gone with them
        #: The ``SCHED_FIFO`` priority the watchdog runs at (0: normal scheduling).
        self.rt = self._page.get("rt")
        self.missed, self.missed_s = 0, 0.0   # (silences it did not run in: report)
        # (the last write's start [ns], -1 none; its hold; the writes then: hold())
        self._prev_ns, self._prev_held, self._prev_fired = -1, False, 0
        self._missed_ns = int((self.bound_s + self.check_s) * 1e9)

    def arm(self, on: bool = True) -> None:
        """Arm or disarm the watchdog.

        Parameters
        ----------
        on : bool
            True: the run's CONFIG (a force may be held from now); False: STOP, close, a
            re-arming's listening (where the host waits on purpose).
        """
        p = self._page
        p.set("beat", time.monotonic_ns())
        p.set("armed", 1 if on else 0)
        self._prev_ns = -1

    def take(self) -> tuple:
        """The writes the watchdog made since the last call (the host reads): the zero
        command, or the robust write (:meth:`take_robust` says how many).

        Returns
        -------
        tuple of int
            Their monotonic times [ns] (in practice at most one: one write per silence;
            the last one's time for each when several came in one silence of the host);
            ``()`` when none (nothing allocated: it runs each tick of a real-time loop).
        """
        p = self._page
        c = p.get("counts")                 # (one load: the writes and the robust ones)
        n = (c >> 32) - self._taken
        if not n:
            return ()
        self._taken += n
        rob = c & 0xFFFFFFFF
        if rob != self._robust_taken:
            self._robust_new += rob - self._robust_taken
            self._robust_taken = rob
            self._wrote = _F32.unpack(p.get("wrote_bits").to_bytes(4, "little"))[0]
        return (p.get("fired_ns"),) * n

    def take_robust(self) -> tuple:
        """How many of the writes :meth:`take` returned since the last call were the
        robust one, and the value the last of them carried (the host reads it after
        :meth:`take`).

        Returns
        -------
        (int, float)
        """
        n, self._robust_new = self._robust_new, 0
        return n, self._wrote

    def suspect(self, on: bool, value: float = 0.0) -> None:
        """Whether the board may have lost its place in the byte stream (the robust write
        then goes instead of the zero command), and the value that write carries.

        Parameters
        ----------
        on : bool
        value : float
            The float32 the robust write carries at its index (the set-up's encoder
            offset [deg]: the joint's last angle read).
        """
        self._page.set("suspect", (1 << 32 | int.from_bytes(_F32.pack(value), "little"))
                       if on else 0)        # (one store: the flag and its value together)

    def angle(self, value: float) -> None:
        """The host's last angle read, which the robust write of a long silence carries
        (module notes; a watchdog without a robust write ignores it).

        Parameters
        ----------
        value : float
            The joint's last angle read [deg] (the set-up's encoder offset).
        """
        self._page.set("angle", 1 << 32 | int.from_bytes(_F32.pack(value), "little"))

    def lossy(self) -> None:
        """The host's link has shown it loses bytes: a long silence's robust write goes
        (:data:`ROBUST_AFTER`), for a robust write that carries no value (``robust=(data,
        None)``; :meth:`angle` for one that does)."""
        self._page.set("angle", 1 << 32)

    def write(self, ser, data: bytes, holding: bool, beaten: bool = False) -> tuple:
        """The host writes ``data``: its time stamped first (the silence the watchdog
        counts is between the host's writes: a host that runs but does not write leaves
        the board holding too), the watchdog's writes made since taken just before it.

        Parameters
        ----------
        ser : serial.Serial or serial-like
            The port (``write``); its exceptions pass through.
        data : bytes
        holding : bool
            ``data`` leaves a non-zero force (a zero force is no hold: no zero write
            follows it).
        beaten : bool
            :meth:`beat` was called for this write (a caller that chose ``data`` from the
            writes it took): not again.

        Returns
        -------
        tuple of int
            As :meth:`take`: the watchdog's writes that went out before ``data``
            (none when ``beaten``).
        """
        times = () if beaten else self.beat()
        if holding:
            self.hold(True)                 # (from before the write: a stop inside it)
        began = time.monotonic_ns()
        ser.write(data)
        self.hold(holding, began)           # (the silence from the write's start)
        return times

    def beat(self) -> tuple:
        """The first half of :meth:`write`: the host's write under way stamped (the
        watchdog waits a check for it), the watchdog's writes made since taken (as
        :meth:`take`'s: a tuple of int)."""
        self._page.set("writing", time.monotonic_ns())
        return self.take()

    def hold(self, holding: bool, began_ns: int | None = None) -> None:
        """The second half of :meth:`write` (``began_ns``): whether the write just made
        leaves a non-zero force, the silence counted from its start; before one, the flag.

        Parameters
        ----------
        holding : bool
            The host's write leaves a non-zero force (set True before a write that
            does, and again after it: a host stopped inside the write leaves it held).
        began_ns : int, optional
            When the write began (``time.monotonic_ns()`` just before it).

        Notes
        -----
        The silence runs from the last write's start, not from :meth:`beat`'s stamp
        (docs/drivers.md). A host stopped inside a write that writes its stale force when
        it runs again starts a new silence, with a write of its own (an independent M3
        model: tools/independent_boards, docs/testing.md).
        """
        p = self._page
        p.set("holding", 1 if holding else 0)
        if began_ns is None:
            return
        p.set("beat", began_ns)
        p.set("writing", 0)
        fired = p.get("counts") >> 32       # (missed silences: nothing allocated)
        gap = began_ns - self._prev_ns
        if (self._prev_ns >= 0 and self._prev_held and fired == self._prev_fired
                and gap > self._missed_ns):
            self.missed += 1
            self.missed_s = max(self.missed_s, gap * 1e-9)
        self._prev_ns, self._prev_held, self._prev_fired = began_ns, holding, fired

    def report(self) -> dict:
        """What the watchdog did.

        Returns
        -------
        dict
            ``fired`` (writes made: the zero command or the robust write), ``failed``
            (writes the sink refused, each counted in ``fired`` and tried again at the
            next check), ``longest_s`` (the longest host silence up to the end of a
            write the watchdog made [s], 0 without one: the stated bound's measured
            part), ``bound_s``, ``check_s``, ``rt_priority`` (granted; 0: none),
            ``robust`` (of the writes, those that were the robust one), ``overslept_s``
            (its largest wake-up past a check's end [s]: how late its own scheduling
            made it, beside ``check_s`` in the bound it keeps), ``acted_s`` (its longest
            time from a wake-up to the write it made then [s], the dying host's write
            included), ``missed``, ``missed_s`` (the host's silences past the bound and a
            check with a force held and no write, the watchdog not run; the longest [s]:
            the stated bound is ``bound_s + check_s`` and the latency, or these).
        """
        p = self._page
        c = p.get("counts")
        return {"fired": c >> 32, "failed": p.get("failed"), "robust": c & 0xFFFFFFFF,
                "longest_s": p.get("longest_ns") * 1e-9, "bound_s": self.bound_s,
                "check_s": self.check_s, "rt_priority": self.rt,
                "overslept_s": p.get("overslept_ns") * 1e-9,
                "acted_s": p.get("acted_ns") * 1e-9, "missed": self.missed,
                "missed_s": self.missed_s}

    def _kill(self) -> None:
        """End the watchdog process: its loop sees ``quit`` within a check; ``SIGTERM``
        (which ends its loop after the write in hand, never inside it) if it has not
        within 0.1 s; ``SIGKILL`` if it still has not when a write's rest would have
        had its time (:data:`REST_S`)."""
        self._page.set("quit", 1)
        for stop, wait in ((None, 0.1), (self._proc.terminate, REST_S + 0.5),
                           (self._proc.kill, None)):
            if stop is not None:
                stop()
            try:
                self._proc.wait(timeout=wait)
                return
            except subprocess.TimeoutExpired:
                continue

    def close(self) -> None:
        """Stop the watchdog process (disarmed first; idempotent). The shared page's file
        is closed; its mapping stays, so :meth:`report` and :meth:`take` still read it."""
        if self._proc.returncode is None:
            self._page.set("armed", 0)
            self._kill()
        if self._page.fd is not None:
            os.close(self._page.fd)
            self._page.fd = None


def start_watchdog(port: str, zero: bytes, bound_s: float, *, sink: tuple | None = None,
                   robust: tuple | None = None, ser=None):
    """A :class:`TorqueWatchdog` on ``port`` (or ``sink``), or the reason it could not
    start.

    Parameters
    ----------
    port : str
        The port's path (with ``sink``: only its name in messages).
    zero : bytes
        The driver's zero-force command.
    bound_s : float
        The host's silence after which the watchdog writes ``zero`` [s]
        (:data:`hapsim.drivers.resync.HOLD_BOUND_S`).
    sink : tuple, optional
        :class:`TorqueWatchdog`'s ``sink``: an inherited file instead of ``port``.
    robust : (bytes, int or None), optional
        :class:`TorqueWatchdog`'s ``robust``.
    ser : serial.SerialBase, optional
        The host's open port: on an emulated link (``emulated://NAME``, no device file,
        :mod:`hapsim.drivers.urlhandler`) the watchdog writes to its socket (the sink
        ``("packet", fd)``).

    Returns
    -------
    (TorqueWatchdog or None, str or None)
        The watchdog, or None and why not (a port that is no device file: a URL, a
        socket; a process that could not start).
    """
    if sink is None and ser is not None:
        from hapsim.drivers.urlhandler import is_emulated
        if is_emulated(port):
            sink = ("packet", ser.fileno())
    if sink is None and not os.path.exists(port):
        return None, f"{port} is not a device file"
    try:
        return TorqueWatchdog(port, zero, bound_s, sink=sink, robust=robust), None
    except OSError as exc:
        return None, str(exc)


def watchdog_report(watchdog, why) -> dict:
    """What a run reports of its watchdog.

    Parameters
    ----------
    watchdog : TorqueWatchdog or None
    why : str or None
        Why there is none (:func:`start_watchdog`'s reason).

    Returns
    -------
    dict
        ``{"running": True, **watchdog.report()}``, or ``{"running": False, "why": why}``.
    """
    if watchdog is None:
        return {"running": False, "why": why}
    return {"running": True, **watchdog.report()}


def watchdog_text(rep: dict, what: str = "zero force") -> str:
    """One line of a run's report on its watchdog.

    Parameters
    ----------
    rep : dict
        :func:`watchdog_report`'s.
    what : str
        What the watchdog writes (``"zero force"``, ``"the zero command"``).

    Returns
    -------
    str
        ``host watchdog: ...``: the writes, the longest silence one ended and the bound,
        or none and why.
    """
    if not rep.get("running"):
        return f"host watchdog: none ({rep.get('why')})"
    failed = f", {rep['failed']} writes refused" if rep.get("failed") else ""
    if rep.get("robust"):
        failed += (f", {rep['robust']} of them with the set-up around it (the board may "
                   "have lost its place)")
    if rep.get("missed"):
        failed += (f"; {rep['missed']} host silences got none, the watchdog not run "
                   f"(the longest {rep['missed_s'] * 1e3:.1f} ms: the board held its force "
                   "that long)")
    return (f"host watchdog: {what} written {rep['fired']} times{failed}, the longest host "
            f"silence one ended {rep['longest_s'] * 1e3:.1f} ms (bound "
            f"{rep['bound_s'] * 1e3:g} ms + {rep['check_s'] * 1e3:g} ms checks)")


def _usbfs_writer(fd: int, ep: int):
    """A write of bytes to bulk OUT endpoint ``ep`` through a usbfs file ``fd`` (the
    Linux kernel's ``USBDEVFS_BULK``: ``struct usbdevfs_bulktransfer {unsigned int ep,
    len, timeout; void *data;}``, ``linux/usbdevice_fs.h``), standard library only. The
    fd is libusb's own, inherited: its claim of the interface is this file's, so the
    kernel takes the transfer; one transfer of at most 64 bytes is one full-speed bulk
    packet, never interleaved with the host's."""
    import ctypes
    import fcntl
    req = (3 << 30) | (struct.calcsize("@IIIP") << 16) | (ord("U") << 8) | 2   # _IOWR('U', 2)

    def write(data: bytes, patience: float = 0.0) -> None:
        buf = ctypes.create_string_buffer(bytes(data), len(data))
        arg = bytearray(struct.pack("@IIIP", ep, len(data), USBFS_TIMEOUT_MS,
                                    ctypes.addressof(buf)))
        fcntl.ioctl(fd, req, arg, True)     # (buf lives through the call)
        return b""                          # (one packet: whole)
    return write


def _write_whole(fd: int, data: bytes, patience: float = 0.0,
                 rest_s: float = REST_S) -> bytes:
    """Write ``data`` to a non-blocking ``fd`` whole, or none of it: a command cut short
    would leave the board's parser inside it, reading the next bytes wrongly.

    Parameters
    ----------
    fd : int
        A non-blocking file descriptor (a tty).
    data : bytes
    patience : float
        How long a port that takes none of it is waited for [s] (0: not at all).
    rest_s : float
        Once a byte has gone, how long the rest is waited for [s].

    Returns
    -------
    bytes
        The rest the port did not take within ``rest_s`` (``b""``: all of it went):
        the caller finishes it before it writes anything else, never from its start.

    Raises
    ------
    BlockingIOError
        The port took none of it within ``patience`` (counted, tried again).
    OSError
        The port failed.
    """
    import select
    view = memoryview(bytes(data))
    first = time.monotonic() + float(patience)
    end = None
    while view:
        try:
            n = os.write(fd, view)
        except BlockingIOError:
            n = 0
        if n:
            view = view[n:]
            end = end or time.monotonic() + rest_s
            continue
        now = time.monotonic()
        if end is None and now >= first:
            raise BlockingIOError("the port took none of the write")
        if end is not None and now >= end:
            return bytes(view)
        select.select([], [fd], [], 0.005)
    return b""


def _writer(port: str):
    """The watchdog's write of bytes, ``write(data, patience=0.0) -> rest``: to a device
    file opened by path (:func:`_write_whole`), or to a file descriptor inherited
    (``fd:N:KIND[:ARG]``, :data:`_SINKS`: one transfer, one pipe write, whole)."""
    if not port.startswith("fd:"):
        # (non-blocking: a full buffer or a hung device refuses the write, counted and
        # tried again at the next check; a write the port took part of waits REST_S for
        # the rest at most, then keeps it for the next checks)
        fd = os.open(port, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
        return lambda data, patience=0.0: _write_whole(fd, data, patience)
    _, n, kind, *arg = port.split(":")
    fd = int(n)
    os.fstat(fd)                        # (OSError EBADF: not inherited)
    if kind == "usbfs":
        return _usbfs_writer(fd, int(arg[0]))
    if kind == "packet":
        # the emulated link's socket (hapsim.drivers.urlhandler): a write is one packet,
        # taken whole or refused, as a tty's is written whole
        os.set_blocking(fd, False)
        return lambda data, patience=0.0: _write_whole(fd, data, patience)
    # "stamped": the emulated chip's side channel, each write its monotonic time first
    def stamped(data: bytes, patience: float = 0.0) -> bytes:
        os.write(fd, time.monotonic_ns().to_bytes(8, "little") + data)  # (<= PIPE_BUF)
        return b""
    return stamped


def _serve(path: str, port: str, zero: bytes, bound_ns: int, parent: int, rt: int,
           robust: bytes = b"", at: int = -1, stop: list | None = None) -> None:
    """The watchdog process (module notes); ``stop`` non-empty ends its loop (the
    process's ``SIGTERM``, :func:`_signals`)."""
    page = _Page(os.open(path, os.O_RDWR))
    stop = [] if stop is None else stop

    def data(late: bool, dying: bool = False) -> tuple:
        """The write to make, whether it is the robust one and its value's bits: the
        robust one while the host suspects the board lost its place, its value patched
        in, or in a long silence (``late``) at the host's last angle, or for a host that
        died (``dying``: at its last value if any, else as it is); else the zero command.
        A robust write with no value (``at`` < 0) is written as it is."""
        word = page.get("suspect") if robust else 0
        if not word and (late or dying) and robust:
            word = page.get("angle")
        if not word and dying and robust:
            word = 1 << 32 | int.from_bytes(robust[at:at + 4], "little") if at >= 0 \
                else 1 << 32
        if word:
            bits = word & 0xFFFFFFFF
            if at < 0:
                return robust, 1, bits
            return robust[:at] + bits.to_bytes(4, "little") + robust[at + 4:], 1, bits
        return zero, 0, 0
    try:
        write = _writer(port)
    except OSError as exc:
        page.set("ready", -(exc.errno or 5))
        return
    got = 0
    if rt > 0 and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt))
            got = rt
        except (OSError, PermissionError):
            pass
    page.set("rt", got)
    page.set("ready", 1)
    check = bound_ns / 4e9
    rest = b""                              # (a write the port took part of: its rest)

    def finish(patience: float) -> bytes:
        try:
            return write(rest, patience)
        except BlockingIOError:
            return rest
        except OSError:
            return b""                      # (the port failed: nothing more goes)

    def held() -> bool:
        """Armed, with a force held or a board that may have lost its place."""
        return bool(page.get("armed") and (page.get("holding")
                                           or (robust and page.get("suspect"))))
    def acted(woke: int) -> None:
        """Note the time from a wake-up to the write about to start."""
        took = time.monotonic_ns() - woke
        if took > page.get("acted_ns"):
            page.set("acted_ns", took)
    woke = time.monotonic_ns()
    while not stop and not page.get("quit") and os.getppid() == parent:
        t_sleep = time.monotonic_ns()
        time.sleep(check)
        # how late its own scheduling woke it (before the parent's death is seen: a
        # dying host's write is as late as this)
        woke = time.monotonic_ns()
        over = woke - t_sleep - bound_ns // 4
        if over > page.get("overslept_ns"):
            page.set("overslept_ns", over)
        if rest:
            rest = finish(0.0)              # (before anything else)
            continue
        if not held():
            continue
        beat = page.get("beat")
        now = time.monotonic_ns()
        if now - beat <= bound_ns:
            continue
        late = page.get("fired_for") == beat
        if late and not (robust and page.get("robust_for") != beat
                         and now - beat > ROBUST_AFTER * bound_ns):
            continue
        if page.get("beat") != beat or not held():
            continue                        # (the host wrote meanwhile, or holds nothing)
        w = page.get("writing")
        if w and now - w <= bound_ns // 4:
            continue                        # (a host write under way: a check for it)
        out, rob, bits = data(late)
        if late and not rob:
            continue                        # (no angle published: no robust write)
        # counted before the write (module notes): its time, its silence, its kind
        was = page.get("fired_for")
        page.set("fired_ns", time.monotonic_ns())
        page.set("fired_for", beat)
        page.set("longest_ns", max(page.get("longest_ns"), now - beat))
        if rob:
            page.set("robust_for", beat)
            page.set("wrote_bits", bits)
        page.set("counts", page.get("counts") + (1 << 32) + rob)  # (the host reads this)
        acted(woke)
        try:
            rest = write(out)
        except OSError:
            page.set("failed", page.get("failed") + 1)
            page.set("fired_for", was)      # (tried again at the next check)
            if rob:
                page.set("robust_for", 0)
        else:
            # the silence to the write's end: a watchdog preempted between its check and
            # its write (by a real-time task above it) left the board that much longer
            # (the bound it states holds up to the write, not up to the check)
            page.set("longest_ns", max(page.get("longest_ns"), time.monotonic_ns() - beat))
    if rest:
        rest = finish(REST_S)
    beat = page.get("beat")
    if (not stop and not page.get("quit") and held()
            and (page.get("fired_for") != beat
                 or (robust and page.get("robust_for") != beat))):
        # the host died (killed, crashed) armed, its last force not yet zeroed (or by the
        # zero command alone, which a board that lost its place does not take: a host
        # stopped, then killed): held until someone writes; the port is ours. The robust
        # write when there is one: the host may have died in the bytes that lost it
        try:
            out = data(False, dying=True)[0]
            acted(woke)
            page.set("dying_ns", time.monotonic_ns())
            write(out, 1.0)                 # (a full buffer waited for, 1 s at most)
        except OSError:
            pass


def _signals() -> list:
    """The watchdog process's signals (module notes): a terminal's ignored (its own
    session already keeps them the host's), ``SIGTERM`` noted in the list returned,
    which ends the loop after the write in hand, never inside it."""
    import signal
    stop: list = []
    for sig in ("SIGINT", "SIGHUP", "SIGTSTP", "SIGTTOU", "SIGTTIN", "SIGQUIT"):
        if hasattr(signal, sig):
            signal.signal(getattr(signal, sig), signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    return stop


if __name__ == "__main__":
    a = sys.argv[1:]
    _serve(a[0], a[1], bytes.fromhex(a[2]), int(a[3]), int(a[4]), int(a[5]),
           bytes.fromhex(a[6]) if len(a) > 6 else b"", int(a[7]) if len(a) > 7 else -1,
           stop=_signals())

"""The host's watchdog in the transport: its writes accounted as commands (issue 29;
:class:`Watched`, a base of :class:`hapsim.drivers.transport.DriverTransport`).

A driver whose board holds its force longer than the hold bound with no write
(:attr:`hapsim.drivers.base.Driver.holds_force_s`: the Haply M3, firmware V1.5, no
watchdog; the Hapkit serial sketch, no silence rule; the FireFader's ``.ino``, whose
silence rule acts after 0.1 s), on a board that keeps its own clock, runs with a
:class:`hapsim.drivers.torque_watchdog.TorqueWatchdog` beside the host: when the host does
not write for :data:`hapsim.drivers.resync.HOLD_BOUND_S` while armed and its last write
left a non-zero force, the watchdog writes the driver's zero-force command itself (the
host stalled: descheduled, stopped, paging; or it ran without writing). Every write of the host and every read takes the watchdog's writes made
since (the order on the wire: :mod:`hapsim.drivers.torque_watchdog`, module notes): each
is a command of its own, numbered after the host's last, stamped with the watchdog's
time; the board answers it in order, and its answer is dropped (counted
``watchdog_replies``): a gap in ``seq``, as a re-synchronisation's, so no measurement
runs across it (the 2DIY's record loop and the FireFader's two-fader loop account them
their own way: :mod:`hapsim.pipeline.haply2_record`, :mod:`hapsim.pipeline.faders_run`).
A lockstep mock (its time is the commands') has none; nor has a port that
is no device file (the report says why).

**A board that may have lost its place.** The zero command reaches no motor on an
unframed board whose parser lost the motor's address (the Haply M3: a reset read out of a
torque's bytes after a lost byte; 1.5 % of the parser's states under 1 byte in 200 lost),
and a host stalled then left its torque held for the whole stall (301 ms in a wall-clock
run whose watchdog wrote at 20 ms). While the transport has evidence pending that the
board lost its place (bytes read since the last record that made none), it tells the
watchdog so (:meth:`TorqueWatchdog.suspect
<hapsim.drivers.torque_watchdog.TorqueWatchdog.suspect>`), and the watchdog writes the
driver's stop instead (:meth:`hapsim.drivers.base.Driver.stop_bytes`: for the Haply board
its re-synchronisation, zero torque whatever the parser is inside, the set-up at the
host's last angle): a re-synchronisation made by the watchdog, counted as one (reason
``watchdog``), answered twice, a gap in ``seq``. A board that lost its place in the last
bytes before the host fell silent, before any evidence was read, takes no zero command:
on a link that has shown it loses bytes (a damaged reply, a desync, a
re-synchronisation: the evidence of the run so far), the silence's second write, at
:data:`hapsim.drivers.torque_watchdog.ROBUST_AFTER` bounds, is the robust one at the last
angle the transport published
(:meth:`TorqueWatchdog.angle <hapsim.drivers.torque_watchdog.TorqueWatchdog.angle>`, at
each new record), accounted the same way (the robust writes of a take are its last).
"""

from __future__ import annotations

import math
import time

from hapsim.drivers.resync import HOLD_BOUND_S, RING

#: The longest wait at a STOP for the answers the watchdog's last writes owe, beyond the
#: board's round trip [s] (:meth:`Watched._wd_stop`): an emulated board's thread beside
#: the suite's other workers may not run for tens of ms (10 ms left one unread in a
#: fresh clone's CI, the FireFader's, fired 2, answered 1).
STOP_WAIT_S = 0.1

__all__ = ["Watched", "robust_stop", "STOP_WAIT_S"]


class Watched:
    """The transport's side of the host watchdog (module notes).

    Attributes
    ----------
    watchdog : hapsim.drivers.torque_watchdog.TorqueWatchdog or None
    """

    def _init_watchdog(self, driver, port: str, own_clock: bool) -> None:
        """Start the watchdog for a board that holds a force longer than the hold bound
        (``driver.holds_force_s``) and keeps its own clock; else none, with the reason in
        :meth:`_watchdog_report`."""
        self.watchdog = None
        self._wd_cmds: set = set()
        self._wd_why = None
        self._wd_zero = b""                 # (its zero command's bytes, once started)
        self._wd_robust = self._wd_suspect = False
        self._wd_angle_s = -1               # (the record whose angle was published)
        self._wd_lossy = False              # (the link has shown it loses bytes)
        self._wd_base = None                # (its counts at the first record)
        if driver.holds_force_s <= HOLD_BOUND_S:
            self._wd_why = "the board zeroes its force itself within the hold bound"
            return
        if not own_clock:
            self._wd_why = "a lockstep mock: its time is the commands'"
            return
        from hapsim.drivers.torque_watchdog import start_watchdog
        robust = robust_stop(driver)
        self._wd_zero = driver.encode_force(0.0)
        self.watchdog, self._wd_why = start_watchdog(port, self._wd_zero, HOLD_BOUND_S,
                                                     robust=robust, ser=self._ser)
        self._wd_robust = self.watchdog is not None and robust is not None

    def _wd_take(self, times: tuple) -> None:
        """The watchdog's writes ``times`` (monotonic ns), made after the host's last
        command: commands of their own (module notes); its robust writes, the last ones
        when there are any, re-synchronisations of its own (:meth:`_wd_resynced`)."""
        if not times:
            return
        own = self._cmd                     # the host's last command before them
        robust, value = self.watchdog.take_robust()
        for i, t_ns in enumerate(times):
            self._cmd += 1
            self._sent_us[self._cmd % RING] = (t_ns - self._t0) // 1000
            # its bytes, which an answer's echo names (late_replies): the zero command,
            # or a robust write's (no command of the driver's: it names nothing)
            self._sent_bytes[self._cmd % RING] = (b"" if i >= len(times) - robust
                                                  else self._wd_zero)
            self._wd_cmds.add(self._cmd)
            self.stats["watchdog_zeroed"] += 1
            self._force = 0.0
            # (one write per silence: several in one take share its time, and the robust
            # ones are taken to be the last)
            if i >= len(times) - robust:
                self._wd_resynced(own, math.radians(value), t_ns)

    def _wd_resynced(self, own: int, x_set: float, t_ns: int) -> None:
        """The watchdog's write just numbered was the driver's stop (module notes), made
        at ``t_ns`` after the host's command ``own``: the board set up again at ``x_set``
        [rad], its zero writes around the set-up answered twice (a second command number,
        dropped too), the host's commands before it missing unless answered, and a
        re-synchronisation counted (``watchdog``) with the bound of its frame's error:
        the joint's reach from the last record to the write at the host's estimate
        (:meth:`hapsim.drivers.resync.Resynchronising._frame_error_bound`), plus the
        estimate's distance from ``x_set``."""
        self._t_resync = self._clock()
        self._resync_times.append(self._t_resync)
        self.stats["resyncs"] += 1
        why = self.stats["resync_reasons"]
        why["watchdog"] = why.get("watchdog", 0) + 1
        x = self._extrapolate(own + 1)
        self.stats["frame_bound"] += (
            self._frame_error_bound(x, at_us=(t_ns - self._t0) // 1000)
            + abs(x_set - (self._x_last if x != x else x)))
        self._rx_since_record = 0
        self._wd_suspect = False            # (the watchdog's next write: the zero command)
        self.watchdog.suspect(False)
        self._floor = min(self._floor, own - 1)
        self._cmd += 1
        self._sent_us[self._cmd % RING] = self._sent_us[(self._cmd - 1) % RING]
        self._sent_bytes[self._cmd % RING] = b""      # a number, no write of its own
        self._wd_cmds.add(self._cmd)
        if self._answered < own:            # the host's commands before it: missing
            self.stats["missing"] += own - self._answered
            self._answered = own

    def _wd_note(self) -> None:
        """Tell the watchdog whether the board may have lost its place (module notes),
        for a driver with a robust write, on a change only: bytes read since the last
        record that made none, once a record has given an angle; cleared when a record
        comes. The robust write would set the board up at the last angle read, which is
        also published at each new record once the link has shown it loses bytes (the
        robust write of a long silence carries it; on a link that has lost none a
        parser never loses its place, and a long silence costs no re-synchronisation). (Set only at a host command, the rule missed boards that lost their place
        just before a stall: one held a torque 94 ms of a 300 ms stall, the watchdog's
        zero command at 25 ms. A reply split across two reads sets it until its rest is
        read, at most a read period: a stall of the hold bound must begin exactly there
        to make a needless set-up.)"""
        if not self._wd_robust:
            return
        on = self._rx_since_record > 0 and self._s_last >= 0
        # (a link that has shown it loses bytes since the first record: a damaged reply,
        # a desync, a re-synchronisation; a reply split across two reads is no such
        # evidence, nor the bytes before the arming's first record; on a link that
        # loses none a parser never loses its place)
        seen = (self._damaged, self._desyncs, self.stats["resyncs"])
        if self._wd_base is None and self._s_last >= 0:
            self._wd_base = seen
        self._wd_lossy = self._wd_lossy or (self._wd_base is not None and seen != self._wd_base)
        if self._wd_lossy and self._s_last != self._wd_angle_s and self._s_last >= 0:
            self._wd_angle_s = self._s_last
            self.watchdog.angle(math.degrees(self._x_last))
        if on != self._wd_suspect:
            self._wd_suspect = on
            self.watchdog.suspect(on, math.degrees(self._x_last))

    def _wd_poll(self) -> None:
        """Before a read: take the watchdog's writes made since."""
        if self.watchdog is not None:
            times = self.watchdog.take()
            if times:
                self._wd_take(times)

    def _wd_settle(self) -> None:
        """Before a host command: take the watchdog's writes made since, and read what
        waits on the port, so that their answers (on the wire since the host's silence)
        are taken while those writes are the newest commands, not for the host's next
        (the transport's rule: a record read answers the newest command sent before it
        was read)."""
        if self.watchdog is None:
            return
        times = self.watchdog.take()
        if times:
            self._wd_take(times)
            waiting = self._ser.in_waiting
            if waiting:
                self._feed(self._ser.read(waiting), self._q)

    def _wd_stop(self) -> None:
        """At a STOP: the watchdog disarmed, the writes it made since the host's last
        command taken, and their answers read for at most the board's round trip and
        :data:`STOP_WAIT_S` more, so that each is counted as the watchdog's
        (``watchdog_replies``):
        before, a host that stalled past the hold bound between its last FORCE and its
        STOP left the watchdog's answer to the stop's tick probe
        (:meth:`hapsim.drivers.tick_align.TickAligned.end_probe`) or unread, counted
        nowhere (once in a fresh clone's CI, ``tests/test_host_watchdog.py``). What has
        arrived when the wait ends is read still (a host descheduled past it)."""
        if self.watchdog is None:
            return
        self.watchdog.arm(False)
        times = self.watchdog.take()
        if times:
            self._wd_take(times)
        end = time.monotonic() + self.driver.round_trip_s() + STOP_WAIT_S
        try:
            while self._wd_cmds and time.monotonic() < end:
                data = self._ser.read(max(self._ser.in_waiting, 1))
                if data:
                    self._n_read += len(data)
                    self._feed(data, self._q)
            if self._wd_cmds and self._ser.in_waiting:
                # a host descheduled past the wait's end: what came meanwhile is read
                # still (before, the deadline left it unread: once in a fresh clone's CI,
                # the Hapkit sketch's, fired 3, answered 2)
                data = self._ser.read(self._ser.in_waiting)
                self._n_read += len(data)
                self._feed(data, self._q)
        except Exception:  # serial.SerialException, OSError: the stop's write says it
            pass

    def _wd_answer(self, s: int) -> bool:
        """Whether command ``s`` was the watchdog's (its answer is dropped, counted)."""
        if s in self._wd_cmds:
            self._wd_cmds.discard(s)
            self.stats["watchdog_replies"] += 1
            return True
        return False

    def _watchdog_report(self) -> dict:
        """``watchdog``: the watchdog's report (:meth:`hapsim.drivers.torque_watchdog.
        TorqueWatchdog.report`), or ``{"running": False, "why": ...}``."""
        from hapsim.drivers.torque_watchdog import watchdog_report
        return watchdog_report(self.watchdog, self._wd_why)


def robust_stop(driver):
    """The write that zeroes ``driver``'s board whatever its parser is inside, for the
    watchdog (:class:`hapsim.drivers.torque_watchdog.TorqueWatchdog`'s ``robust``), or None
    when its zero-force command already does (a framed or a fixed-length protocol).

    Parameters
    ----------
    driver : hapsim.drivers.base.Driver

    Returns
    -------
    (bytes, int) or None
        ``driver.stop_bytes(0.0)`` and the index of the float32 in it that carries the
        position in degrees (where the stops at two positions differ: four bytes in a
        row); None when the stop is the zero-force command, or carries no such float.
    """
    import struct
    zero = driver.encode_force(0.0)
    a, b = driver.stop_bytes(0.0), driver.stop_bytes(1.0)
    if a == zero or len(a) != len(b):
        return None
    diff = [i for i in range(len(a)) if a[i] != b[i]]
    if not diff or diff[-1] - diff[0] > 3 or diff[0] + 4 > len(a):
        return None
    i = diff[0]
    # the float is the angle in degrees (the watchdog's host writes it so: the Haply
    # set-up's encoder offset), or this is no stop the watchdog can patch
    deg = struct.unpack("<f", struct.pack("<f", math.degrees(1.0)))[0]
    if struct.unpack("<f", b[i:i + 4])[0] != deg:
        return None
    return a, i

"""The host's watchdog in the transport: its zero writes accounted as commands (issue 29;
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
"""

from __future__ import annotations

from hapsim.drivers.resync import HOLD_BOUND_S, RING

__all__ = ["Watched"]


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
        if driver.holds_force_s <= HOLD_BOUND_S:
            self._wd_why = "the board zeroes its force itself within the hold bound"
            return
        if not own_clock:
            self._wd_why = "a lockstep mock: its time is the commands'"
            return
        from hapsim.drivers.torque_watchdog import start_watchdog
        self.watchdog, self._wd_why = start_watchdog(port, driver.encode_force(0.0),
                                                     HOLD_BOUND_S)

    def _wd_take(self, times: tuple) -> None:
        """The watchdog's zero writes ``times`` (monotonic ns), made after the host's last
        command: commands of their own (module notes)."""
        for t_ns in times:
            self._cmd += 1
            self._sent_us[self._cmd % RING] = (t_ns - self._t0) // 1000
            self._wd_cmds.add(self._cmd)
            self.stats["watchdog_zeroed"] += 1
            self._force = 0.0

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

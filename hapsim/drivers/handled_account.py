"""A lockstep mock's account of the bytes it handled, as the transport reads it
(:class:`HandledAccount`, a base of :class:`hapsim.drivers.transport.DriverTransport`;
the transport's module notes: a lockstep mock has no time of its own, so the transport
reads only once the mock has handled every byte written to it, then all it wrote)."""

from __future__ import annotations

import time

__all__ = ["HandledAccount", "CLAIM_QUIET_S", "LOCKSTEP_WRITE_TIMEOUT_S"]

#: A lockstep mock's account standing still this long [s] when the transport takes the
#: port (an earlier user's bytes handled and landed: :meth:`HandledAccount._claim`).
CLAIM_QUIET_S = 0.03
#: How long a write to a lockstep mock may block [s]. A board on its own clock that takes
#: no byte for 1 s is lost; a lockstep mock is a process paced by the writes, which a
#: loaded host can deschedule for over a second (a CI pass at nice 19: "write timeout",
#: the run lost): late, not lost. (A mock that died is found by the reads between the
#: writes: its pty reads as disconnected once no slave is open.)
LOCKSTEP_WRITE_TIMEOUT_S = 30.0


class HandledAccount:
    """Reads against a lockstep mock's account (``self._handled() -> (read, written)``,
    :class:`hapsim.spawn.HandledBytes` ``totals``), with the transport's counts of the
    bytes it wrote (``_n_written``) and read (``_n_read``) on its port ``_ser``."""

    def _claim(self) -> None:
        """A lockstep mock's account counts every byte since it started, an earlier
        user's of the port too (identify's direction probe and travel sweep): wait until
        it has stood still for :data:`CLAIM_QUIET_S` (at most 1 s), drop what is left on
        the line (answers to that user), and count from there."""
        ser = self._ser
        last = None
        t_still = time.monotonic()
        end = t_still + 1.0
        while True:
            now = time.monotonic()
            tot = self._handled()
            left = ser.in_waiting
            if left:
                ser.read(left)
            if tot != last or left:
                last, t_still = tot, now
            elif now - t_still >= CLAIM_QUIET_S or now > end:
                break
            time.sleep(1e-3)
        self._n_written, self._n_read = last

    @property
    def settles(self) -> bool:
        """Whether this transport's device is a lockstep mock with its account: its
        record is then the commands', whatever the clock, and the host loop takes each
        tick once :meth:`settled` says so (:mod:`hapsim.host.host_clock`)."""
        return self._handled is not None

    def settled(self) -> bool:
        """A lockstep mock (:attr:`settles`) has answered everything it will (its account:
        every byte written to it handled, every byte it wrote read here); False without
        an account.

        Returns
        -------
        bool
        """
        return self._handled is not None and self._quiet()

    def _quiet(self) -> bool:
        """A lockstep mock (``handled``) has answered everything it will: it has read
        every byte written to it and its every byte has been read here."""
        r, w = self._handled()
        return r == self._n_written and w == self._n_read

    def _read_handled(self) -> bytes:
        """A lockstep mock's whole answer: nothing while it has not handled every byte
        written to it; then every byte it wrote that was not read yet (they are on their
        way through the pty: waited for, up to a second)."""
        r, w = self._handled()
        if r != self._n_written or w <= self._n_read:
            return b""
        need = w - self._n_read
        buf = bytearray()
        end = time.monotonic() + 1.0
        while len(buf) < need and time.monotonic() < end:
            buf += self._ser.read(need - len(buf))
        return bytes(buf)

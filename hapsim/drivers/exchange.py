"""The exchanges that run before a loop: one write, its reply, on a device that answers
every write (the Haply boards' direction probes, the FireFader's travel sweep), and the
serial port they run on. Not the real-time loop's transport
(:class:`hapsim.drivers.transport.DriverTransport`): these wait for each reply."""

from __future__ import annotations

import math
import time

from hapsim.errors import DeviceError

__all__ = ["Exchange", "SerialLink"]


class Exchange:
    """One write, its reply: a device that answers every write (the driver's decoder),
    paced at ``rate_hz`` [Hz] on the host's clock or not (``pace``), each reply waited for
    at most ``timeout`` [s]. Shared by the probes and sweeps that run before a loop (the
    Haply joint's and the 2DIY's direction probes, the FireFader's travel sweep).

    Parameters
    ----------
    drv : hapsim.drivers.base.Driver
        Gives the reply decoder.
    link : object
        ``write(bytes)`` and ``read(timeout [s]) -> bytes`` on the device's port.
    rate_hz : float
        Writes per second when paced [Hz].
    pace : bool
        Pace the writes on the host's clock (False: a mock paced by the writes).
    timeout : float
        Longest wait for one reply [s].
    max_missing : int
        Writes in a row without any reply allowed before :class:`DeviceError` (a board
        that stopped answering). A reply that comes after its timeout is late, not lost:
        it is read with the next write's (the board answers every write, in order), so a
        loaded host or device slows the exchange without failing it.
    lost : str
        That error's message.
    first_timeout : float, optional
        Longest wait for the first write's reply [s] (a board, or a board process, still
        starting when the port opened); default ``timeout``.
    resync : callable, optional
        ``resync(x) -> bytes``: the writes that put a board without framing back in step
        at the last angle read ``x`` (the Haply M3's :meth:`~hapsim.drivers.haply.HaplyM3.
        resync`: zero torque, its set-up at ``x``, zero torque). Given, a write whose reply
        did not come while the decoder shows the board lost its place (its ``desync``,
        ``lone`` or ``unreachable`` counts grew), or the fifth in a row without one, is
        followed by them, and the decoder's
        prediction restarts at ``x`` (as the transport does in a run:
        :mod:`hapsim.drivers.resync`). Before, the exchange had none: with one host byte
        in 200 lost, every direction probe of the M3 (about 400 writes) ended "does not
        answer its writes" (hapsim's emulated board, 20 seeds of 20; the independent
        model of ``tools/independent_boards``, 3 of 3).

    Attributes
    ----------
    writes, missing, replies, resyncs : int
        Writes sent, writes whose reply did not come within the timeout, replies read,
        and re-synchronisations sent (``resync``).
    silence : float
        Host time between the last two writes [s] (a firmware's silence rule reads it).

    Raises
    ------
    DeviceError
        From :meth:`reply`: more than ``max_missing`` writes in a row without a reply
        (``lost``; or, where replies came but out of the joint's reach, that said).
    """

    def __init__(self, drv, link, rate_hz: float, pace: bool, timeout: float, *,
                 max_missing: int = 20,
                 lost: str = ("the Haply board does not answer its writes (no reply to "
                              "more than 20 writes in a row while finding the motor "
                              "direction): check the port and the device id"),
                 first_timeout: float | None = None, resync=None) -> None:
        self.drv = drv
        self._resync = resync
        self.resyncs = 0
        self._x = math.nan
        self.link = link
        self.dec = drv.decoder()
        self.period = 1.0 / rate_hz
        self.pace = pace
        self.timeout = timeout
        self.writes = 0
        self.missing = 0
        self.replies = 0
        self.silent = 0                  # writes in a row without any reply
        self.first_timeout = timeout if first_timeout is None else float(first_timeout)
        self.max_missing = max_missing
        self.lost = lost
        self.silence = 0.0
        self._next = self._last = time.monotonic()
        self._ev = self._evidence()
        self._unreach0 = 0              # the decoder's 'unreachable' at the last reply

    def _lost_message(self) -> str:
        """The error of a board silent for more than ``max_missing`` writes: ``lost``,
        unless well-formed replies came meanwhile that no motion of the joint reaches (the
        decoder's ``unreachable``): then the board answers, and what differs is the
        encoder's scale or the device. Before, a board whose encoder counted 2e5 times
        the driver's resolution was said not to answer (55 of its 86 replies out of
        reach)."""
        u = int(self.dec.stats.get("unreachable", 0)) - self._unreach0
        if u <= 0:
            return self.lost
        return (f"the board answers, but {u} of its replies since the last one taken "
                f"(over {self.silent} writes) were out of the joint's reach (further "
                f"from the readings before them than its inertia lets it move under the "
                f"torque sent, in the time between): the "
                f"encoder's counts per revolution may differ from the driver's "
                f"resolution (--protocol-option resolution=COUNTS), or the joint is "
                f"lighter than the device's mass states")

    def _evidence(self) -> int:
        """The decoder's count of evidence that the board lost its place."""
        st = self.dec.stats
        return sum(int(st.get(k, 0)) for k in ("desync", "lone", "unreachable"))

    def send(self, data: bytes) -> float:
        """Send ``data`` (one period), return the last angle answered [rad] (NaN: none
        within the timeout).

        Parameters
        ----------
        data : bytes
            The write (the driver's command bytes).

        Returns
        -------
        float
            The angle [rad] (the decoder's unit), or NaN.

        Raises
        ------
        DeviceError
            As :meth:`reply`.
        """
        got = self.reply(data)
        return math.nan if got is None else float(got)

    def reply(self, data: bytes):
        """Send ``data`` (one period), return the last reply the decoder gave (None: none
        within the timeout).

        Parameters
        ----------
        data : bytes
            The write (the driver's command bytes).

        Returns
        -------
        object or None
            The decoder's last value: the M3's angle [rad], the 2DIY's two angles [deg]
            (tuple), the FireFader's position [m]; None when no reply came in time.

        Raises
        ------
        DeviceError
            More than ``max_missing`` writes in a row without a reply (``lost``, or the
            replies out of reach said); a write or read of the link failed.
        """
        if self.pace:
            now = time.monotonic()
            if now < self._next:
                time.sleep(self._next - now)
            self._next = max(now, self._next) + self.period
        now = time.monotonic()
        self.silence, self._last = now - self._last, now
        self.link.write(data)
        self.writes += 1
        end = time.monotonic() + (self.first_timeout if self.writes == 1 else self.timeout)
        got = []
        while not got:
            got = self.dec.feed(self.link.read(max(0.0, end - time.monotonic())))
            if not got and time.monotonic() >= end:
                break
        if not got:
            self.missing += 1
            self.silent += 1
            if self.silent > self.max_missing:
                raise DeviceError(self._lost_message())
            ev = self._evidence()
            # (or every 5 writes unanswered since: the re-synchronisation's own 62 bytes
            # may lose one, leaving a garbage set-up the decoder counts once)
            if self._resync is not None and (ev > self._ev or self.silent % 5 == 0):
                # the board lost its place (no framing): put it back at the last angle
                self._ev = ev
                x = self._x if math.isfinite(self._x) else 0.0
                self.link.write(self._resync(x))
                self.writes += 1
                self.resyncs += 1
                anchor = getattr(self.drv, "rearm_anchor", lambda v: None)(x)
                self.dec.reset_prediction(jumps=2, anchor=anchor)
            return None
        self.replies += len(got)
        self.silent = 0
        self._unreach0 = int(self.dec.stats.get("unreachable", 0))
        if isinstance(got[-1], float):
            self._x = got[-1]
        return got[-1]

    def stop(self, data: bytes, replies: int) -> None:
        """Send the stop ``data`` (zero torque) and read its ``replies`` and those of
        earlier writes still on their way (late ones; at most the timeout): a reply left
        on the line would be read by whoever opens the port next as the answer to its own
        first write. Best effort: never raises (the port may be gone; this runs on every
        exit).

        Parameters
        ----------
        data : bytes
            The stop write (zero torque).
        replies : int
            Replies it brings (those of earlier writes still owed are added).
        """
        try:
            self.link.write(data)
            replies += max(0, self.writes - self.replies) if self.replies else 0
            replies += int(getattr(self.link, "extra", 0))  # (a watchdog's writes')
            end = time.monotonic() + self.timeout
            n = 0
            while n < replies and time.monotonic() < end:
                n += len(self.dec.feed(self.link.read(max(0.0, end - time.monotonic()))))
        except Exception:  # noqa: BLE001 -- best effort: the port may be gone
            pass


class SerialLink:
    """``write``/``read(timeout)`` on a serial port (pyserial): the link :class:`Exchange`
    takes, for hardware or a driver mock's pty.

    Parameters
    ----------
    port : str
        Serial port.
    baud : int
        Baud rate [bit/s].
    rtscts : bool
        RTS/CTS flow control (as the driver asks).
    watchdog : hapsim.drivers.torque_watchdog.TorqueWatchdog, optional
        The host's watchdog on this port, armed by the caller: each write goes through
        it (:meth:`write`).
    zero : bytes
        The driver's zero-torque command (with ``watchdog``: a write ending with it
        leaves no torque held).

    Raises
    ------
    DeviceError
        The port cannot be opened; a write or read failed.
    """

    def __init__(self, port: str, baud: int, rtscts: bool = False, *, watchdog=None,
                 zero: bytes = b"") -> None:
        import serial

        from hapsim.drivers.urlhandler import serial_for_url
        self.watchdog, self.zero = watchdog, bytes(zero)
        #: The watchdog's writes taken (each answered by a reply the exchange reads as a
        #: late one: :meth:`Exchange.stop` reads them too).
        self.extra = 0
        try:
            # a fixed short read timeout (setting it per read reconfigures the port)
            self.ser = serial_for_url(port, baudrate=baud, rtscts=rtscts, timeout=0.005,
                                      write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self.port = port

    def write(self, data: bytes) -> None:
        """Write ``data``; with a watchdog (a board without one, on its own clock), through
        it: its time stamped, whether it leaves a torque held (anything but the zero
        command, or writes that end with it), the watchdog's writes since counted.

        Parameters
        ----------
        data : bytes

        Raises
        ------
        DeviceError
            The write failed.
        """
        try:
            if self.watchdog is None:
                self.ser.write(data)
            else:
                holding = not data.endswith(self.zero)
                self.extra += len(self.watchdog.write(self.ser, data, holding))
        except Exception as exc:  # serial.SerialException, OSError, timeouts
            raise DeviceError(f"write to {self.port} failed: {exc}") from None

    def read(self, timeout: float) -> bytes:
        """Bytes waiting, or the first within the port's 5 ms (the caller loops to its
        own ``timeout`` [s]).

        Parameters
        ----------
        timeout : float
            The caller's wait [s]; not used (the port's read timeout is a fixed 5 ms).

        Returns
        -------
        bytes
            Possibly empty.

        Raises
        ------
        DeviceError
            The read failed.
        """
        try:
            n = self.ser.in_waiting
            return self.ser.read(n if n else 1)
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.port} failed: {exc}") from None

    def close(self) -> None:
        """Flush and close the port (best effort: an error closing it is not raised)."""
        try:
            self.ser.flush()
            self.ser.close()
        except Exception:  # noqa: BLE001 -- the port may be gone
            pass

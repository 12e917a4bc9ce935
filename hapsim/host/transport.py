"""Message transports between the host loop and a device, behind one interface.

:class:`Transport` declares what :mod:`hapsim.host.loop`, its compiled twin and their
handshake and recovery call on every transport; ``tests/test_drivers.py`` checks each
transport class against it. :class:`SerialTransport` opens any port with pyserial:
hardware, or the pty of an emulated device. The host side knows only a port: the
transports that hold an emulated device in-process (no bytes, or a virtual clock) and the
emulated mock started on a pty are the device side's (:mod:`hapsim.emulated.links`); a
device family's own link is :class:`hapsim.drivers.transport.DriverTransport`.
:func:`open_transport` opens the one a port and a family call for (as pyserial's
``serial_for_url``)."""

from __future__ import annotations

import os
import time
from typing import Protocol, runtime_checkable

import firmware_protocol as fp
from hapsim.errors import DeviceError

__all__ = ["Transport", "SerialTransport", "open_transport"]


@runtime_checkable
class Transport(Protocol):
    """What the host loop calls on a transport (a structural type: no class inherits it).

    Attributes
    ----------
    info : dict
        Facts for the loop report: ``kind``, ``port``, ``baud``, ``low_latency``,
        ``low_latency_note``.

    Notes
    -----
    Members the loop uses when a transport has them: ``clock()`` and ``sleep(s)`` (virtual
    time), ``reopen()`` (recover a failed port), ``decoder`` (counters), ``serial_port``
    (the compiled loop's file descriptor), ``set_compact`` and ``compact`` (compact
    frames), ``driver``, ``hold``, ``overdue``, ``estimate`` and ``host_stalled`` (a
    driver's replies).
    """

    info: dict

    def send(self, msg) -> None:
        """Send one protocol message (DeviceError when the port is gone).

        Parameters
        ----------
        msg : firmware_protocol message
            A host message (``Force``, ``Config``, ...).
        """

    def receive(self, timeout: float = 0.0) -> list:
        """The messages received so far, waiting up to ``timeout`` [s] for a first one.

        Parameters
        ----------
        timeout : float
            Longest wait [s], >= 0 (0: only what is waiting).

        Returns
        -------
        list of firmware_protocol messages
            In arrival order; empty after the timeout.
        """

    def close(self) -> None:
        """Release the port (idempotent)."""

    def last_frames(self) -> str:
        """Text of the last frames received (docs/design.md, rule 11), for errors."""


def _is_pty(port: str) -> bool:
    """Whether ``port`` is a pseudo-terminal's slave (``/dev/pts/N``, followed through a
    link): Linux's Unix98 pty slaves have the character major numbers 136-143
    (Documentation/admin-guide/devices.txt)."""
    try:
        st = os.stat(port)
    except (OSError, TypeError, ValueError):
        return False
    import stat
    return stat.S_ISCHR(st.st_mode) and 136 <= os.major(st.st_rdev) <= 143


class SerialTransport:
    """Framed protocol over a pyserial port (hardware, or the mock's pseudo-terminal).

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyACM0``, ``/dev/pts/N``) or any pyserial URL.
    baud : int
        Baud rate (ignored by USB CDC-ACM devices and ptys).
    read_timeout : float
        pyserial read timeout [s]: the longest a single blocking read waits, hence the
        resolution of :meth:`receive`'s ``timeout`` (the loop declares a silent device lost
        after its watchdog period, 50 ms: 10 ms keeps that within a fifth of it; a read
        returns as soon as a byte arrives, so it costs nothing while frames flow).

    Raises
    ------
    DeviceError
        When the port cannot be opened (the pyserial message is kept).

    Notes
    -----
    ``set_low_latency_mode(True)`` (Linux ASYNC_LOW_LATENCY, e.g. to bypass the FTDI 16 ms
    latency timer) is tried; on a pty or an OS without it it raises, which is caught and
    recorded in :attr:`info` (``low_latency`` false with the reason).
    """

    def __init__(self, port: str, baud: int = 115200, read_timeout: float = 0.01) -> None:
        self.info = {"kind": "serial", "port": port, "baud": baud, "low_latency": False,
                     "low_latency_note": ""}
        self._timeout = read_timeout
        self._open()
        self._dec = fp.StreamDecoder()
        self._compact = False

    def _open(self) -> None:
        """Open :attr:`info`'s port, in low-latency mode where it has one (DeviceError when
        it cannot be opened)."""
        import serial  # pyserial; imported here so in-process tests do not need it

        from hapsim.drivers.urlhandler import serial_for_url
        port = self.info["port"]
        try:
            self._ser = serial_for_url(port, baudrate=self.info["baud"],
                                       timeout=self._timeout, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self._read, self._write = self._ser.read, self._ser.write
        if _is_pty(port):
            # ASYNC_LOW_LATENCY is a serial driver's flag (the FTDI latency timer): a pty
            # (the embedded mock) has none, and asking only yields ENOTTY (issue 31)
            self.info["low_latency_note"] = "a pty: not a serial driver"
            return
        try:
            self._ser.set_low_latency_mode(True)
            self.info["low_latency"] = True
        except (AttributeError, NotImplementedError, ValueError, OSError) as exc:
            self.info["low_latency_note"] = f"not available: {exc}".strip()

    @property
    def decoder(self) -> fp.StreamDecoder:
        """The stream decoder (counters in ``.stats``)."""
        return self._dec

    @property
    def serial_port(self):
        """The open pyserial port (``serial.SerialBase``; the compiled loop reads and
        writes its file descriptor ``fd`` directly). Replaced by :meth:`reopen`."""
        return self._ser

    @property
    def compact(self) -> bool:
        """Whether the session uses the compact frames (:meth:`set_compact`)."""
        return self._compact

    def set_compact(self, rate_hz: float | None) -> None:
        """Enter (``rate_hz``) or leave (None) a compact session (PROTOCOL.md §4 "Compact
        frames"): each FORCE is then sent as FORCE_COMPACT and each STATE_COMPACT received
        comes out as the STATE it stands for (:class:`firmware_protocol.CompactExpander`,
        restarted at every CONFIG sent).

        Parameters
        ----------
        rate_hz : float or None
            Tick rate of the session [Hz]; None: full frames.
        """
        self._compact = rate_hz is not None
        self._dec.expander = fp.CompactExpander(rate_hz) if self._compact else None

    def send(self, msg) -> None:
        """Encode and write one message.

        Parameters
        ----------
        msg : firmware_protocol message
            A host message; written as one COBS frame with its ``0x00`` delimiter.

        Raises
        ------
        DeviceError
            When the write fails (port gone); the message carries the last frames.
        """
        if self._compact:
            if type(msg) is fp.Force:
                msg = fp.compact_force(msg)
            elif type(msg) is fp.Config:
                self._dec.expander.restart(msg.rate_hz)   # the device restarts its seq
        try:
            self._write(fp.encode(msg))
        except Exception as exc:  # serial.SerialException, OSError, SerialTimeoutException
            raise DeviceError(f"write to {self.info['port']} failed: {exc}\n"
                              f"last frames:\n{self.last_frames()}") from None

    def receive(self, timeout: float = 0.0) -> list:
        """Messages received, waiting up to ``timeout`` for at least one.

        Parameters
        ----------
        timeout : float
            Longest wait [s] for a first message, >= 0 (0: only what is waiting); honoured
            to ``read_timeout`` (a blocking read returns at its first byte).

        Returns
        -------
        list of firmware_protocol messages
            Messages of the frames completed, in arrival order; empty after the timeout.
            Bad frames are dropped and counted by :attr:`decoder`.

        Raises
        ------
        DeviceError
            When the read fails (port gone); the message carries the last frames.
        """
        ser = self._ser
        end = time.monotonic() + timeout
        feed = self._dec.feed
        try:
            while True:
                waiting = ser.in_waiting
                if waiting:
                    msgs = feed(self._read(waiting))
                elif timeout > 0:
                    msgs = feed(self._read(1))
                else:
                    return []
                if msgs:
                    return msgs
                if time.monotonic() >= end:
                    return []
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.info['port']} failed: {exc}\n"
                              f"last frames:\n{self.last_frames()}") from None

    def close(self) -> None:
        """Close the port (idempotent)."""
        try:
            self._ser.close()
        except Exception:  # pragma: no cover - closing a vanished port
            pass

    def reopen(self) -> None:
        """Close the port and open the same path again (after the device vanished).

        The decoder keeps its counters and history; its partial frame is dropped.

        Raises
        ------
        DeviceError
            When the port cannot be opened (yet).
        """
        self.close()
        self._open()
        self._dec.reset()
        self.set_compact(None)   # a device that vanished may have reset: ask again
        self.reopened = getattr(self, "reopened", 0) + 1

    def last_frames(self) -> str:
        """The last frames received as text (docs/design.md, rule 11).

        Returns
        -------
        str
            One line ``outcome: hex`` per frame, oldest first (the decoder keeps 16);
            ``""`` before any frame.
        """
        return self._dec.format_last_frames()




def open_transport(port: str, driver=None, *, baud: int = 115200, **options) -> Transport:
    """The transport a port and a device family call for, as pyserial's ``serial_for_url``
    opens the port a URL calls for: the family's link is read from the drivers' registry
    (:data:`hapsim.drivers.FAMILIES`).

    Parameters
    ----------
    port : str
        A device path (``/dev/ttyACM0``), a pty (an emulated device's), or any pyserial URL
        (``loop://``).
    driver : str or hapsim.drivers.base.Driver, optional
        None or ``"framed"`` (the default protocol): :class:`SerialTransport`; a 1-D
        family's name or its driver object:
        :class:`~hapsim.drivers.transport.DriverTransport`.
    baud : int
        The framed protocol's baud rate (a driver has its own).
    **options
        :class:`~hapsim.drivers.transport.DriverTransport`'s keywords (``delay``,
        ``reply_deadline``, ``inertia``, ...).

    Returns
    -------
    Transport

    Raises
    ------
    ConfigError
        An unknown driver name (the valid ones listed).
    DeviceError
        The port cannot be opened.
    """
    from hapsim.drivers import DEFAULT, family, get_driver
    name = driver if isinstance(driver, str) or driver is None else driver.name
    if family(name or DEFAULT).transport == "framed":
        return SerialTransport(port, baud)
    from hapsim.drivers.transport import DriverTransport
    return DriverTransport(get_driver(driver) if isinstance(driver, str) else driver, port,
                           **options)

"""pyserial's handler of ``emulated://NAME``: the host's end of the link to an emulated board,
a Unix ``SOCK_SEQPACKET`` socket connected to the abstract name NAME (the package's notes).

Each write is one packet (at most :data:`PACKET` bytes), which the kernel stamps for a
receiver that asks (``SO_TIMESTAMPNS``); reads are a byte stream, as a serial port's.
Line settings (baud, parity, DTR, RTS) are taken and ignored: there is no line.
"""

from __future__ import annotations

import select
import socket
import time

from serial.serialutil import (PortNotOpenError, SerialBase, SerialException,
                               SerialTimeoutException)

__all__ = ["Serial", "PACKET", "SEND_BUFFER"]

#: The largest packet one write makes [bytes]; a longer write is cut into packets of this
#: size (every command of every driver is shorter).
PACKET = 4096
#: The send buffer asked for [bytes] (the kernel caps it at ``net.core.wmem_max`` and
#: doubles it). A packet of 10 bytes takes about 770 bytes of the buffer: its default
#: (212,992) holds 278 commands, fewer than a board's 0.5 s silence queues at 1 kHz
#: (:data:`hapsim.drivers.resync.SILENCE_LOST_S`); 4 MB holds thousands, as a tty's
#: buffer holds a silence's bytes.
SEND_BUFFER = 1 << 22
#: The longest a blocking read or write waits in one ``select`` [s], so that a closed
#: port is noticed.
_POLL_S = 0.1


class Serial(SerialBase):
    """A serial port on an emulated board's link (module notes; pyserial's
    ``serial.SerialBase`` interface: ``read``, ``write``, ``in_waiting``,
    ``reset_input_buffer``, ``fileno``, ``close``).

    Raises
    ------
    serial.SerialException
        The URL is not ``emulated://NAME``, nothing listens on NAME, a read finds the board
        gone (its end closed), or a write fails.
    serial.SerialTimeoutException
        A write not taken within ``write_timeout``.
    """

    def open(self) -> None:
        """Connect to the emulated board named by the port's URL."""
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        name = self._name(self.portstr)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
            sock.connect("\0" + name)
        except OSError as exc:
            sock.close()
            raise SerialException(f"could not open port {self.portstr}: {exc}") from None
        sock.setblocking(False)
        self._socket = sock
        self._rx = bytearray()
        self._eof = False
        self.is_open = True

    @staticmethod
    def _name(url: str) -> str:
        scheme, sep, name = str(url).partition("://")
        if scheme.lower() != "emulated" or not sep or not name or "\0" in name:
            raise SerialException(f"expected a port 'emulated://NAME', got {url!r}")
        return name

    def from_url(self, url: str) -> str:
        """The abstract socket name in ``emulated://NAME``.

        Parameters
        ----------
        url : str
            The port's URL.

        Returns
        -------
        str
            ``NAME`` (no leading NUL).

        Raises
        ------
        serial.SerialException
            Another URL.
        """
        return self._name(url)

    def _reconfigure_port(self, *args, **kwargs) -> None:
        """Nothing to set on a link with no line (baud, parity and the rest are ignored)."""

    def _update_dtr_state(self) -> None:
        """No line: DTR is ignored."""

    def _update_rts_state(self) -> None:
        """No line: RTS is ignored."""

    def _update_break_state(self) -> None:
        """No line: a break is ignored."""

    def close(self) -> None:
        """Close the link (the emulated board reads its end and stops)."""
        if self.is_open:
            try:
                self._socket.close()
            finally:
                self._socket = None
                self.is_open = False

    def _pull(self) -> None:
        """Every packet waiting, appended to the read buffer; the board's end closed noted."""
        sock = self._socket
        while not self._eof:
            try:
                data = sock.recv(PACKET)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                raise SerialException(f"read failed: {exc}") from None
            if not data:
                self._eof = True
                return
            self._rx += data

    @property
    def in_waiting(self) -> int:
        """Bytes received and not yet read."""
        if not self.is_open:
            raise PortNotOpenError()
        self._pull()
        return len(self._rx)

    @property
    def out_waiting(self) -> int:
        """Bytes written and not yet sent: none (a write is in the kernel when it returns)."""
        return 0

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes: as many as come within the port's ``timeout`` (None: wait
        for all of them; 0: those waiting).

        Parameters
        ----------
        size : int
            Most bytes to read.

        Returns
        -------
        bytes
            The bytes read, fewer than ``size`` after the timeout or the board's end.

        Raises
        ------
        serial.SerialException
            The board's end closed with no byte left to read.
        """
        if not self.is_open:
            raise PortNotOpenError()
        end = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            self._pull()
            if len(self._rx) >= size or self._eof:
                break
            left = _POLL_S if end is None else min(end - time.monotonic(), _POLL_S)
            if end is not None and left <= 0:
                break
            select.select([self._socket], [], [], left)
        out = bytes(self._rx[:size])
        del self._rx[:size]
        if not out and self._eof and size > 0:
            raise SerialException("read failed: the emulated board closed its link")
        return out

    def write(self, data) -> int:
        """Send ``data``, one packet per :data:`PACKET` bytes, whole.

        Parameters
        ----------
        data : bytes-like
            The bytes to send.

        Returns
        -------
        int
            ``len(data)``: every byte sent.

        Raises
        ------
        serial.SerialTimeoutException
            A packet not taken within ``write_timeout`` (the board does not read).
        serial.SerialException
            The link failed (the board's end closed).
        """
        if not self.is_open:
            raise PortNotOpenError()
        view = memoryview(bytes(data))
        end = (None if self._write_timeout is None
               else time.monotonic() + self._write_timeout)
        for i in range(0, len(view), PACKET):
            packet = view[i:i + PACKET]
            while True:
                try:
                    self._socket.send(packet)
                    break
                except (BlockingIOError, InterruptedError):
                    pass
                except OSError as exc:
                    raise SerialException(f"write failed: {exc}") from None
                left = _POLL_S if end is None else min(end - time.monotonic(), _POLL_S)
                if end is not None and left <= 0:
                    raise SerialTimeoutException("Write timeout")
                select.select([], [self._socket], [], left)
        return len(view)

    def flush(self) -> None:
        """Nothing to wait for: a write is in the kernel when it returns."""

    def reset_input_buffer(self) -> None:
        """Drop every byte received and not yet read."""
        if not self.is_open:
            raise PortNotOpenError()
        self._pull()
        self._rx.clear()

    def reset_output_buffer(self) -> None:
        """Nothing to drop: a write is in the kernel when it returns."""

    def fileno(self) -> int:
        """The socket's descriptor (``select`` sees the packets not yet pulled into the read
        buffer, not the bytes already there: :attr:`in_waiting` first).

        Returns
        -------
        int
            The socket's file descriptor.

        Raises
        ------
        serial.PortNotOpenError
            The port is not open.
        """
        if not self.is_open:
            raise PortNotOpenError()
        return self._socket.fileno()

    @property
    def cts(self) -> bool:
        """No line: clear to send."""
        return True

    @property
    def dsr(self) -> bool:
        """No line: data set ready."""
        return True

    @property
    def ri(self) -> bool:
        """No line: no ring."""
        return False

    @property
    def cd(self) -> bool:
        """No line: carrier detected."""
        return True

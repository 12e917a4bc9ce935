"""The emulated board's end of an emulated link (``emulated://NAME``,
:mod:`hapsim.drivers.urlhandler`; its listening socket made by :meth:`hapsim.spawn.PtyChild.
open_link`): the host's connection taken, and its writes read with the time the kernel
stamped each with when it was made.

A board emulated in a process takes the host's bytes when that process reads them. Over a
pseudo-terminal that is after the tty's flip-buffer worker and the emulator's own wake-up:
on a virtual machine that halts its idle CPUs, 0.3 ms at the median and 1-2 ms at the 99th
percentile (``tools/pty_latency.py``), up to a tick and more of the Hapkit sketch's 0.992
ms, so the emulated sketch took 10-65 % of the commands at another tick than the period's
(``tick_arrivals.off_period``), which a board on its own processor never does. The
socket's stamp is the write's own time, 10-20 us after the host's call whatever the
emulator's scheduling (``SO_TIMESTAMPNS``, socket(7); taken by Unix datagram and
seqpacket sockets, not stream ones).
"""

from __future__ import annotations

import select
import socket
import struct
import time

from hapsim.drivers.urlhandler.protocol_emulated import PACKET, SEND_BUFFER

__all__ = ["accept", "connection", "StampedReader"]

_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_SCM_TIMESTAMPNS = getattr(socket, "SCM_TIMESTAMPNS", _SO_TIMESTAMPNS)
_TS = struct.Struct("@qq")
#: How long the emulator waits for the host to open the port between checks of its stop [s].
ACCEPT_POLL_S = 0.1


def accept(listener: socket.socket, stop=None):
    """The host's connection (the port opened), stamped; None when ``stop()`` came first.

    Parameters
    ----------
    listener : socket.socket
        The listening socket (:meth:`hapsim.spawn.PtyChild.open_link`).
    stop : callable, optional
        Polled every :data:`ACCEPT_POLL_S`; True ends the wait.

    Returns
    -------
    socket.socket or None
        Non-blocking, its receive stamps on (``SO_TIMESTAMPNS``), its send buffer as large as
        the host's (:data:`hapsim.drivers.urlhandler.protocol_emulated.SEND_BUFFER`).
    """
    while not (stop and stop()):
        try:
            r, _, _ = select.select([listener], [], [], ACCEPT_POLL_S)
        except InterruptedError:
            continue
        if not r:
            continue
        conn, _ = listener.accept()
        conn.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        conn.setblocking(False)
        return conn
    return None


def connection(listen_fd: int, stop=None) -> tuple:
    """A child's side of :func:`accept` from its inherited listening descriptor: the
    connection and its :class:`StampedReader`, or ``(None, None)`` when ``stop()`` came
    first (the host never opened the port).

    Parameters
    ----------
    listen_fd : int
        The listening socket's descriptor (:meth:`hapsim.spawn.PtyChild.open_link`).
    stop : callable, optional
        As :func:`accept`'s.

    Returns
    -------
    (socket.socket or None, StampedReader or None)
        Keep the socket referenced while serving its descriptor.
    """
    conn = accept(socket.socket(fileno=listen_fd), stop=stop)
    return (None, None) if conn is None else (conn, StampedReader(conn))


class StampedReader:
    """The host's packets on a stamped socket, each with the time it was written, on this
    process's ``time.monotonic()`` clock.

    The kernel stamps on ``CLOCK_REALTIME``; a stamp is moved to the monotonic clock by
    the two clocks' difference read at the read (a step of the real-time clock between
    the write and the read would move it: each stamp is kept between the last packet's and
    the read's own time, so time never runs back and no byte comes before it was read).

    Parameters
    ----------
    sock : socket.socket
        :func:`accept`'s socket.

    Attributes
    ----------
    eof : bool
        The host closed its end.
    stamped, unstamped : int
        Packets read with and without a stamp (none: taken at the read's time).
    """

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.eof = False
        self.stamped = self.unstamped = 0
        self._last = -float("inf")
        self._space = socket.CMSG_SPACE(_TS.size)

    def read(self) -> list:
        """Every packet waiting, oldest first.

        Returns
        -------
        list of (bytes, float)
            Each packet and when it was written [s, ``time.monotonic()``].

        Raises
        ------
        OSError
            The socket failed (a closed host end is :attr:`eof`, not an error).
        """
        out = []
        while not self.eof:
            try:
                data, anc, _flags, _ = self.sock.recvmsg(PACKET, self._space)
            except (BlockingIOError, InterruptedError):
                break
            if not data:
                self.eof = True
                break
            now = time.monotonic()
            t = now
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == _SCM_TIMESTAMPNS:
                    s, ns = _TS.unpack(raw[:_TS.size])
                    off = time.time_ns() - time.monotonic_ns()
                    t = min(now, max((s * 1_000_000_000 + ns - off) * 1e-9, self._last))
                    self.stamped += 1
                    break
            else:
                self.unstamped += 1
            self._last = t
            out.append((data, t))
        return out

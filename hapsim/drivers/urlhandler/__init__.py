"""Ports beyond pyserial's own: the link to an emulated board on the wall clock
(``emulated://NAME``, :mod:`hapsim.drivers.urlhandler.protocol_emulated`), opened as any
serial port is (:func:`serial_for_url`).

A board emulated in a process of the machine's has no line of its own: what it is sent
reaches it through the kernel, and a pseudo-terminal hands it over late (its flip buffer's
worker thread, then the emulator's own wake-up: 0.3 ms at the median, 1-2 ms at the 99th
percentile on a virtual machine that halts its idle CPUs, docs/testing.md). A real board's
UART takes each byte as it comes on the wire. The emulated link is a Unix packet socket
whose every write the kernel stamps with the time it was made (``SO_TIMESTAMPNS``): the
emulated board takes the bytes at that time, whenever its process reads them
(:func:`hapsim.emulated.driver_mock.serve`), as a board on its own processor would.
"""

from __future__ import annotations

__all__ = ["serial_for_url", "SCHEME", "is_emulated"]

#: The emulated link's URL scheme: ``emulated://NAME``, NAME an abstract Unix socket's
#: name (the emulator listens on it, :class:`hapsim.emulated.driver_mock.EmbeddedDriverMock`).
SCHEME = "emulated"


def is_emulated(port) -> bool:
    """Whether ``port`` names an emulated link (``emulated://NAME``).

    Parameters
    ----------
    port : str or None

    Returns
    -------
    bool
    """
    return isinstance(port, str) and port.lower().startswith(SCHEME + "://")


def serial_for_url(url: str, **kwargs):
    """pyserial's ``serial.serial_for_url``, with this package's URL schemes known
    (``emulated://``; pyserial's handler packages, ``serial.protocol_handler_packages``).

    Parameters
    ----------
    url : str
        A device's path (``/dev/ttyACM0``), a pyserial URL (``socket://``, ``loop://``)
        or ``emulated://NAME``.
    **kwargs
        As ``serial.serial_for_url`` (``baudrate``, ``timeout``, ``write_timeout``, ...).

    Returns
    -------
    serial.SerialBase
        The open port.

    Raises
    ------
    serial.SerialException
        The port cannot be opened.
    ValueError
        A setting pyserial refuses, or a URL scheme no handler knows.
    """
    import serial
    if __name__ not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(__name__)
    return serial.serial_for_url(url, **kwargs)

"""The 2DIY's port as the record loop and the wiring probe use it: non-blocking reads,
whole writes, and :class:`PortLink` (:mod:`hapsim.pipeline.haply2_record`). The port is a
:class:`hapsim.drivers.device_port.DevicePort` (:func:`hapsim.pipeline.haply2_record.
record_realtime` and :func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port` make it
one): its failures are :class:`~hapsim.errors.DeviceError`."""

from __future__ import annotations

import time


__all__ = ["PortLink", "read_waiting", "write_all"]


def read_waiting(ser) -> bytes:
    """The bytes waiting on the port, without waiting.

    Parameters
    ----------
    ser : hapsim.drivers.device_port.DevicePort
        An open port (``in_waiting``, ``read``).

    Returns
    -------
    bytes
        What was waiting (``b""``: nothing).

    Raises
    ------
    DeviceError
        The read failed.
    """
    n = ser.in_waiting
    return ser.read(n) if n else b""


def write_all(ser, data: bytes) -> None:
    """Write ``data`` (host -> board bytes) to the port.

    Parameters
    ----------
    ser : hapsim.drivers.device_port.DevicePort
        An open port (``write``).
    data : bytes

    Raises
    ------
    DeviceError
        The write failed.
    """
    ser.write(data)


class PortLink:
    """``write``/``read(timeout)`` (the wiring probe's link,
    :func:`hapsim.drivers.haply2_probe.find_directions`) on an open serial-like port.

    Parameters
    ----------
    ser : hapsim.drivers.device_port.DevicePort
        An open port with ``in_waiting``, ``read`` and ``write`` (non-blocking reads);
        left open.
    """

    def __init__(self, ser) -> None:
        self.ser = ser

    def write(self, data: bytes) -> None:
        """Write ``data`` (host -> board bytes) to the port.

        Parameters
        ----------
        data : bytes
            The bytes to send.

        Raises
        ------
        DeviceError
            The port's write failed.
        """
        write_all(self.ser, data)

    def read(self, timeout: float) -> bytes:
        """The bytes waiting, or the first to come within ``timeout`` [s] (polled).

        Parameters
        ----------
        timeout : float
            Longest wait [s] (polled every 0.1 ms); <= 0: one look.

        Returns
        -------
        bytes
            What was waiting (``b""``: nothing came in time).

        Raises
        ------
        DeviceError
            The port's read failed.
        """
        end = time.monotonic() + timeout
        while True:
            data = read_waiting(self.ser)
            if data or time.monotonic() >= end:
                return data
            time.sleep(1e-4)

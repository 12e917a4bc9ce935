"""A serial-like port whose failures are :class:`~hapsim.errors.DeviceError`: what a
device-specific run's record loop reads and writes through, so that a board unplugged (or an
emulated board's process ended) in the middle of a run ends it as a device lost, with its
report, never as pyserial's traceback."""

from __future__ import annotations

from hapsim.errors import DeviceError

__all__ = ["DevicePort"]


class DevicePort:
    """``ser`` with its reads, writes and buffer calls raising :class:`DeviceError`.

    Parameters
    ----------
    ser : serial.Serial or serial-like
        An open port (``read``, ``write``, ``in_waiting``, ``reset_input_buffer``); every
        other attribute (``fileno``, ``idle``, ``close``, ...) is ``ser``'s own.
    name : str
        The device, for the error (``"the FireFader"``).

    Notes
    -----
    pyserial raises ``SerialException`` (an ``OSError``) for a port that failed, an
    ``OSError`` from the operating system, and ``SerialTimeoutException`` for a write that
    timed out; hapsim's own URL handlers (:mod:`hapsim.drivers.urlhandler`) raise the
    same. Each becomes a :class:`DeviceError` naming the operation and the device.
    """

    def __init__(self, ser, name: str) -> None:
        self.ser = ser
        self.name = name

    @classmethod
    def of(cls, ser, name: str) -> "DevicePort":
        """``ser`` as a :class:`DevicePort` (itself when it is one already).

        Parameters
        ----------
        ser : serial.Serial, serial-like or DevicePort
        name : str
            The device, for the error.

        Returns
        -------
        DevicePort
        """
        return ser if isinstance(ser, cls) else cls(ser, name)

    def _failed(self, what: str, exc: BaseException) -> DeviceError:
        return DeviceError(f"{what} {self.name}'s port failed: {str(exc).splitlines()[0]}")

    def write(self, data: bytes):
        """Write ``data`` (``ser.write``'s return).

        Parameters
        ----------
        data : bytes

        Returns
        -------
        int or None
            ``ser.write``'s return: pyserial's count of the bytes written.

        Raises
        ------
        DeviceError
            The write failed or timed out.
        """
        try:
            return self.ser.write(data)
        except Exception as exc:  # serial.SerialException, OSError, timeouts
            raise self._failed("write to", exc) from None

    def read(self, size: int = 1) -> bytes:
        """Read up to ``size`` bytes (``ser.read``'s return).

        Parameters
        ----------
        size : int
            Most bytes read.

        Returns
        -------
        bytes
            Fewer than ``size`` (or none) when the port's read timeout ran out.

        Raises
        ------
        DeviceError
            The read failed.
        """
        try:
            return self.ser.read(size)
        except Exception as exc:  # serial.SerialException, OSError
            raise self._failed("read from", exc) from None

    @property
    def in_waiting(self) -> int:
        """Bytes waiting to be read.

        Raises
        ------
        DeviceError
            The port failed.
        """
        try:
            return self.ser.in_waiting
        except Exception as exc:  # serial.SerialException, OSError
            raise self._failed("read from", exc) from None

    def reset_input_buffer(self) -> None:
        """Drop the bytes waiting.

        Raises
        ------
        DeviceError
            The port failed.
        """
        try:
            self.ser.reset_input_buffer()
        except Exception as exc:  # serial.SerialException, OSError
            raise self._failed("read from", exc) from None

    def __getattr__(self, attr):
        return getattr(self.ser, attr)

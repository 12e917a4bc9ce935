"""Message transports between the host loop and a device.

Every transport offers the same small interface to :mod:`hapsim.daemon.loop`:

``send(msg)``
    Send one protocol message.
``receive(timeout)``
    Messages received so far, waiting up to ``timeout`` [s] for at least one.
``close()``
    Release the port.
``info``
    Dict of facts for the loop report (kind, port, baud, low-latency mode).
``last_frames()``
    Text of the last frames received (CONVENTIONS §11), for error messages.

:class:`InProcessTransport` calls a :class:`~hapsim.daemon.mock.MockDevice` directly (no
bytes: fast lockstep tests). :class:`SerialTransport` opens any port with pyserial (a pty of
the mock or hardware). :class:`EmbeddedMock` starts ``python -m hapsim mock --fd`` on the
master side of a fresh pseudo-terminal whose slave path a :class:`SerialTransport` opens.
"""

from __future__ import annotations

import json
import math
import os
import pty
import subprocess
import sys
import time
import tty
from collections import deque

import firmware_protocol as fp
from hapsim.errors import DeviceError

__all__ = ["InProcessTransport", "SerialTransport", "EmbeddedMock"]


class InProcessTransport:
    """The host talks to a mock device object directly (lockstep, no bytes).

    Parameters
    ----------
    mock : MockDevice
        A lockstep mock; its replies are queued and returned by :meth:`receive`.
    """

    def __init__(self, mock) -> None:
        self.mock = mock
        self._q: deque = deque([mock.hello()])
        self.info = {"kind": "in-process", "port": None, "baud": None, "low_latency": False,
                     "low_latency_note": "in-process: no port"}

    def send(self, msg) -> None:
        """Hand ``msg`` to the mock; queue its replies."""
        self._q.extend(self.mock.handle(msg, 0))

    def receive(self, timeout: float = 0.0) -> list:
        """Queued replies (never waits: the mock answers synchronously)."""
        out = list(self._q)
        self._q.clear()
        return out

    def close(self) -> None:
        """Nothing to release."""

    def last_frames(self) -> str:
        """No frames in-process: empty string."""
        return ""


class SerialTransport:
    """Framed protocol over a pyserial port (hardware, or the mock's pseudo-terminal).

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyACM0``, ``/dev/pts/N``) or any pyserial URL.
    baud : int
        Baud rate (ignored by USB CDC-ACM devices and ptys).
    read_timeout : float
        pyserial read timeout [s]: the longest a single blocking read waits.

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

    def __init__(self, port: str, baud: int = 115200, read_timeout: float = 0.05) -> None:
        import serial  # pyserial; imported here so in-process tests do not need it

        try:
            self._ser = serial.serial_for_url(port, baudrate=baud, timeout=read_timeout,
                                              write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self.info = {"kind": "serial", "port": port, "baud": baud, "low_latency": False,
                     "low_latency_note": ""}
        try:
            self._ser.set_low_latency_mode(True)
            self.info["low_latency"] = True
        except (AttributeError, NotImplementedError, ValueError, OSError) as exc:
            self.info["low_latency_note"] = f"not available: {exc}".strip()
        self._dec = fp.StreamDecoder()
        self._read = self._ser.read
        self._write = self._ser.write

    @property
    def decoder(self) -> fp.StreamDecoder:
        """The stream decoder (counters in ``.stats``)."""
        return self._dec

    def send(self, msg) -> None:
        """Encode and write one message.

        Raises
        ------
        DeviceError
            When the write fails (port gone).
        """
        try:
            self._write(fp.encode(msg))
        except Exception as exc:  # serial.SerialException, OSError, SerialTimeoutException
            raise DeviceError(f"write to {self.info['port']} failed: {exc}\n"
                              f"last frames:\n{self.last_frames()}") from None

    def receive(self, timeout: float = 0.0) -> list:
        """Messages received, waiting up to ``timeout`` [s] for at least one.

        Raises
        ------
        DeviceError
            When the read fails (port gone).
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

    def last_frames(self) -> str:
        """The last frames received as text (CONVENTIONS §11)."""
        return self._dec.format_last_frames()


def _package_root() -> str:
    import hapsim
    return os.path.dirname(os.path.dirname(os.path.abspath(hapsim.__file__)))


class EmbeddedMock:
    """A mock device in a child process on the master side of a new pseudo-terminal.

    Parameters
    ----------
    device : hapsim.scene.Device
        The device the mock models (passed to the child as JSON).
    excitation : hapsim.scene.Excitation
        How the mock's hand starts the motion.
    rate_hz : float
        Native rate announced by the mock [Hz] (the host's CONFIG sets the rate used).
    lockstep : bool
        One period per FORCE (deterministic) instead of real-time ticks.
    seed : int
        Sensor-noise seed.
    base_dir : str, optional
        Directory relative profile paths are resolved against.

    Attributes
    ----------
    port : str
        Slave path (``/dev/pts/N``), to open with :class:`SerialTransport`.
    report_path : str
        JSON file where the child writes its :class:`~hapsim.daemon.mock.MockStats` on exit.

    Notes
    -----
    The child is ``sys.executable -m hapsim mock --fd N`` with the pty master passed by
    ``pass_fds`` and ``PYTHONPATH`` extended with this package's parent, started in a new
    session (a Ctrl-C at the terminal reaches only the host, which then stops the device
    cleanly). The slave is put in raw mode (``tty.setraw``) and kept open by this object
    until :meth:`close`, so the child never sees EIO before the host opens the port.
    """

    def __init__(self, device, excitation, rate_hz: float, *, lockstep: bool = False,
                 seed: int = 0, base_dir: str | None = None) -> None:
        import dataclasses
        import tempfile

        master, slave = pty.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave
        fd, self.report_path = tempfile.mkstemp(prefix="hapsim-mock-", suffix=".json")
        os.close(fd)
        os.unlink(self.report_path)
        spec = {"device": dataclasses.asdict(device),
                "excitation": dataclasses.asdict(excitation), "base_dir": base_dir}
        if not math.isfinite(spec["device"]["force_limit"]):
            spec["device"]["force_limit"] = None
        cmd = [sys.executable, "-m", "hapsim", "mock", "--fd", str(master),
               "--spec", json.dumps(spec), "--rate", repr(float(rate_hz)),
               "--report", self.report_path, "--seed", str(seed)]
        if lockstep:
            cmd.append("--lockstep")
        env = dict(os.environ)
        root = _package_root()
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        try:
            self.proc = subprocess.Popen(cmd, pass_fds=(master,), env=env,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        finally:
            os.close(master)

    def report(self, timeout: float = 3.0) -> dict | None:
        """Wait for the child to exit and return its JSON report (None if it has none)."""
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        try:
            with open(self.report_path) as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def release_slave(self) -> None:
        """Close this object's slave fd (once the host has opened the port)."""
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def close(self) -> None:
        """Close the slave, stop the child if still running, remove the report file."""
        self.release_slave()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        try:
            os.unlink(self.report_path)
        except OSError:
            pass

"""The framed-protocol face of a driver: what the host loop talks to.

:class:`DriverTransport` offers the loop the transport interface of
:mod:`hapsim.daemon.transport` (``send``, ``receive``, ``close``, ``info``,
``last_frames``, ``decoder``) and speaks the driver's bytes on the port:

- HELLO_REQUEST -> a HELLO made from the driver's facts (1 axis, its resolutions and
  force limit); PING -> a PONG at once (the driver has no round trip to measure);
- CONFIG -> arms: the driver's set-up bytes and one zero-force command, whose answer is
  the first record;
- FORCE -> the driver's force packet; each record the device answers with becomes a STATE
  (``seq`` counted here, ``time_us`` the host clock when it was read, ``force_seq = seq - d``
  with ``d`` the delay the scene states: the protocol cannot tell it);
- STOP -> a zero-force packet.

Host-clocked only (the loop must run with ``host_clocked``): the device answers packets.
"""

from __future__ import annotations

import time
from collections import deque

import firmware_protocol as fp
from hapsim.errors import DeviceError

__all__ = ["DriverTransport", "DriverStats"]


class DriverStats:
    """Decoder counters in the shape the host loop reads (:class:`firmware_protocol.DecoderStats`).

    The driver's own counters map as ``skipped`` + ``out_of_range`` -> ``malformed``,
    ``truncated`` -> ``overlong``; the protocol has no CRC, COBS or message types.
    """

    def __init__(self, raw: dict) -> None:
        self.raw = raw
        self.bad_crc = 0
        self.bad_cobs = 0
        self.unknown_type = 0

    @property
    def malformed(self) -> int:
        return int(self.raw.get("skipped", 0) + self.raw.get("out_of_range", 0))

    @property
    def overlong(self) -> int:
        return int(self.raw.get("truncated", 0))

    def as_dict(self) -> dict:
        return dict(self.raw)


class _Dec:
    """What the loop reads of a decoder: counters, and no frame history (no frames)."""

    last_frames = ()

    def __init__(self, stats):
        self.stats = stats


class DriverTransport:
    """A driver's device on a serial port, as the host loop's transport.

    Parameters
    ----------
    driver : hapsim.drivers.base.Driver
        The protocol.
    port : str
        Serial port (hardware or the driver mock's pty).
    delay : int >= 0
        The loop delay d the scene states [samples] (reported in ``force_seq``).
    read_timeout : float
        pyserial read timeout [s].

    Raises
    ------
    DeviceError
        The port cannot be opened.
    """

    def __init__(self, driver, port: str, delay: int = 1, read_timeout: float = 0.005) -> None:
        import serial
        try:
            self._ser = serial.serial_for_url(port, baudrate=driver.baud, rtscts=driver.rtscts,
                                              timeout=read_timeout, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self.driver = driver
        self._d = int(delay)
        self._dec = driver.decoder()
        self.decoder = _Dec(DriverStats(self._dec.stats))
        self._q: deque = deque()
        self._seq = 0
        self._armed = False
        self._t0 = time.monotonic_ns()
        self._last = deque(maxlen=16)
        self.info = {"kind": f"driver {driver.name}", "port": port, "baud": driver.baud,
                     "low_latency": False, "driver": driver.name,
                     "low_latency_note": "driver protocol"}
        try:
            self._ser.set_low_latency_mode(True)
            self.info["low_latency"] = True
        except (AttributeError, NotImplementedError, ValueError, OSError) as exc:
            self.info["low_latency_note"] = f"not available: {exc}".strip()

    def _write(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except Exception as exc:  # serial.SerialException, OSError, timeouts
            raise DeviceError(f"write to {self.info['port']} failed: {exc}") from None

    def send(self, msg) -> None:
        """Translate one framed-protocol message into the driver's bytes (module notes)."""
        dr = self.driver
        t = type(msg)
        if t is fp.Force:
            self._write(dr.encode_force(msg.force[0]))
        elif t is fp.HelloRequest:
            self._q.append(fp.Hello(fp.PROTOCOL_VERSION, 1, dr.device_id, dr.position_scale,
                                    dr.force_scale, dr.force_limit, dr.native_rate_hz))
        elif t is fp.Ping:
            now = (time.monotonic_ns() - self._t0) // 1000
            self._q.append(fp.Pong(msg.nonce, msg.host_time_us, now))
        elif t is fp.Config:
            self._armed = True
            self._write(dr.arm())
        elif t is fp.Stop:
            self._armed = False
            self._write(dr.encode_force(0.0))

    def receive(self, timeout: float = 0.0) -> list:
        """Messages: queued HELLO/PONG, and one STATE per complete record.

        Parameters
        ----------
        timeout : float
            Longest wait [s] for a first message.

        Returns
        -------
        list of firmware_protocol messages
        """
        out = list(self._q)
        self._q.clear()
        ser = self._ser
        end = time.monotonic() + timeout
        try:
            while True:
                waiting = ser.in_waiting
                if waiting:
                    data = ser.read(waiting)
                elif timeout > 0 and not out:
                    data = ser.read(1)
                else:
                    data = b""
                if data:
                    self._last.append(data.hex())
                    for x in self._dec.feed(data):
                        if not self._armed:
                            continue
                        s = self._seq
                        out.append(fp.State(s & 0xFFFFFFFF,
                                            (time.monotonic_ns() - self._t0) // 1000,
                                            fp.STATUS_ARMED | fp.STATUS_CONFIGURED,
                                            (s - self._d) & 0xFFFFFFFF, (x,)))
                        self._seq = s + 1
                if out or timeout <= 0 or time.monotonic() >= end:
                    return out
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.info['port']} failed: {exc}") from None

    def close(self) -> None:
        """Close the port (idempotent)."""
        try:
            self._ser.close()
        except Exception:  # pragma: no cover
            pass

    def last_frames(self) -> str:
        """The last chunks of bytes received, as hex (CONVENTIONS §11)."""
        return "\n".join(self._last)

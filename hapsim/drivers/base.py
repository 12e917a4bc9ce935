"""The small interface every driver implements (see :mod:`hapsim.drivers`)."""

from __future__ import annotations

__all__ = ["Driver", "MappedDecoder", "AlignedDecoder"]


class AlignedDecoder:
    """Fixed-length frames without a start byte: a frame is taken where ``parse`` accepts
    it (its fixed bytes match, its values are plausible), else one byte is dropped and
    the next position tried.

    Subclasses set ``length`` and define ``parse(buf) -> value or None`` (``buf`` holds at
    least ``length`` bytes).

    Attributes
    ----------
    stats : dict
        ``frames`` (taken), ``skipped`` (bytes dropped realigning).
    """

    length = 1

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = {"frames": 0, "skipped": 0}

    def parse(self, buf):
        raise NotImplementedError

    def feed(self, data: bytes) -> list:
        """Bytes in, the values of the frames taken out."""
        buf = self._buf
        buf += data
        out = []
        n = self.length
        while len(buf) >= n:
            v = self.parse(buf)
            if v is not None:
                out.append(v)
                del buf[:n]
                self.stats["frames"] += 1
                continue
            del buf[:1]
            self.stats["skipped"] += 1
        return out


class MappedDecoder:
    """A frame decoder whose outputs are mapped to the axis position [m] or [rad].

    Parameters
    ----------
    frames : object
        A decoder with ``feed(bytes) -> list`` and a ``stats`` dict.
    position : callable
        Frame -> position.
    """

    def __init__(self, frames, position) -> None:
        self.frames = frames
        self.stats = frames.stats
        self._position = position

    def feed(self, data: bytes) -> list:
        """Bytes in, the positions of the complete frames out."""
        pos = self._position
        return [pos(fr) for fr in self.frames.feed(data)]


class Driver:
    """Base class of the drivers: serial settings, units and codec of one device.

    Attributes
    ----------
    name : str
        ``--driver`` name.
    baud : int
        Baud rate.
    rtscts : bool
        Hardware flow control.
    position_scale : float
        Position resolution [m/count] (or [rad/count]).
    force_scale : float
        Force resolution [N/count] (or [N m/count]).
    force_limit : float
        Largest force the protocol can carry [N].
    native_rate_hz : float
        Rate the device is usually run at [Hz].
    device_id : int
        Reported as HELLO.device_id.
    limits : str
        What the protocol cannot do, for ``--help`` and docs/devices.md.
    """

    name = ""
    baud = 115200
    rtscts = False
    position_scale = 0.0
    force_scale = 0.0
    force_limit = 0.0
    native_rate_hz = 1000.0
    device_id = 0
    limits = ""

    def encode_force(self, force: float) -> bytes:
        """Bytes commanding ``force`` [N] on the driven axis (zero on the others)."""
        raise NotImplementedError

    def arm(self) -> bytes:
        """Bytes sent when the host arms the device (CONFIG): by default one zero-force
        command, whose answer is the first record."""
        return self.encode_force(0.0)

    def applied_force(self, force: float) -> float:
        """The force [N] the device receives for ``force`` (after the protocol's
        quantisation and clamp): what identification must fit against."""
        return float(force)

    def decoder(self):
        """A fresh decoder: ``feed(data) -> list of positions [m]``, ``stats`` dict."""
        raise NotImplementedError

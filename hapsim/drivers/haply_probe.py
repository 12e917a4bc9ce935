"""The Haply board's motor direction, found before an identification excites the joint.

The board's two direction bytes are independent (firmware V1.5: the motor's flips its
direction pin in ``create_torque``, the encoder's swaps its two pins in
``initialize_encoder``), and which pair drives the joint the way its angle counts up is
the wiring's, not the protocol's. A wrong pair is positive feedback: identification's
centring spring pushes the joint away and its excitation runs away, so the record of a
normal identification does not show the direction; a pulse does.

The probe (:func:`find_direction`): arm the board (zero torque first: it has no
watchdog), then for each sign a torque pulse of ``PULSE_S`` at a level raised by doubling
from 1/16 of the largest allowed (the smaller of the force limit and the board's 0.123 N
m) until the encoder moved ``min_counts`` counts (static friction holds a joint below
some torque), each pulse ended by zero torque as soon as motion is seen and followed by
``REST_S`` at zero torque. The sign of the motion against the torque's gives the motor
byte; both signs must agree. Zero torque is sent after every pulse and, whatever happens
(an error, an interrupt), when the probe ends.
"""

from __future__ import annotations

import dataclasses
import math
import time

from hapsim.errors import DeviceError, IdentificationError

__all__ = ["DirectionProbe", "find_direction", "probe_port", "PULSE_S", "REST_S",
           "LEVELS"]

#: Longest torque pulse [s] at one level.
PULSE_S = 0.03
#: Zero torque after each pulse [s] (the joint coasts to rest against its friction).
REST_S = 0.05
#: Levels tried per sign: the largest torque allowed times 2^-(LEVELS-1) ... 2^0.
LEVELS = 5


@dataclasses.dataclass(frozen=True)
class DirectionProbe:
    """What :func:`find_direction` found.

    Attributes
    ----------
    motor_direction : int
        The motor's direction byte that makes a positive torque turn the joint the way
        its angle counts up (with the driver's encoder ``direction``).
    relative : int
        +1 when the driver's motor byte was already right, -1 when it was flipped.
    torque : tuple of float
        The torque [N m] of the pulse that moved the joint, positive then negative pulse.
    counts : tuple of int
        The encoder counts moved under it (signed), positive then negative pulse.
    writes : int
        Writes sent (periods).
    """

    motor_direction: int
    relative: int
    torque: tuple
    counts: tuple
    writes: int

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return {"motor_direction": self.motor_direction, "relative": self.relative,
                "torque": list(self.torque), "counts": list(self.counts),
                "writes": self.writes}


class _Exchange:
    """One write, its reply: a board that answers every write (the driver's decoder)."""

    def __init__(self, drv, link, rate_hz: float, pace: bool, timeout: float) -> None:
        self.drv = drv
        self.link = link
        self.dec = drv.decoder()
        self.period = 1.0 / rate_hz
        self.pace = pace
        self.timeout = timeout
        self.writes = 0
        self.missing = 0
        self._next = time.monotonic()

    def send(self, data: bytes) -> float:
        """Send ``data`` (one period), return the last angle answered [rad] (NaN: none
        within the timeout)."""
        if self.pace:
            now = time.monotonic()
            if now < self._next:
                time.sleep(self._next - now)
            self._next = max(now, self._next) + self.period
        self.link.write(data)
        self.writes += 1
        end = time.monotonic() + self.timeout
        got = []
        while not got:
            got = self.dec.feed(self.link.read(max(0.0, end - time.monotonic())))
            if not got and time.monotonic() >= end:
                break
        if not got:
            self.missing += 1
            if self.missing > 20:
                raise DeviceError("the Haply board does not answer its writes (more than "
                                  "20 missing replies while finding the motor direction): "
                                  "check the port and the device id")
            return math.nan
        return float(got[-1])


def find_direction(drv, link, *, force_limit: float, envelope: float,
                   rate_hz: float = 1000.0, min_counts: int = 3, pace: bool = True,
                   timeout: float = 0.05) -> DirectionProbe:
    """Find the motor direction byte of a Haply joint from a torque pulse of each sign
    (module notes).

    Parameters
    ----------
    drv : hapsim.drivers.haply.HaplyM3
        The driver as configured (its ``direction`` is kept; its ``motor_direction`` is
        the one tried).
    link : object
        ``write(bytes)`` and ``read(timeout [s]) -> bytes`` on the board's port.
    force_limit : float
        Largest torque [N m] (capped at the board's 0.123 N m).
    envelope : float
        A pulse also ends when the joint moved this far [rad].
    rate_hz : float
        Write rate [Hz] (one reply per write).
    min_counts : int
        Encoder counts of motion that count as moving.
    pace : bool
        Pace the writes at ``rate_hz`` on the host's clock (False: as fast as the link
        answers, for a board that advances one period per write).
    timeout : float
        Longest wait for a reply [s].

    Returns
    -------
    DirectionProbe

    Raises
    ------
    IdentificationError
        No motion of ``min_counts`` counts under the largest torque of either sign (the
        joint is blocked, held, unpowered, or its static friction exceeds the force
        limit), or the two signs disagree (something else moves the joint).
    DeviceError
        The board does not answer.
    """
    from hapsim.drivers.haply import MAX_TORQUE
    top = min(float(force_limit), MAX_TORQUE)
    if not (math.isfinite(top) and top > 0):
        raise IdentificationError(f"no torque to probe the motor direction with: force "
                                  f"limit {force_limit!r} N m")
    q = drv.position_scale                       # one count [rad]
    ex = _Exchange(drv, link, rate_hz, pace, timeout)
    n_pulse = max(1, round(PULSE_S * rate_hz))
    n_rest = max(1, round(REST_S * rate_hz))
    reach = min(min_counts * q, float(envelope)) if envelope > 0 else min_counts * q
    zero = drv.encode_force(0.0)
    found_t, found_c, rel = [], [], []
    x = math.nan
    try:
        ex.send(drv.arm())
        for _ in range(3):                      # the replies of a board in step
            x = ex.send(zero)
        for sign in (1.0, -1.0):
            moved = None
            for k in range(LEVELS - 1, -1, -1):
                tau = sign * top * 2.0 ** -k
                x0 = x if math.isfinite(x) else ex.send(zero)
                dx = 0.0
                for _ in range(n_pulse):
                    x = ex.send(drv.encode_force(tau))
                    if math.isfinite(x) and math.isfinite(x0) and abs(x - x0) >= reach - q / 2:
                        dx = x - x0
                        break
                for _ in range(n_rest):          # zero at once, then let it stop
                    x = ex.send(zero)
                    if not dx and math.isfinite(x) and math.isfinite(x0) \
                            and abs(x - x0) >= reach - q / 2:
                        dx = x - x0             # it moved after the delay
                if dx:
                    moved = (tau, round(dx / q))
                    break
            if moved is None:
                raise IdentificationError(
                    f"the Haply joint did not move {min_counts} encoder counts under "
                    f"{sign * top:+.4g} N m pulses of {PULSE_S * 1e3:g} ms (raised from "
                    f"{sign * top * 2.0 ** -(LEVELS - 1):+.4g} N m): the motor direction "
                    f"cannot be found. The joint is blocked, held, or unpowered, or its "
                    f"static friction exceeds --force-limit; free it (let go of the "
                    f"handle: identify with --hand after one without it), or raise the "
                    f"limit (at most the board's {MAX_TORQUE} N m), or give the motor "
                    f"direction (--protocol-option motor_direction=0 or 1: then it is not "
                    f"probed)")
            found_t.append(moved[0])
            found_c.append(moved[1])
            rel.append(1 if moved[1] * moved[0] > 0 else -1)
    finally:
        try:
            link.write(drv.stop_bytes(x if math.isfinite(x) else 0.0))
        except Exception:  # noqa: BLE001 -- best effort: the port may be gone
            pass
    if rel[0] != rel[1]:
        raise IdentificationError(
            f"the Haply joint moved the same way under both torque signs ({found_c[0]:+d} "
            f"counts under {found_t[0]:+.4g} N m, {found_c[1]:+d} under {found_t[1]:+.4g} "
            f"N m): something else moves it (a hand, a spring, gravity); let go of the "
            f"handle and identify again")
    r = rel[0]
    md = drv.motor_direction if r > 0 else 1 - drv.motor_direction
    return DirectionProbe(md, r, tuple(found_t), tuple(found_c), ex.writes)


class _SerialLink:
    """``write``/``read(timeout)`` on a serial port (pyserial)."""

    def __init__(self, port: str, baud: int) -> None:
        import serial
        try:
            # a fixed short read timeout (setting it per read reconfigures the port)
            self.ser = serial.serial_for_url(port, baudrate=baud, timeout=0.005,
                                             write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self.port = port

    def write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
        except Exception as exc:  # serial.SerialException, OSError, timeouts
            raise DeviceError(f"write to {self.port} failed: {exc}") from None

    def read(self, timeout: float) -> bytes:
        """Bytes waiting, or the first within the port's 5 ms (the caller loops to its
        own ``timeout`` [s])."""
        try:
            n = self.ser.in_waiting
            return self.ser.read(n if n else 1)
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.port} failed: {exc}") from None

    def close(self) -> None:
        try:
            self.ser.flush()
            self.ser.close()
        except Exception:  # noqa: BLE001 -- the port may be gone
            pass


def probe_port(drv, port: str, *, force_limit: float, envelope: float,
               rate_hz: float = 1000.0, timeout: float = 0.05,
               pace: bool = True) -> DirectionProbe:
    """:func:`find_direction` on a serial port (hardware, or a driver mock's pty).

    Parameters
    ----------
    drv : hapsim.drivers.haply.HaplyM3
    port : str
    force_limit, envelope, rate_hz, timeout, pace
        As :func:`find_direction` ([N m], [rad], [Hz], [s]).

    Returns
    -------
    DirectionProbe

    Raises
    ------
    IdentificationError, DeviceError
        As :func:`find_direction`; DeviceError also when the port cannot be opened.
    """
    link = _SerialLink(port, drv.baud)
    try:
        return find_direction(drv, link, force_limit=force_limit, envelope=envelope,
                              rate_hz=rate_hz, timeout=timeout, pace=pace)
    finally:
        link.close()

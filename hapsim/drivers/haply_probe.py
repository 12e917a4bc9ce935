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
some torque), each pulse ended as soon as motion is seen, then the opposite torque for as
many periods (an equal and opposite impulse: it takes back the velocity the pulse gave,
whatever the motor's sign; on the host's clock, for as long as the pulse was held) and
``REST_S`` at zero torque. The sign of the motion against
the torque's gives the motor byte; both signs must agree.

Each pulse starts from rest: zero torque until the encoder has not moved for a whole
measurement window (``PULSE_S + REST_S``), at most ``SETTLE_S``. A joint with little
friction coasts long after a pulse (an inertia of 1e-3 kg m^2 on 1e-3 N m s/rad: a time
constant of 1 s), and a pulse measured from a coasting joint reads the coast, not the
torque: the next pulse of the other sign then "moves the same way". A joint that slows
under friction alone (its speed falls monotonically) and moved less than one count in the
last window moves less than one count in the next, below the ``min_counts`` a pulse must
show. A joint that does not come to rest is moved by something else and is refused.
Zero torque is sent after every pulse and, whatever happens (an error, an interrupt),
when the probe ends; the stop's replies are read (left on the line, they would be taken
for the answer to the next arming).
"""

from __future__ import annotations

import dataclasses
import math
import time

from hapsim.drivers.exchange import Exchange, SerialLink
from hapsim.errors import IdentificationError

__all__ = ["DirectionProbe", "find_direction", "probe_port", "PULSE_S", "REST_S",
           "LEVELS", "SETTLE_S", "AxisProbe", "probe_axis", "Exchange", "pulse_limits"]

#: Longest torque pulse [s] at one level.
PULSE_S = 0.03
#: Zero torque after each pulse [s] (the joint coasts to rest against its friction).
REST_S = 0.05
#: Levels tried per sign: the largest torque allowed times 2^-(LEVELS-1) ... 2^0.
LEVELS = 5
#: Longest wait at zero torque for the joint to come to rest before a pulse [s].
SETTLE_S = 3.0


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
        """JSON-ready fields.

        Returns
        -------
        dict
            The fields by name, tuples as lists (``torque`` [N m], ``counts``).
        """
        return {"motor_direction": self.motor_direction, "relative": self.relative,
                "torque": list(self.torque), "counts": list(self.counts),
                "writes": self.writes}


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
    q = drv.position_scale                       # one count [rad]
    top, reach = pulse_limits(force_limit, q, envelope, min_counts, "the motor direction")
    ex = Exchange(drv, link, rate_hz, pace, timeout,
                  resync=drv.resync if getattr(drv, "unframed", False) else None)
    zero = drv.encode_force(0.0)
    x = math.nan
    try:
        ex.send(drv.arm())
        for _ in range(3):                      # the replies of a board in step
            x = ex.send(zero)
        axis = probe_axis(ex.send, drv.encode_force, zero, top=top, count=q, reach=reach,
                          rate_hz=rate_hz, min_counts=min_counts, label="the Haply joint",
                          option="motor_direction", clock=time.monotonic if pace else None)
        x = axis.last
    finally:
        ex.stop(drv.stop_bytes(x if math.isfinite(x) else 0.0), 2)
    r = axis.relative
    md = drv.motor_direction if r > 0 else 1 - drv.motor_direction
    return DirectionProbe(md, r, axis.torque, axis.counts, ex.writes)


def pulse_limits(force_limit: float, count: float, envelope: float, min_counts: int,
                 what: str) -> tuple:
    """The largest torque of the pulses and the motion that counts as moving.

    Parameters
    ----------
    force_limit : float
        Largest torque allowed [N m].
    count : float
        One encoder count [rad].
    envelope : float
        Largest motion allowed [rad] (not positive: none).
    min_counts : int
    what : str
        What is probed, for the message.

    Returns
    -------
    (float, float)
        ``min(force_limit, 0.123)`` [N m] (the board's clamp) and ``min(min_counts
        count, envelope)`` [rad].

    Raises
    ------
    IdentificationError
        No positive torque allowed.
    """
    from hapsim.drivers.haply import MAX_TORQUE
    top = min(float(force_limit), MAX_TORQUE)
    if not (math.isfinite(top) and top > 0):
        raise IdentificationError(f"no torque to probe {what} with: force limit "
                                  f"{force_limit!r} N m")
    reach = min_counts * count
    return top, (min(reach, float(envelope)) if envelope > 0 else reach)


@dataclasses.dataclass(frozen=True)
class AxisProbe:
    """What :func:`probe_axis` found on one joint.

    Attributes
    ----------
    relative : int
        +1 when a positive torque turns the joint the way its angle counts up, else -1.
    torque : tuple of float
        The torque [N m] of the pulse that moved the joint, positive then negative pulse.
    counts : tuple of int
        The encoder counts moved under it (signed), positive then negative pulse.
    last : float
        The joint's last angle read [rad] (NaN: the last reply was missing).
    """

    relative: int
    torque: tuple
    counts: tuple
    last: float


def probe_axis(send, write_of, zero: bytes, *, top: float, count: float, reach: float,
               rate_hz: float, min_counts: int = 3, label: str = "the Haply joint",
               option: str = "motor_direction", clock=None) -> AxisProbe:
    """One joint's torque pulses of each sign, each from rest (module notes): the sign of
    its motion against the torque's. Shared by the 1-DoF board (:func:`find_direction`)
    and each joint of the 2DIY (:func:`hapsim.drivers.haply2_probe.find_directions`).

    Parameters
    ----------
    send : callable
        ``send(bytes) -> float``: one write (one period), the joint's angle read after it
        [rad] (NaN: no reply).
    write_of : callable
        ``write_of(tau) -> bytes``: the write of torque ``tau`` [N m] on this joint (zero
        on any other).
    zero : bytes
        The zero-torque write.
    top : float
        Largest torque [N m].
    count : float
        One encoder count [rad] (at the set-up's resolution).
    reach : float
        Motion that counts as moving [rad] (``min_counts`` counts, or less within an
        envelope).
    rate_hz : float
        Writes per second [Hz] (the pulse, rest and settling lengths in writes).
    min_counts : int
    label, option : str
        The joint's name and the protocol option that gives its motor direction, for the
        messages.
    clock : callable, optional
        ``clock() -> float`` [s], the host's clock when the writes are paced on it: the
        opposite torque is then held for the time the pulse was (a loaded host holds a
        write longer than its period, and an impulse counted in writes leaves the joint
        coasting). Default: counted in writes (a board paced by the writes: lockstep).

    Returns
    -------
    AxisProbe

    Raises
    ------
    IdentificationError
        The joint does not come to rest within :data:`SETTLE_S` at zero torque, or does
        not move ``min_counts`` counts under the largest torque of either sign, or moves
        the same way under both signs (something else moves it).
    """
    from hapsim.drivers.haply import MAX_TORQUE
    n_pulse = max(1, round(PULSE_S * rate_hz))
    n_rest = max(1, round(REST_S * rate_hz))
    n_still = n_pulse + n_rest
    n_settle = max(n_still, round(SETTLE_S * rate_hz))
    found_t, found_c, rel = [], [], []
    x = math.nan

    def settle():
        """Zero torque until the angle has not moved for ``n_still`` replies (a reply that
        did not come says nothing of the motion: neither counted nor a reset; a loaded
        host misses one now and then, and a reset at each kept a resting 2DIY joint
        "not at rest" for the whole 3 s, once in a fresh clone's CI)."""
        nonlocal x
        ref, still = math.nan, 0
        for _ in range(n_settle):
            x = send(zero)
            if not math.isfinite(x):
                continue
            if math.isfinite(ref) and abs(x - ref) < count / 2:
                still += 1
                if still >= n_still:
                    return x
            else:
                ref, still = x, 0
        raise IdentificationError(
            f"{label} did not come to rest at zero torque within {SETTLE_S:g} s (it "
            f"never stayed within a count for {n_still} periods): something else moves it "
            f"(a hand, a spring, gravity), or it coasts that long on its own (a joint "
            f"whose friction is small for its inertia: inertia over friction of a second "
            f"or more); let go of the handle and identify again")
    for sign in (1.0, -1.0):
        moved = None
        for k in range(LEVELS - 1, -1, -1):
            tau = sign * top * 2.0 ** -k
            x0 = settle()
            dx = 0.0
            sent = 0
            t0 = None if clock is None else clock()
            for _ in range(n_pulse):
                x = send(write_of(tau))
                sent += 1
                if math.isfinite(x) and abs(x - x0) >= reach - count / 2:
                    dx = x - x0
                    break
            # the opposite impulse: whatever the motor's sign, it takes back the
            # velocity the pulse gave (a joint with little friction coasts for seconds)
            # (on the host's clock: for as long as the pulse was held, each write held
            # until the next one's)
            brake = write_of(-tau)
            t1 = None if clock is None else clock()
            braked = 0
            while (braked < sent if clock is None
                   else braked == 0 or clock() - t1 < t1 - t0):
                x = send(brake)
                braked += 1
                if not dx and math.isfinite(x) and abs(x - x0) >= reach - count / 2:
                    dx = x - x0             # it moved after the delay
            for _ in range(n_rest):          # zero, then let it stop
                x = send(zero)
                if not dx and math.isfinite(x) and abs(x - x0) >= reach - count / 2:
                    dx = x - x0
            if dx:
                moved = (tau, round(dx / count))
                break
        if moved is None:
            raise IdentificationError(
                f"{label} did not move {min_counts} encoder counts under "
                f"{sign * top:+.4g} N m pulses of {PULSE_S * 1e3:g} ms (raised from "
                f"{sign * top * 2.0 ** -(LEVELS - 1):+.4g} N m): the motor direction "
                f"cannot be found. The joint is blocked, held, or unpowered, or its "
                f"static friction exceeds --force-limit; free it (let go of the "
                f"handle: identify with --hand after one without it), or raise the "
                f"limit (at most the board's {MAX_TORQUE} N m), or give the motor "
                f"direction (--protocol-option {option}=0 or 1: then it is not "
                f"probed)")
        found_t.append(moved[0])
        found_c.append(moved[1])
        rel.append(1 if moved[1] * moved[0] > 0 else -1)
    if rel[0] != rel[1]:
        raise IdentificationError(
            f"{label} moved the same way under both torque signs ({found_c[0]:+d} "
            f"counts under {found_t[0]:+.4g} N m, {found_c[1]:+d} under {found_t[1]:+.4g} "
            f"N m): something else moves it (a hand, a spring, gravity); let go of the "
            f"handle and identify again")
    return AxisProbe(rel[0], tuple(found_t), tuple(found_c), x)


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
    wd = None
    link = SerialLink(port, drv.baud, zero=drv.encode_force(0.0))
    try:
        if pace:
            # a board on its own clock holds each pulse's torque while the host does not
            # run: the host's watchdog beside the probe too (hapsim.drivers.
            # torque_watchdog; before, none: an identify over a lossy M3 held a torque
            # 54 ms, the independent board model's count, tools/independent_boards)
            from hapsim.drivers.resync import HOLD_BOUND_S
            from hapsim.drivers.torque_watchdog import start_watchdog
            wd, _ = start_watchdog(port, drv.encode_force(0.0), HOLD_BOUND_S, ser=link.ser)
            link.watchdog = wd
    except BaseException:
        link.close()
        raise
    try:
        if wd is not None:
            wd.arm()
        return find_direction(drv, link, force_limit=force_limit, envelope=envelope,
                              rate_hz=rate_hz, timeout=timeout, pace=pace)
    finally:
        if wd is not None:
            wd.arm(False)
        link.close()
        if wd is not None:
            wd.close()

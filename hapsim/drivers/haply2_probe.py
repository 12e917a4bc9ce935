"""The Haply 2DIY's wiring, checked joint by joint before any torque loop runs.

Each joint of the 2DIY has its own motor and encoder direction bytes (firmware V1.5 keeps
them apart: ``actuators[k]``, ``encoders[k]``), and the bytes hAPI sends for a generation
(:data:`hapsim.drivers.haply2.GENERATIONS`) are right only for a board wired as Haply
wires it. A joint whose motor, or whose encoder, is wired backwards turns its angle down
under a positive torque: with the pantograph's kinematics that is positive feedback, and
every spring pushes the handle away.

The probe (:func:`find_directions`): arm the board (zero torque first: no watchdog), then
on each joint in turn, the other at zero torque, the 1-DoF joint's torque pulses of each
sign from rest (:func:`hapsim.drivers.haply_probe.probe_axis`: raised by doubling until
the joint's encoder moved 3 counts, each pulse braked by the opposite impulse), zero
torque whatever happens. A joint whose angle went up under a positive torque is wired as
its bytes say (or both its motor and its encoder are reversed: see below). A joint whose
angle went down has its motor *or* its encoder reversed, and a pulse cannot tell which:
a reversed motor turns the joint down, a reversed encoder counts the joint's rise down,
and either reads the same. The probe then refuses, naming the joint and the two
corrections (the motor byte flipped, or the encoder byte flipped: ``motor_direction`` /
``encoder_direction`` of :class:`hapsim.drivers.haply2.Haply2DIY`); given the one that
matches the board, the probe passes and the loop is right.

What no pulse shows: a joint whose motor *and* encoder are both reversed (a positive
torque turns it down and its encoder counts that down as up: the loop on that joint is
stable, but its angle is mirrored about the pose it was armed at, and the handle's
position computed from it is wrong), and which of the two is reversed on a joint the
probe refuses. The joints' coupling through the pantograph's inertia could tell an
encoder from a motor, but it is about a tenth of a joint's own response (the off-diagonal
of the joint-space inverse inertia at the shipped operating points): below the 3 counts
a pulse moves.
"""

from __future__ import annotations

import dataclasses
import math
import time

from hapsim.errors import IdentificationError

__all__ = ["WiringProbe", "find_directions"]


@dataclasses.dataclass(frozen=True)
class WiringProbe:
    """What :func:`find_directions` found (when it did not refuse).

    Attributes
    ----------
    relative : tuple of int
        Per joint, +1: a positive torque turned its angle up.
    torque : tuple of tuple of float
        Per joint, the torques [N m] of the pulses that moved it (positive, negative).
    counts : tuple of tuple of int
        Per joint, the encoder counts moved under them (signed).
    writes : int
        Writes sent (periods).
    setups : int
        Set-ups sent (the arming and the closing re-synchronisation: 2).
    """

    relative: tuple
    torque: tuple
    counts: tuple
    writes: int
    setups: int = 2

    def to_dict(self) -> dict:
        """JSON-ready fields.

        Returns
        -------
        dict
            The fields by name, tuples as lists (``torque`` [N m], ``counts``).
        """
        return {"relative": list(self.relative), "torque": [list(t) for t in self.torque],
                "counts": [list(c) for c in self.counts], "writes": self.writes,
                "setups": self.setups}


def find_directions(drv, link, joints_deg, *, force_limit: float, envelope: float,
                    rate_hz: float = 1000.0, min_counts: int = 3, pace: bool = True,
                    timeout: float = 0.05, first_timeout: float | None = None) -> WiringProbe:
    """Check each joint of a 2DIY turns the way its angle counts up (module notes).

    Parameters
    ----------
    drv : hapsim.drivers.haply2.Haply2DIY
        The codec as configured (its direction bytes are the ones checked).
    link : object
        ``write(bytes)`` and ``read(timeout [s]) -> bytes`` on the board's port.
    joints_deg : sequence of float, length 2
        The joints' angles [deg] at the pose the handle is held at (the set-up's offsets).
    force_limit : float
        Largest torque [N m] (capped at the board's 0.123 N m).
    envelope : float
        A pulse also ends when the joint moved this far [rad].
    rate_hz, min_counts, pace, timeout
        As :func:`hapsim.drivers.haply_probe.find_direction` ([Hz], counts, bool, [s]).
    first_timeout : float, optional
        Longest wait for the arming's reply [s] (a board process still starting: the
        probe is the first to talk to it); default ``timeout``.

    Returns
    -------
    WiringProbe

    Raises
    ------
    IdentificationError
        A joint whose angle went down under a positive torque (its motor or its encoder
        is wired backwards: the joint and both corrections named); a joint that does not
        come to rest, does not move, or moves the same way under both signs (as the 1-DoF
        probe).
    DeviceError
        The board does not answer (no reply to more than 20 writes in a row; replies that
        come late are read, :class:`hapsim.drivers.exchange.Exchange`).
    """
    from hapsim.drivers.exchange import Exchange
    from hapsim.drivers.haply_probe import probe_axis, pulse_limits
    count = 2 * math.pi / drv.resolution
    top, reach = pulse_limits(force_limit, count, envelope, min_counts, "the 2DIY's wiring")
    ex = Exchange(drv, link, rate_hz, pace, timeout, first_timeout=first_timeout,
                  lost="the 2DIY does not answer its writes (no reply to more than 20 "
                       "writes in a row while checking its wiring): check the port and "
                       "the device id")
    zero = drv.write_bytes((0.0, 0.0))
    found = []
    try:
        ex.reply(drv.arm_bytes(joints_deg))
        for _ in range(3):                      # the replies of a board in step
            ex.reply(zero)
        for j in range(2):
            def send(data, j=j):
                r = ex.reply(data)
                return math.nan if r is None else drv.joints_of(r)[j]

            def write_of(tau, j=j):
                return drv.write_bytes((tau, 0.0) if j == 0 else (0.0, tau))
            found.append(probe_axis(send, write_of, zero, top=top, count=count,
                                    reach=reach, rate_hz=rate_hz, min_counts=min_counts,
                                    label=f"the 2DIY's joint {j + 1}",
                                    option="motor_direction",
                                    clock=time.monotonic if pace else None))
    finally:
        ex.stop(drv.arm_bytes(joints_deg), 2)   # zero torque whatever the parser is in
    g = drv.generation
    bad = [j for j in range(2) if found[j].relative < 0]
    if bad:
        def flipped(bytes_, js):
            return tuple(1 - b if k in js else b for k, b in enumerate(bytes_))
        names = " and ".join(f"joint {j + 1}" for j in bad)
        moved = ", ".join(f"{found[j].counts[0]:+d} counts under {found[j].torque[0]:+.4g} "
                          f"N m" for j in bad)
        raise IdentificationError(
            f"the 2DIY's {names} turned {'their' if len(bad) > 1 else 'its'} angle down "
            f"under a positive torque ({moved}"
            f"): {'each' if len(bad) > 1 else 'its'} motor or encoder is wired backwards "
            f"against the {g.name} direction bytes (motor {g.motor_direction}, encoder "
            f"{g.encoder_direction}), and a torque pulse cannot tell which; a torque loop "
            f"would push the handle away. Set the 2DIY up with "
            f"motor_direction={flipped(g.motor_direction, bad)} if the motor is reversed, "
            f"or encoder_direction={flipped(g.encoder_direction, bad)} if the encoder is")
    return WiringProbe(tuple(a.relative for a in found), tuple(a.torque for a in found),
                       tuple(a.counts for a in found), ex.writes)

"""What every driver mock's board shares: the handle's physics driven by the board's force,
on the board's own clock or in lockstep (:class:`Actuated`), and the exact integration of
the physics over the real time between two forces (:class:`WallClock`).

The physics is the mock device's (:class:`hapsim.device_model.MockPhysics`: exact ZOH,
optional Coulomb friction, noise); each board (:mod:`hapsim.emulated.firefader_board`,
:mod:`hapsim.emulated.haply_board`, :mod:`hapsim.emulated.hapkit_serial_board`) adds its
firmware's bytes and its rule for a silence.
"""

from __future__ import annotations

import math
from collections import deque

from hapsim.device_model import MockPhysics

__all__ = ["Actuated", "WallClock"]



class Actuated:
    """The physics side shared by the driver mocks: delay, clamp, and the device's clock.

    Two clocks (``clock``):

    - ``"wall"``: the device keeps its own time (:class:`WallClock`): its physics runs
      with the monotonic time :func:`serve` gives each packet, holding the last force
      while the host is silent or late, as a board does. A packet's force takes effect
      when it arrives plus the latency that brings the loop to the device's delay
      (:attr:`extra_latency_s`); the sample a reply carries is taken when its packet
      arrives.
    - ``"lockstep"`` (named, for deterministic tests): one period per command; the force
      of the packet ``delay`` packets back is applied over it.

    Parameters
    ----------
    device : hapsim.scene.Device
        Mass (or inertia), friction, delay and imperfections of the driven axis.
    rate_hz : float
        Period the host runs at [Hz] (lockstep: one period per command).
    excitation : hapsim.scene.Excitation, optional
        Initial displacement / velocity / hand force.
    limit : float
        The device's own force clamp [N] (or [N m]); the device section's is also applied.
    seed : int
        Sensor-noise seed.
    clock : {"wall", "lockstep"}
        The device's clock (above).

    Attributes
    ----------
    applied : list of float
        Forces applied per command (for tests).

    Raises
    ------
    ConfigError
        An unknown ``clock``.
    """

    #: The delay [periods] a host-clocked board on the wall clock has by itself: the
    #: sample of a reply is taken when the packet arrives, and the force computed from it
    #: arrives with the next packet, one period later.
    natural_delay = 1.0

    def __init__(self, device, rate_hz, excitation, limit, seed, clock="lockstep"):
        from hapsim.errors import ConfigError
        if clock not in ("wall", "lockstep"):
            raise ConfigError(f"unknown clock {clock!r}; valid: wall, lockstep", key="clock")
        self.clock = clock
        self.physics = MockPhysics(device, rate_hz, excitation, seed=seed)
        self.delay = int(device.delay)
        self.limit = min(float(device.force_limit), float(limit))
        self._fifo: deque = deque([0.0] * self.delay)
        self.applied: list = []
        self.held = 0.0
        self.clamped = 0
        self.last_command = 0.0
        self.wall = WallClock(self.physics) if clock == "wall" else None
        #: Latency [s] added to each force on the wall clock: what brings a board whose
        #: own delay is :attr:`natural_delay` to the scene's (never negative: a board is
        #: not faster than its protocol).
        self.extra_latency_s = (max(0.0, float(device.delay) - self.natural_delay)
                                / float(rate_hz))

    def apply(self, force, now: float | None = None) -> None:
        """Lockstep: queue ``force``, apply the one due (``delay`` commands back), advance a
        period. Wall clock: run the physics to ``now`` [s], then the force takes effect at
        ``now + extra_latency_s``. ``None``: this command changes no force (the one held
        goes on).

        Parameters
        ----------
        force : float or None
            The command's force [N] (or [N m]); clamped to :attr:`limit`, a non-finite one
            applied as 0.
        now : float, optional
            Wall clock: the packet's time on the device's clock [s] (needed); lockstep:
            ignored.

        Raises
        ------
        ValueError
            Wall clock: ``now`` not finite (:meth:`WallClock.run_to`).
        TypeError
            Wall clock: ``now`` None.
        """
        if force is not None:
            self.last_command = force
            if not math.isfinite(force):
                force = 0.0                 # a corrupted float is no reason to push hard
        if self.wall is not None:
            self.wall.run_to(now)
            self.held = self.wall.held
            if force is None:
                return
            if abs(force) > self.limit:
                force = math.copysign(self.limit, force)
                self.clamped += 1
            self.applied.append(force)
            self.wall.schedule(now + self.extra_latency_s, force)
            return
        self._fifo.append(force)
        due = self._fifo.popleft()
        if due is None:
            due = self.held
        if abs(due) > self.limit:
            due = math.copysign(self.limit, due)
            self.clamped += 1
        self.held = due
        self.applied.append(due)
        self.physics.advance(due)

    def commands(self) -> int:
        """Force commands applied so far.

        Returns
        -------
        int
            Entries of :attr:`applied`: every command in lockstep, those that set a force
            on the wall clock.
        """
        return len(self.applied)

    def held_from_now(self) -> float:
        """Lockstep: the force the device holds over the coming period [N], the head of
        its delay queue (clamped; the one held goes on where a queued command set none)
        -- what a firmware that reports "the force applied" says at the instant it read
        the position it sends (the wall clock's reply takes it from its schedule).

        Returns
        -------
        float
            The force [N] (or [N m]).
        """
        due = self._fifo[0] if self._fifo else None
        if due is None:
            return self.held
        if not math.isfinite(due):
            return 0.0
        return math.copysign(self.limit, due) if abs(due) > self.limit else due

    def settles_on(self) -> float:
        """The force the device holds once the commands in its delay queue are applied
        (the last one that sets a force), [N]: what it is left with when the host is gone.

        Returns
        -------
        float
            The force [N] (or [N m]), clamped (a non-finite command: 0).
        """
        if self.wall is not None:
            return self.wall.settles_on()
        for f in reversed(self._fifo):
            if f is not None:
                return 0.0 if not math.isfinite(f) else max(-self.limit, min(self.limit, f))
        return self.held

    def apply_now(self, force: float) -> None:
        """The device sets ``force`` itself, at once (a firmware's silence rule): the queue
        is emptied too.

        Parameters
        ----------
        force : float
            The force held from now on [N] (or [N m]; not clamped).
        """
        self._fifo = deque([None] * self.delay)
        self.held = force
        if self.wall is not None:
            self.wall.set_now(force)
            return
        self.physics.hold_now(force)

    def idle(self, silent_s: float) -> bytes:
        """The host has been silent ``silent_s`` [s]; by default nothing happens (the
        device holds its force: no watchdog).

        Parameters
        ----------
        silent_s : float
            Time since the host's last bytes [s].

        Returns
        -------
        bytes
            ``b""`` here; a board's override returns what its firmware sends meanwhile.
        """
        return b""

    #: From the end of a command read to the end of its answer on the wire [s]: what
    #: :func:`serve` waits before writing the answer (0: at once, a USB device's time).
    reply_delay_s = 0.0


class WallClock:
    """A device's own time: its physics integrated exactly over the real time between
    events, holding the force in effect (a board's motor holds its last PWM duty).

    Events are the packets' arrival times and the times their forces take effect; the
    physics is stepped from one to the next by :meth:`MockPhysics.advance_interval`, cut
    at the period boundaries (the hand force is per period).

    Parameters
    ----------
    physics : hapsim.device_model.MockPhysics
        The device's plant (``hold: zoh``).

    Attributes
    ----------
    t : float
        The device's time the physics has reached [s] (0 at the first packet's clock).
    held : float
        The force in effect [N].
    """

    def __init__(self, physics) -> None:
        self.physics = physics
        self.t = 0.0
        self.held = 0.0
        #: The largest |position| the physics reached [m] (or [rad]): the true excursion,
        #: whatever the host believes.
        self.excursion = abs(physics.x)
        #: The longest time a non-zero force was held with no command taking effect
        #: [s] (a board without a watchdog, its host silent), up to the last event.
        self.longest_hold = 0.0
        self._since = 0.0                # when the force in effect took effect [s]
        self._due: deque = deque()       # (time [s], force [N]) not yet in effect

    def schedule(self, at: float, force: float) -> None:
        """The force ``force`` [N] takes effect at ``at`` [s] (in time order: a later
        packet's force never takes effect before an earlier one's).

        Parameters
        ----------
        at : float
            The device's time it takes effect at [s].
        force : float
            The force [N] (or [N m]).
        """
        if self._due and at < self._due[-1][0]:
            at = self._due[-1][0]
        self._due.append((float(at), float(force)))

    def set_now(self, force: float) -> None:
        """The device sets its force itself, at once (a firmware's silence rule); what was
        due is dropped.

        Parameters
        ----------
        force : float
            The force in effect from :attr:`t` on [N] (or [N m]).
        """
        self._due.clear()
        self._take(float(force))

    def _take(self, force: float) -> None:
        """A force takes effect now (:attr:`t`): the hold it ends counted."""
        if self.held != 0.0:
            self.longest_hold = max(self.longest_hold, self.t - self._since)
        self.held, self._since = force, self.t

    def settles_on(self) -> float:
        """The force in effect once everything due has taken effect [N].

        Returns
        -------
        float
            The last force scheduled, else :attr:`held` [N] (or [N m]).
        """
        return self._due[-1][1] if self._due else self.held

    def run_to(self, now: float) -> None:
        """Integrate the physics to ``now`` [s] (nothing when ``now`` is not later).

        Parameters
        ----------
        now : float
            The device's time to reach [s].

        Raises
        ------
        ValueError
            ``now`` is not finite (a wall-clock device needs the packet's time).
        """
        if not math.isfinite(now):
            raise ValueError("a device on the wall clock needs the time of each packet")
        ph = self.physics
        T = ph.period
        due = self._due
        while self.t < now:
            boundary = (ph.n + 1) * T
            nxt = min(now, boundary)
            if due and due[0][0] < nxt:
                nxt = max(due[0][0], self.t)
            ph.advance_interval(nxt - self.t, self.held)
            self.t = nxt
            if abs(ph.x) > self.excursion:
                self.excursion = abs(ph.x)
            if nxt >= boundary:
                ph.end_period()
            while due and due[0][0] <= self.t:
                self._take(due.popleft()[1])
        while due and due[0][0] <= self.t:
            self._take(due.popleft()[1])


def offline_record(scene, driver, command, n: int, time_of) -> dict:
    """A 1-D scene's loop closed through a board's bytes on a simulated clock: the
    engine's port force at each reading, the driver's applied (wire-rounded) force logged,
    the next command sent with it (the host's order: read, compute, write).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated scene (its engine, device delay and force limit [N]).
    driver : hapsim.drivers.base.Driver
        The driver whose ``applied_force`` the record logs.
    command : callable
        ``command(j, f) -> x``: sends command ``j`` carrying force ``f`` [N] to the board at
        its simulated time and returns the reading [m or rad] its reply gives.
    n : int
        Rows [samples].
    time_of : callable
        ``time_of(k) -> t``: the time stamped on row ``k`` [s], read once command ``k``
        has gone out.

    Returns
    -------
    dict of ndarray
        Telemetry columns, shape (n,): ``time``, ``position``, ``force`` (the applied
        force), ``seq`` (0 .. n - 1), ``flags`` and ``late`` (0), ``force_seq`` (``seq -
        delay``), ``status`` (0).
    """
    import numpy as np

    from hapsim.engine import Engine
    x = command(0, 0.0)
    cols = {q: np.zeros(n) for q in ("time", "position", "force")}
    lim = float(scene.device.force_limit)
    eng = Engine(scene)
    for k in range(n):
        cols["time"][k] = time_of(k)
        cols["position"][k] = x
        f = min(max(eng.port_step(x), -lim), lim)
        cols["force"][k] = driver.applied_force(f)
        x = command(k + 1, f)
    cols.update(seq=np.arange(n), flags=np.zeros(n, np.uint8), late=np.zeros(n, np.uint8),
                force_seq=np.arange(n) - int(scene.device.delay),
                status=np.zeros(n, np.uint16))
    return cols

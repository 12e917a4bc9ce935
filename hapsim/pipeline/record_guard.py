"""The safety of an n-D record over a port: the 1-D host loop's bounds, braking and
lateness guard, at ``n`` axes.

A 2-D or 3-D scene is measured over the framed protocol as ``2n + 1`` records of free
responses (:func:`hapsim.pipeline.felt_port.measure_felt_port`), each up to a few
seconds of a loop closed in real time on a device that keeps its own clock. Each STATE
of a record is checked, as the 1-D host loop checks it (:mod:`hapsim.host.loop`):

- **the position bound**: the handle's distance from its rest position (the Euclidean
  norm) beyond ``max(0.1 m, 20 a)``, ``a`` the records' amplitude (the 1-D run's
  default bound, :mod:`hapsim.pipeline.runner`, around the rest position);
- **the lateness guard**: the growth the device's holds of late FORCEs put into the loop's
  modes (:mod:`hapsim.kernels.late_growth`, the same kernels and the same stop at
  ``ln 2``; the tables from the n-D closed loop,
  :func:`hapsim.analysis.late_growth.late_growth`), counted once the handle moves faster
  than the braking's rest speed.

A breach ends the measurement: the host brakes the handle (:mod:`hapsim.braking`, ``F =
-B v``, ``B = g M / T`` with ``M`` the device's Cartesian mass matrix, the one the framed
device's axes carry; for a pantograph or a delta, its Cartesian mass at the operating
point: a handle away from it, whose true mass is ``M'``, sees each mode's gain ``g``
times an eigenvalue of ``M'^-1 M``; the backward-difference loop of each mode,
:func:`hapsim.braking.brake_mode_polynomial`, is stable to a gain of 0.83 at ``d = 1``
and 0.54 at 2, so for eigenvalues up to 3.3 and 2.1 times), then sends the zero FORCE and
STOP, and the run reports the stop
("safety: ...") with what was recorded by then (the felt matrices are then not
measured). As in 1-D, no braking is sent to a device that takes none of the host's FORCEs:
the last STATE names a FORCE more than ``d +`` :data:`hapsim.braking.IGNORED_TICKS` ticks
old, or a braking STATE that many ticks past the tick the first braking FORCE was due at
still names an older one; STOP is sent at once (the device zeroes its force,
``firmware_protocol/PROTOCOL.md`` §STOP). ``safety: {brake: false}`` sends the zero FORCE
at once.
"""

from __future__ import annotations

import math

import numpy as np

import firmware_protocol as fp
from hapsim.braking import BRAKE_MAX_S, IGNORED_TICKS, Brake, brake_damping, brake_rest
from hapsim.errors import DeviceError
from hapsim.host.recovery import names_older
from hapsim.kernels.late_growth import (LATE_GROWTH_SLACK, LATE_GROWTH_STOP,
                                        late_growth_reason, late_growth_step,
                                        open_hold_growth)
from hapsim.kernels.ticks import named_delay

__all__ = ["RecordGuard", "POSITION_FLOOR", "POSITION_SCALE"]

#: The position bound's floor [m] and its scale on the records' amplitude (the 1-D run's
#: default bound, ``max(0.1, 20 x0)``: :mod:`hapsim.pipeline.runner`).
POSITION_FLOOR = 0.1
POSITION_SCALE = 20.0


class RecordGuard:
    """The bounds of an n-D record, checked STATE by STATE, and the braking after a breach
    (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The measured scene (its device's rest position, Cartesian mass and friction
        matrices, delay ``d`` [periods] and ``safety.brake``).
    amplitude : float
        The records' amplitude ``a`` [m].
    guard : hapsim.kernels.late_growth.LateGrowth or None
        The lateness guard's tables (None: no lateness guard, as in lockstep).
    force_limit : float
        CONFIG's force limit [N] (the braking's clamp).

    Attributes
    ----------
    bound : float
        The position bound [m] around the rest position.
    rest_speed : float
        The braking's rest speed [m/s] (:func:`hapsim.braking.brake_rest` over the
        bound), below which the lateness guard does not stop a handle.
    reason : str or None
        Why the measurement was stopped (None: no stop).
    brake : dict or None
        The braking's report (:meth:`hapsim.braking.Brake.report`) after a stop.
    """

    def __init__(self, scene, amplitude: float, guard, force_limit: float) -> None:
        dev = scene.device
        self.n = scene.dimension
        self.rate = float(scene.rate_hz)
        self.rest = np.asarray(dev.position, float).reshape(self.n)
        self._rest = [float(v) for v in self.rest]
        self._prev = [0.0] * self.n         # the last STATE's position, kept in place
        self.d = int(dev.delay)
        self.bound = max(POSITION_FLOOR, POSITION_SCALE * abs(float(amplitude)))
        self.rest_speed = brake_rest(self.bound, dev.mass, dev.friction)
        self.damping = (brake_damping(dev.mass, self.rate)
                        if getattr(scene.safety, "brake", True) else None)
        self.force_limit = float(force_limit)
        self.guard = guard
        self.tables = guard.lists() if guard is not None else None
        self.reason = None
        self.brake = None
        self.start()

    def start(self) -> None:
        """Start a record: the lateness sums at zero, no FORCE named yet."""
        self.acc = [0.0] * (len(self.tables) if self.tables is not None else 0)
        self.named = -1
        self.applied = False
        self._seen = False                  # a STATE of this record read already
        self.lag = -1

    def check(self, m, pos) -> str | None:
        """Check one STATE of the record (before it is answered).

        Parameters
        ----------
        m : firmware_protocol.State
            The STATE (``seq``, ``force_seq``, ``status``).
        pos : ndarray, shape (n,)
            Its handle position [m].

        Returns
        -------
        str or None
            The stop reason of a breached bound, the first breached first (also kept in
            :attr:`reason`); None while every bound holds.
        """
        st = int(m.status)
        if st & fp.STATUS_FORCE_APPLIED:
            self.applied = True
        self.lag = lag = named_delay(int(m.seq), int(m.force_seq), st, self.applied)
        grown = 0.0
        if self.tables is not None:
            step = self.guard.step
            self.named = late_growth_step(self.acc, self.named, int(m.force_seq), lag,
                                          self.tables, step)
            grown = open_hold_growth(self.acc, self.named, int(m.seq), lag, self.d,
                                     self.tables, step)
        # per STATE nothing is made (the real-time rule): n <= 3 floats, updated in place
        prev, rest, seen = self._prev, self._rest, self._seen
        step = off2 = 0.0
        for a in range(self.n):
            x = pos.item(a)
            if seen:
                step = max(step, abs(x - prev[a]))
            prev[a] = x
            e = x - rest[a]
            off2 += e * e
        self._seen = True
        speed = step * self.rate            # the largest component's, as the braking's
        off = math.sqrt(off2)
        if not off <= self.bound:           # (a position not finite stops too)
            self.reason = (f"safety: position {off:.6g} m from rest beyond {self.bound:g} "
                           "m")
        elif grown > LATE_GROWTH_STOP and speed > self.rest_speed:
            self.reason = late_growth_reason(grown, self.guard, 1.0 / self.rate)
        return self.reason

    def stop_device(self, transport, m, pos, receive_timeout: float = 0.05) -> None:
        """After a breach at STATE ``m``: brake the handle (module notes), then send the
        zero FORCE, whatever ended the braking (the caller sends STOP).

        Parameters
        ----------
        transport
            The framed transport (``send``, ``receive``; a virtual clock's ``clock``).
        m : firmware_protocol.State
            The STATE the breach was found at (not answered).
        pos : ndarray, shape (n,)
            Its handle position [m].
        receive_timeout : float
            Each wait for the next STATE [s].

        Raises
        ------
        DeviceError
            The port failed under the braking (:attr:`brake` then says ``"port"``).
        """
        zero = tuple(0.0 for _ in range(self.n))
        if self.damping is None:
            transport.send(fp.Force(int(m.seq), zero))
            return
        law = Brake(self.damping, self.force_limit, self.rest_speed)
        try:
            self._brake(transport, m, pos, law, zero, receive_timeout)
        except DeviceError:
            # the port failed under the braking: nothing more can be sent (the caller's
            # STOP fails too, and the measurement ends on its safety stop)
            b = law.report(0, 0.0, "port")
            self.brake = b if self.brake is None else {**self.brake, "ended": "port"}
            raise

    def _brake(self, transport, m, pos, law, zero, receive_timeout: float) -> None:
        """:meth:`stop_device`'s braking (the law made), its report in :attr:`brake`."""
        if self.lag < 0 or self.lag > self.d + IGNORED_TICKS:
            # the device took none of the host's FORCEs lately: STOP at once
            self.brake = law.report(0, 0.0, "ignored")
            transport.send(fp.Force(int(m.seq), zero))
            return
        law.observe(pos, None)
        first, last = int(m.seq), int(m.seq)
        most = max(int(math.ceil(BRAKE_MAX_S * self.rate)), 1)
        silent, quiet = 0.0, 0.25
        ended = "time"
        sent = 0
        cur = m
        while True:
            if law.at_rest:
                ended = "rest"
                break
            if cur.seq - first >= most:
                break
            transport.send(fp.Force(int(cur.seq), tuple(float(v) for v in law.command())))
            sent += 1
            nxt = None
            while nxt is None:
                msgs = transport.receive(receive_timeout)
                got = [s for s in msgs if type(s) is fp.State and len(s.position) == self.n
                       and ((int(s.seq) - last) & 0xFFFFFFFF) - 1 < 0x7FFFFFFF]
                if got:
                    nxt = got[-1]                   # the newest: the braking answers it
                    break
                silent += receive_timeout
                if silent >= quiet:
                    ended = "port"
                    break
            if nxt is None:
                break
            silent = 0.0
            q = np.asarray(nxt.position, float)
            law.observe(q, (int(nxt.seq) - last) / self.rate)
            last = int(nxt.seq)
            st = int(nxt.status)
            if st & fp.STATUS_FORCE_APPLIED:
                self.applied = True
            if names_older(nxt, first, self.d, self.applied):
                ended = "ignored"                   # none of the braking's FORCEs taken
                break
            cur = nxt
        self.brake = law.report(sent, (last - first) / self.rate, ended)
        transport.send(fp.Force(int(cur.seq), zero))

    def to_dict(self) -> dict:
        """The record's safety as a run reports it (``safety`` in ``--json``).

        Returns
        -------
        dict
            ``position_limit`` [m] (around the rest position), ``stop`` (the reason, or
            None), ``brake`` (the braking's report, or None), ``late_guard`` (None where
            off; else ``stable_to_periods``, ``modes``, ``stop_growth`` [nepers],
            ``slack_per_s``), as the 1-D run's ``loop.safety``.
        """
        g = self.guard
        return {"position_limit": self.bound, "stop": self.reason, "brake": self.brake,
                "brake_damping": (None if self.damping is None
                                  else np.asarray(self.damping).tolist()),
                "late_guard": None if g is None else {
                    "stable_to_periods": g.stable_to, "modes": len(g.table),
                    "stop_growth": LATE_GROWTH_STOP, "slack_per_s": LATE_GROWTH_SLACK}}

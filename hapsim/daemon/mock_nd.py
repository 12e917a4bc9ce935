"""The n-DoF mock device behind the framed protocol: a 2-D or 3-D scene's device on a port.

The framed protocol carries n axes as it is (``firmware_protocol/PROTOCOL.md`` §4: HELLO
announces ``n_axes``; STATE and FORCE carry ``f64[n]``, their length implying n; the golden
vectors hold 2-, 3- and 8-axis frames), so nothing new goes on the wire: this device says
``n_axes = n`` in HELLO, sends the handle's Cartesian position [m] in STATE and applies the
FORCE's Cartesian force [N] (a device that does its kinematics itself; a joint-level board
such as the Haply 2DIY is driven through its own driver).

Its physics (:class:`PhysicsND`) is the device of :mod:`hapsim.lockstep_nd`: a pantograph or
a delta integrates its joint-space dynamics (:class:`hapsim.lockstep_nd.LocalJointDeviceND`:
the configuration-dependent inertia, joint friction, the torques ``J^T F`` held over the
period, the kinematics to second order about the operating point, compiled: tens of
microseconds a tick, ``tools/bench_joint_nd.py``),
a cartesian device the exact zero-order hold of its Cartesian mass and friction.
Device duties as the 1-D mock (:class:`hapsim.daemon.mock.MockDevice`, whose serving loop
:func:`hapsim.daemon.mock.serve_fd` runs it): FORCE ``n`` applied at tick ``n + d`` when it
arrived in time, else the last force held (``late``, STATUS_OVERRUN, ``force_seq`` naming the
force held), the watchdog zeroing it, STOP, PING.

The hand: at the ``k``-th CONFIG since the device's last HELLO (on connect or answering
HELLO_REQUEST) it lets the handle go from start ``k mod (2n + 1)`` of
:func:`hapsim.lockstep_nd.excitation_starts` (rest; displaced by ``a`` along each axis;
moving at ``a / (10 T)`` along each), ``a`` the mock's amplitude. A host identifying the
felt matrices (:mod:`hapsim.daemon.run_nd`) asks HELLO and then runs ``2n + 1`` CONFIGs.
"""

from __future__ import annotations

import math

import numpy as np

import firmware_protocol as fp
from hapsim.analysis.ths_nd import LoopModelND, zoh_matrices
from hapsim.daemon.mock import MOCK_DEVICE_ID, MockDevice, MockStats
from hapsim.errors import ConfigError
from hapsim.lockstep_nd import LocalJointDeviceND, excitation_starts

__all__ = ["PhysicsND", "MockDeviceND", "DEFAULT_AMPLITUDE"]

#: The hand's default amplitude ``a`` [m] (as ``hapsim run --lockstep`` on n-D scenes:
#: the scenes' Euclidean links depart from their linearisation by ~1e-7 there).
DEFAULT_AMPLITUDE = 1e-8


class PhysicsND:
    """The device of an n-D scene advanced one sample period at a time.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a device.
    x0, v0 : array_like, shape (n,)
        Initial displacement from the rest position [m] and velocity [m/s].
    joint_space : bool
        A pantograph or delta integrates its joint-space dynamics
        (:class:`hapsim.lockstep_nd.LocalJointDeviceND`); False, or a cartesian device: the
        exact ZOH of the Cartesian mass at rest (:func:`hapsim.analysis.ths_nd.zoh_matrices`).

    Attributes
    ----------
    n : int
        Ticks advanced since the start (the next STATE's seq).
    """

    def __init__(self, scene, x0, v0, joint_space: bool = True) -> None:
        dev = scene.device
        self.dim = scene.dimension
        self.rest = np.asarray(dev.position, float).copy()
        self.n = 0
        x0 = np.asarray(x0, float)
        v0 = np.asarray(v0, float)
        self.joint = None
        if joint_space and dev.joints is not None:
            self.joint = LocalJointDeviceND(scene, x0, v0)
        else:
            self.Ad, self.Bd = zoh_matrices(LoopModelND(mass=dev.mass, friction=dev.friction,
                                                        rate_hz=scene.rate_hz, delay=0))
        self.state = np.concatenate([x0, v0])

    def sample(self) -> tuple:
        """The handle's position [m] at the current tick, as a tuple of n floats."""
        if self.joint is not None:
            return tuple(float(v) for v in self.joint.position())
        return tuple(float(v) for v in self.rest + self.state[:self.dim])

    def advance(self, u) -> None:
        """Hold the force ``u`` [N] (shape (n,)) over one period and advance."""
        if self.joint is not None:
            self.joint.step(u)
        else:
            self.state = self.Ad @ self.state + self.Bd @ np.asarray(u, float)
        self.n += 1


class MockDeviceND(MockDevice):
    """The framed protocol's device side for an n-D scene (module notes); I/O-free.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device (``device.delay`` is ``d``).
    amplitude : float
        The hand's amplitude ``a`` [m] (> 0).
    native_rate_hz : float, optional
        Rate announced in HELLO [Hz] (default the scene's).
    lockstep : bool
        One period per FORCE (True) or ticks on a clock (:meth:`tick`).
    joint_space : bool
        :class:`PhysicsND`'s choice.

    Raises
    ------
    ConfigError
        No device; ``d = 0`` in real time; a bad amplitude.
    """

    def __init__(self, scene, amplitude: float = DEFAULT_AMPLITUDE, *,
                 native_rate_hz: float | None = None, lockstep: bool = False,
                 joint_space: bool = True) -> None:
        if scene.device is None or scene.port is None:
            raise ConfigError("the n-D mock needs a port and a device section",
                              file=scene.path, key="device")
        if not (math.isfinite(amplitude) and amplitude > 0):
            raise ConfigError(f"must be a positive number [m], got {amplitude}",
                              key="--amplitude")
        self.scene = scene
        self.dim = scene.dimension
        self.amplitude = float(amplitude)
        self.joint_space = bool(joint_space)
        self.native_rate_hz = float(native_rate_hz or scene.rate_hz)
        self.lockstep = bool(lockstep)
        self.delay = int(scene.device.delay)
        if self.delay == 0 and not self.lockstep:
            raise ConfigError("delay d = 0 (force applied at once) exists in lockstep only; "
                              "a real-time device needs d >= 1", file=scene.path,
                              key="device.delay")
        self._ring = max(16, 2 * self.delay + 2)
        self._zero = (0.0,) * self.dim
        self._rf = [self._zero] * self._ring
        self._rs = [-1] * self._ring
        self.armed = self.configured = False
        self.physics = None
        self.stats = MockStats()
        self.history = []
        self.trace = None
        self.applied_log = None
        self.rate_hz = self.native_rate_hz
        self.force_limit = math.inf
        self.watchdog_us = 0
        self._applied = self._zero
        self._applied_seq = 0
        self._status_extra = 0
        self._last_force_us = 0
        self._u = self._zero
        self.sensors = 0
        self.velocity_out = None
        #: CONFIGs accepted since the last HELLO (which start the hand takes)
        self.configs_since_hello = 0

    def hello(self) -> fp.Hello:
        """HELLO: version 1, ``n_axes = n``, device id :data:`MOCK_DEVICE_ID`, scales 0,
        no force limit (1e300), the native rate. Restarts the hand's cycle."""
        self.configs_since_hello = 0
        return fp.Hello(fp.PROTOCOL_VERSION, self.dim, MOCK_DEVICE_ID, 0.0, 0.0, 1e300,
                        self.native_rate_hz)

    @property
    def sensors_offered(self) -> int:
        """No extra sensors (0)."""
        return 0

    def stop(self) -> None:
        """Zero the force at once and disarm."""
        self._applied = self._u = self._zero
        self.armed = False
        self.stats.last_applied = 0.0
        self._rs = [-1] * self._ring

    def _on_config(self, msg: fp.Config, now_us: int) -> list:
        ok = (math.isfinite(msg.rate_hz) and msg.rate_hz > 0 and msg.watchdog_us > 0
              and math.isfinite(msg.force_limit) and msg.force_limit >= 0)
        if not ok:
            self.stats.faults.append("BAD_CONFIG")
            return [fp.Fault(fp.FAULT_BAD_CONFIG, 0)]
        if abs(msg.rate_hz - self.scene.rate_hz) > 1e-9 * self.scene.rate_hz:
            # the joint-space physics is built at the scene's period
            self.stats.faults.append("BAD_CONFIG")
            return [fp.Fault(fp.FAULT_BAD_CONFIG, 0)]
        self.rate_hz = float(msg.rate_hz)
        self.watchdog_us = int(msg.watchdog_us)
        self.force_limit = float(msg.force_limit)
        starts = excitation_starts(self.dim, self.amplitude, 1.0 / self.rate_hz)
        x0, v0 = starts[self.configs_since_hello % len(starts)]
        self.configs_since_hello += 1
        self.physics = PhysicsND(self.scene, x0, v0, joint_space=self.joint_space)
        self.history.append(self.stats)
        self.stats = MockStats(last_host_message="Config")
        self._rs = [-1] * self._ring
        self._applied = self._u = self._zero
        self._applied_seq = 0
        self._status_extra = 0
        self._last_force_us = now_us
        self.armed = self.configured = True
        if self.lockstep:
            return self.frames(self._emit(now_us))
        return []

    def _on_force(self, msg: fp.Force, now_us: int) -> list:
        st = self.stats
        if not self.armed or self.physics is None:
            st.unexpected += 1
            return []
        f = tuple(msg.force)
        if len(f) != self.dim:
            st.unexpected += 1
            return []
        if not all(math.isfinite(v) for v in f):
            self.stop()
            st.faults.append("NON_FINITE_FORCE")
            return [fp.Fault(fp.FAULT_NON_FINITE_FORCE, msg.seq)]
        if not self.lockstep:
            lo = self.physics.n - self.delay
            ahead = (msg.seq - lo) & 0xFFFFFFFF
            if ahead > self.delay:
                st.stale += 1
                return []
            seq = lo + ahead
            st.forces_rx += 1
            self._last_force_us = now_us
            i = seq % self._ring
            self._rf[i] = f
            self._rs[i] = seq
            return []
        st.forces_rx += 1
        self._last_force_us = now_us
        i = msg.seq % self._ring
        self._rf[i] = f
        self._rs[i] = msg.seq
        n = self.physics.n
        if msg.seq != n:
            st.unexpected += 1
            return []
        if self.delay == 0:
            self._apply_due(n, now_us)
        self.physics.advance(self._u)
        return self.frames(self._emit(now_us))

    def _apply_due(self, n: int, now_us: int) -> None:
        """Choose the force held over ``[nT, (n+1)T)``: FORCE ``n - d`` or the last one."""
        due = n - self.delay
        applied = self._status_extra & fp.STATUS_FORCE_APPLIED
        self._status_extra = 0
        if due < 0:
            f, seq, applied = self._zero, 0, 0
        else:
            i = due % self._ring
            if self._rs[i] == due:
                f, seq, applied = self._rf[i], due, fp.STATUS_FORCE_APPLIED
            else:
                self.stats.late += 1
                self._status_extra |= fp.STATUS_OVERRUN
                f, seq = self._applied, self._applied_seq
        self._status_extra |= applied
        if (not self.lockstep and self.watchdog_us > 0
                and now_us - self._last_force_us > self.watchdog_us):
            f = self._zero
            self.stats.watchdog_trips += 1
            self._status_extra |= fp.STATUS_WATCHDOG_TRIPPED
        lim = self.force_limit
        if any(v > lim or v < -lim for v in f):
            f = tuple(max(-lim, min(lim, v)) for v in f)
            self.stats.clamped += 1
            self._status_extra |= fp.STATUS_FORCE_CLAMPED
        self._applied = f
        self._applied_seq = seq
        self._u = f
        self.stats.last_applied = float(f[0])

    def _emit(self, now_us: int) -> fp.State:
        ph = self.physics
        n = ph.n
        if self.delay > 0:
            self._apply_due(n, now_us)
        self.stats.ticks += 1
        time_us = int(round(n * 1e6 / self.rate_hz)) if self.lockstep else now_us
        status = fp.STATUS_ARMED | fp.STATUS_CONFIGURED | self._status_extra
        return fp.State(n & 0xFFFFFFFF, time_us, status, self._applied_seq & 0xFFFFFFFF,
                        ph.sample())

"""The n-DoF mock device behind the framed protocol: a 2-D or 3-D scene's device on a port.

The framed protocol carries n axes as it is (``firmware_protocol/PROTOCOL.md`` §4: HELLO
announces ``n_axes``; STATE and FORCE carry ``f64[n]``, their length implying n; the golden
vectors hold 2-, 3- and 8-axis frames), so nothing new goes on the wire: this device says
``n_axes = n`` in HELLO, sends the handle's Cartesian position [m] in STATE and applies the
FORCE's Cartesian force [N] (a device that does its kinematics itself; a joint-level board
such as the Haply 2DIY is driven through its own driver).

Its physics (:class:`PhysicsND`) is the device of :mod:`hapsim.lockstep`: a pantograph or
a delta integrates its joint-space dynamics (:class:`hapsim.joint_device.LocalJointDeviceND`:
the configuration-dependent inertia, joint friction, the torques ``J^T F`` held over the
period, the kinematics to second order about the operating point, compiled: tens of
microseconds a tick, ``tools/bench_joint_nd.py``),
a cartesian device the exact zero-order hold of its Cartesian mass and friction.
Device duties are the 1-D mock's own code (:class:`hapsim.emulated.mock.MockDevice`, whose
force hooks this device gives n axes, and whose serving loop
:func:`hapsim.emulated.serve.serve_fd` runs it): FORCE ``n`` applied at tick ``n + d`` when it
arrived in time, else the last force held (``late``, STATUS_OVERRUN, ``force_seq`` naming the
force held), the watchdog zeroing it, STOP, PING.

The hand: at the ``k``-th CONFIG since the device's last HELLO (on connect or answering
HELLO_REQUEST) it lets the handle go from start ``k mod (2n + 1)`` of
:func:`hapsim.lockstep.excitation_starts` (rest; displaced by ``a`` along each axis;
moving at ``a / (10 T)`` along each), ``a`` the mock's amplitude. A host identifying the
felt matrices (:mod:`hapsim.pipeline.run_nd`) asks HELLO and then runs ``2n + 1`` CONFIGs.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import firmware_protocol as fp
from hapsim.analysis.ths_nd import LoopModelND, split_hold_matrices, zoh_matrices
from hapsim.emulated.mock import MOCK_DEVICE_ID, MockDevice
from hapsim.errors import ConfigError
from hapsim.joint_device import LocalJointDeviceND
from hapsim.lockstep import excitation_starts

__all__ = ["PhysicsND", "MockDeviceND", "DEFAULT_AMPLITUDE"]

#: The hand's default amplitude ``a`` [m] (as ``hapsim run --lockstep`` on n-D scenes:
#: the scenes' Euclidean links depart from their linearisation by ~1e-7 there).
DEFAULT_AMPLITUDE = 1e-8


class PhysicsND:
    """The device of an n-D scene advanced one sample period at a time.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a device.
    x0, v0 : array_like, shape (n,)
        Initial displacement from the rest position [m] and velocity [m/s].
    joint_space : bool
        A pantograph or delta integrates its joint-space dynamics
        (:class:`hapsim.joint_device.LocalJointDeviceND`); False, or a cartesian device: the
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
        self.split = float(dev.delay) % 1.0
        if joint_space and dev.joints is not None:
            if self.split > 0:
                raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is "
                                  "modelled on the Cartesian device; the joint-space model "
                                  "applies whole periods: use a whole delay or the "
                                  "Cartesian model", file=scene.path, key="device.delay")
            self.joint = LocalJointDeviceND(scene, x0, v0)
        else:
            lm = LoopModelND(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                             delay=dev.delay)
            self.Ad, self.Bd = zoh_matrices(lm)
            if self.split > 0:        # the split hold (ths_nd.split_hold_matrices)
                _, self._G0, self._G1 = split_hold_matrices(lm)
                self._held = np.zeros(self.dim)
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
        elif self.split > 0:      # the previous force over the first f T, then u
            u = np.asarray(u, float)
            self.state = self.Ad @ self.state + self._G0 @ u + self._G1 @ self._held
            self._held = u
        else:
            self.state = self.Ad @ self.state + self.Bd @ np.asarray(u, float)
        self.n += 1


class MockDeviceND(MockDevice):
    """The framed protocol's device side for an n-D scene (module notes); I/O-free.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
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
        self._zero = (0.0,) * self.dim
        self._init_protocol(math.inf)
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

    # the force's axes: a tuple of n forces [N] (MockDevice's hooks)
    def _force_value(self, msg: fp.Force):
        f = tuple(msg.force)
        return f if len(f) == self.dim else None

    @staticmethod
    def _is_finite(f) -> bool:
        return all(math.isfinite(v) for v in f)

    @staticmethod
    def _clamp(f, lim: float):
        if any(v > lim or v < -lim for v in f):
            return tuple(max(-lim, min(lim, v)) for v in f), True
        return f, False

    @staticmethod
    def _first(f) -> float:
        return float(f[0])

    def _position(self, ph) -> tuple:
        return ph.sample()

    def _on_config(self, msg: fp.Config, now_us: int) -> list:
        if not self._config_ok(msg):
            self.stats.faults.append("BAD_CONFIG")
            return [fp.Fault(fp.FAULT_BAD_CONFIG, 0)]
        self.rate_hz = float(msg.rate_hz)
        # the physics at the CONFIG's period (the host's rate, which may be another than
        # the scene's: hapsim run --rate)
        scene = (self.scene if self.rate_hz == self.scene.rate_hz
                 else dataclasses.replace(self.scene, rate_hz=self.rate_hz))
        self.watchdog_us = int(msg.watchdog_us)
        self.force_limit = float(msg.force_limit)
        starts = excitation_starts(self.dim, self.amplitude, 1.0 / self.rate_hz)
        x0, v0 = starts[self.configs_since_hello % len(starts)]
        self.configs_since_hello += 1
        self.physics = PhysicsND(scene, x0, v0, joint_space=self.joint_space)
        return self._armed(now_us)

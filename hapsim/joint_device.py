"""The n-DoF device in joint space: a pantograph or a delta with its configuration-dependent
inertia and joint friction, the torques ``J^T F`` held over each period, integrated over
the period (:class:`JointDeviceND`), or linearised about its working point
(:class:`LocalJointDeviceND`). The plant of the lockstep n-D loop
(:mod:`hapsim.lockstep`) and of the emulated n-D devices (:mod:`hapsim.emulated`)."""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError
from hapsim.kernels.joint import joint_step

__all__ = ["JointDeviceND", "LocalJointDeviceND"]


def _kinematics_of(scene):
    """The kinematics of a scene's pantograph or delta (ConfigError for a cartesian one)."""
    from hapsim.kinematics import device
    dev = scene.device
    if dev.joints is None:
        raise ConfigError("a joint-space device needs a pantograph or a delta",
                          file=scene.path, key="device.kind")
    return device(dev.kind, dev.geometry)


#: The quadratic kinematics ``(J0, f0, H)`` of :class:`LocalJointDeviceND` at the
#: operating points last asked, keyed by the device's kind, geometry and joints: each is
#: eight closed-loop solves of a delta (~10 ms), and an emulated Falcon builds the same
#: device twice a record (its start and its hand's start, :mod:`hapsim.emulated.
#: falcon_device`), 16 times a measurement of the felt matrices. At most
#: :data:`_QUADRATIC_KEPT` points are kept.
_QUADRATIC: dict = {}
_QUADRATIC_KEPT = 16


def _quadratic_model(scene) -> tuple:
    """``(J0, f0, H)`` of :class:`LocalJointDeviceND` for ``scene``'s device: copies of
    the ones computed at the same kind, geometry and joints (the same calls on the same
    numbers, so the same bits), else computed and kept."""
    dev = scene.device
    kin = _kinematics_of(scene)
    q0 = np.asarray(dev.joints, float)
    try:
        key = (dev.kind, dev.geometry, q0.tobytes())
        hash(key)
    except TypeError:                                    # an unhashable geometry
        key = None
    got = _QUADRATIC.get(key) if key is not None else None
    if got is None:
        n = q0.size
        h = 1e-5
        H = np.empty((n, n, n))
        J0 = kin.jacobian(q0)
        f0 = kin.forward(q0)
        for k in range(n):
            e = np.zeros(n)
            e[k] = h
            H[:, :, k] = (kin.jacobian(q0 + e) - kin.jacobian(q0 - e)) / (2 * h)
        got = (J0, f0, 0.5 * (H + H.transpose(0, 2, 1)))  # d2f/dq_j dq_k is symmetric
        if key is not None:
            if len(_QUADRATIC) >= _QUADRATIC_KEPT:
                _QUADRATIC.pop(next(iter(_QUADRATIC)))
            _QUADRATIC[key] = got
    return tuple(a.copy() for a in got)


class JointDeviceND:
    """A kinematic device's joint-space dynamics, integrated over each sample period.

    ``(M_q + m_h J^T J) q'' = J^T u - B_q q' - b_h J^T J q' - m_h J^T (d^2 f / ds^2)`` with
    ``J = J(q)`` and the handle's acceleration bias ``d^2 f(q + s q') / ds^2`` (the
    velocity-product terms of the hand mass carried by the handle; Lagrange's equations for
    the rotor inertia ``M_q`` and the Cartesian point mass ``m_h``: Khatib 1987). The
    joint torques ``tau = J(q_n)^T u`` are held over the period (a torque zero-order hold,
    as a device applies them). Classical fourth-order Runge-Kutta with ``substeps`` steps
    per period; for small motion it is the Cartesian loop of
    :func:`hapsim.analysis.ths.zoh_matrices` at rest (to the integrator's error,
    ``O((w T / substeps)^4)`` relative), and for larger motion it carries the kinematic
    nonlinearity :mod:`hapsim.analysis.linearisation` bounds.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A scene whose device is a pantograph or a delta.
    x0 : array_like, shape (n,)
        Initial handle position [m] (joints by Newton steps from the operating point).
    v0 : array_like, shape (n,)
        Initial handle velocity [m/s].
    substeps : int, optional
        Runge-Kutta steps per period.

    Raises
    ------
    ConfigError
        A cartesian device (no joints).
    hapsim.errors.KinematicsError
        A motion leaving the workspace or reaching a singularity.
    """

    def __init__(self, scene, x0, v0, substeps: int = 2) -> None:
        dev = scene.device
        self.kin = _kinematics_of(scene)
        self.Mq, self.Bq = dev.joint_inertia, dev.joint_friction
        self.mh, self.bh = dev.hand_mass, dev.hand_damping
        self.h = scene.period / int(substeps)
        self.substeps = int(substeps)
        q = np.asarray(dev.joints, float).copy()
        x0 = np.asarray(x0, float)
        for _ in range(6):                          # Newton: f(q) = x0
            q = q + np.linalg.solve(self.kin.jacobian(q), x0 - self.kin.forward(q))
        self.q = q
        self.qd = np.linalg.solve(self.kin.jacobian(q), np.asarray(v0, float))
        self.tau = np.zeros_like(q)

    def position(self) -> np.ndarray:
        """Handle position ``f(q)`` [m], shape (n,).

        Returns
        -------
        ndarray, shape (n,)
            The forward kinematics of the joints [m].
        """
        return self.kin.forward(self.q)

    def _accel(self, q, qd):
        J = self.kin.jacobian(q)
        speed = float(np.linalg.norm(qd))
        bias = np.zeros(J.shape[0])
        if speed > 0:
            eps = 1e-4 / speed                      # a 1e-4 rad step along q'
            bias = (self.kin.forward(q + eps * qd) - 2 * self.kin.forward(q)
                    + self.kin.forward(q - eps * qd)) / (eps * eps)
        JtJ = J.T @ J
        rhs = self.tau - self.Bq @ qd - self.bh * (JtJ @ qd) - self.mh * (J.T @ bias)
        return np.linalg.solve(self.Mq + self.mh * JtJ, rhs)

    def step(self, u) -> None:
        """Hold the torques of the Cartesian force ``u`` [N] over one period and advance.

        Parameters
        ----------
        u : array_like, shape (n,)
            Force on the handle [N].
        """
        self.tau = self.kin.jacobian(self.q).T @ np.asarray(u, float)
        q, qd, h = self.q, self.qd, self.h
        for _ in range(self.substeps):
            k1q, k1v = qd, self._accel(q, qd)
            k2q, k2v = qd + 0.5 * h * k1v, self._accel(q + 0.5 * h * k1q, qd + 0.5 * h * k1v)
            k3q, k3v = qd + 0.5 * h * k2v, self._accel(q + 0.5 * h * k2q, qd + 0.5 * h * k2v)
            k4q, k4v = qd + h * k3v, self._accel(q + h * k3q, qd + h * k3v)
            q = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
            qd = qd + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        self.q, self.qd = q, qd


class LocalJointDeviceND:
    """A kinematic device's joint-space dynamics with its kinematics to second order about
    the operating point: fast enough for a real-time mock (a delta's exact forward
    kinematics is a Newton solve of ~5 ms).

    ``f(q0 + s) = f(q0) + J0 s + H(s, s) / 2`` with ``J0 = J(q0)`` and ``H[:, j, k] =
    d J[:, j] / d q_k`` (central differences of :meth:`hapsim.kinematics` Jacobians, step
    ``1e-5`` rad: error ``O(1e-10)`` relative); the Jacobian is then ``J0 + H s`` and the
    handle's acceleration bias ``H(q', q')`` exactly, and the dynamics are those of
    :class:`JointDeviceND` (Lagrange's equations, Khatib 1987) for this quadratic
    kinematics: the configuration-dependent inertia and the velocity-product terms are
    exact to first order in the motion ``s``, which is the order of the linearisation bound
    (:mod:`hapsim.analysis.linearisation`); the next term is ``O(|s|^2)`` relative.
    Torques ``J(q_n)^T u`` held over the period; classical Runge-Kutta, ``substeps`` per
    period.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A scene whose device is a pantograph or a delta.
    x0, v0 : array_like, shape (n,)
        Initial handle displacement from the rest position [m] and velocity [m/s] (the
        joints by Newton steps on the quadratic model).
    substeps : int, optional
        Runge-Kutta steps per period.

    Raises
    ------
    ConfigError
        A cartesian device (no joints).
    hapsim.errors.KinematicsError
        The operating point at a singularity or outside the workspace.
    """

    def __init__(self, scene, x0, v0, substeps: int = 2) -> None:
        dev = scene.device
        q0 = np.asarray(dev.joints, float)
        n = q0.size
        self.q0 = q0.copy()
        self.J0, self.f0, self.H = _quadratic_model(scene)
        self.Mq, self.Bq = dev.joint_inertia, dev.joint_friction
        self.mh, self.bh = dev.hand_mass, dev.hand_damping
        self.substeps = int(substeps)
        self.h = scene.period / self.substeps
        target = np.asarray(dev.position, float) + np.asarray(x0, float) - self.f0
        s = np.zeros(n)
        for _ in range(8):                               # Newton on the quadratic model
            s = s + np.linalg.solve(self.J(s), target - self._disp(s))
        self.s = s
        self.sd = np.linalg.solve(self.J(s), np.asarray(v0, float))
        self.Mq = np.ascontiguousarray(self.Mq, float)
        self.Bq = np.ascontiguousarray(self.Bq, float)
        self.mh, self.bh = float(self.mh), float(self.bh)
        self._u = np.zeros(n)
        self._wv = np.zeros((10, n))
        self._wm = np.zeros((2, n, n))

    def J(self, s) -> np.ndarray:
        """Jacobian ``J0 + H s`` [m/rad] at joint displacement ``s`` [rad], shape (n, n).

        Parameters
        ----------
        s : ndarray, shape (n,)
            Joint displacement from the operating point ``q0`` [rad].

        Returns
        -------
        ndarray, shape (n, n)
            ``d f / d q`` of the quadratic model [m/rad].
        """
        return self.J0 + self.H @ s

    def _disp(self, s):
        return self.J0 @ s + 0.5 * ((self.H @ s) @ s)

    def position(self) -> np.ndarray:
        """Handle position ``f(q0 + s)`` [m], shape (n,).

        Returns
        -------
        ndarray, shape (n,)
            ``f0 + J0 s + H(s, s) / 2`` [m] (absolute, not from the rest position).
        """
        return self.f0 + self._disp(self.s)

    def step(self, u) -> None:
        """Hold the torques ``J(q_n)^T u`` of the Cartesian force ``u`` [N] (shape (n,))
        over one period and advance.

        Parameters
        ----------
        u : array_like, shape (n,)
            Force on the handle [N].
        """
        self.step_torque(self.J(self.s).T @ np.asarray(u, float))

    def step_torque(self, tau) -> None:
        """Hold the joint torques ``tau`` [N m] (shape (n,)) over one period and advance
        (:func:`hapsim.kernels.joint.joint_step`).

        Parameters
        ----------
        tau : array_like, shape (n,)
            Joint torques [N m].
        """
        self._u[:] = tau
        joint_step(self.s, self.sd, self._u, self.J0, self.H, self.Mq, self.Bq, self.mh,
                   self.bh, self.h, self.substeps, self._wv, self._wm)

    def advance_torque(self, tau, dt: float) -> None:
        """Hold the joint torques ``tau`` [N m] (shape (n,)) over ``dt`` [s], any length: a
        board on the wall clock (:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`).

        The same Runge-Kutta steps as :meth:`step_torque`, none longer than this device's
        ``h`` (``ceil(dt / h)`` equal steps): a period cut into intervals is the period's
        motion to the integrator's error, ``O((w h)^4)`` relative.

        Parameters
        ----------
        tau : array_like, shape (n,)
            Joint torques [N m].
        dt : float
            The time they are held over [s]; not > 0 (NaN included): nothing happens.
        """
        if not dt > 0.0:
            return
        n = max(1, math.ceil(dt / self.h - 1e-9))
        self._u[:] = tau
        joint_step(self.s, self.sd, self._u, self.J0, self.H, self.Mq, self.Bq, self.mh,
                   self.bh, dt / n, n, self._wv, self._wm)

    def joints(self) -> np.ndarray:
        """Joint angles ``q0 + s`` [rad], shape (n,).

        Returns
        -------
        ndarray, shape (n,)
            A new array [rad].
        """
        return self.q0 + self.s

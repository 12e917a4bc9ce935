"""The n-DoF loop closed in-process, in lockstep: the n-D engine coupled to the exact
sampled device (the first piece of issue 23's n-DoF mock).

One sample ``n`` (the timing of :mod:`hapsim.analysis.scene_nd_check`, so the analysis's
state matrix is exactly this loop's one-step map for a linear scene):

1. the port is at the device sample ``x_dev[n]``;
2. the engine advances (:class:`hapsim.engine_nd.EngineND`), computing the force on the
   port ``F[n]`` from the positions at ``n`` and ``n - 1``;
3. ``F[n]`` enters the delay line; the device holds ``u[n] = F[n-d]`` over the period and
   advances exactly, ``[x, v][n+1] = Ad [x, v][n] + Bd u[n]``
   (:func:`hapsim.analysis.ths_nd.zoh_matrices` of its Cartesian mass and friction).

No protocol and no pseudo-terminal yet: the n-axis device, its mock behind a port, the
hand's excitation and the identification of the felt matrices from a record are what is
left of the n-DoF run.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.ths_nd import LoopModelND, split_hold_matrices, zoh_matrices
from hapsim.engine_nd import EngineND
from hapsim.errors import ConfigError
from hapsim.kernels.joint_nd import joint_step

__all__ = ["LockstepND", "JointDeviceND", "measure_felt_lockstep", "excitation_starts",
           "felt_deviation", "default_samples", "LocalJointDeviceND",
           "identification_plan", "error_responses", "felt_verdict", "MEASURABLE_WIRE",
           "felt_directions", "wire_terms_nd", "statement_name"]


class LockstepND:
    """An n-D scene felt through its device, closed in-process.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    x0, v0 : array_like, shape (n,), optional
        The device's initial displacement from its rest position [m] and velocity [m/s].
    joint_space : bool, optional
        Integrate a kinematic device's joint-space dynamics (:class:`JointDeviceND`: the
        configuration-dependent inertia and the velocity-product terms) instead of the
        exact ZOH of its Cartesian mass at rest.

    Raises
    ------
    ConfigError
        No port or device; ``x0``/``v0`` not n finite numbers; ``joint_space`` with a
        cartesian device.
    """

    def __init__(self, scene, x0=None, v0=None, joint_space: bool = False) -> None:
        if scene.port is None or scene.device is None:
            raise ConfigError("the lockstep loop needs a port and its device",
                              file=scene.path, key="masses")
        n = scene.dimension
        self.n = n
        dev = scene.device
        lm = LoopModelND(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                         delay=dev.delay)
        self.Ad, self.Bd = zoh_matrices(lm)
        # a sub-sample delay m + f: the device holds the previous force over the period's
        # first f T (the split hold, hapsim.analysis.ths_nd.split_hold_matrices)
        self.split = float(dev.delay) % 1.0
        if self.split > 0:
            if joint_space:
                raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is "
                                  "modelled on the Cartesian device; the joint-space model "
                                  "applies whole periods: use a whole delay or the "
                                  "Cartesian model", file=scene.path, key="device.delay")
            _, self._G0, self._G1 = split_hold_matrices(lm)
            self._held = np.zeros(n)
        self.engine = EngineND(scene)
        self.rest = dev.position.copy()

        def vec(v, key):
            a = np.zeros(n) if v is None else np.asarray(v, float)
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ConfigError(f"must be {n} finite numbers, got {v!r}", key=key)
            return a
        self.state = np.concatenate([vec(x0, "x0"), vec(v0, "v0")])  # deviation, velocity
        self.delay = np.zeros((int(dev.delay), n))     # F[n-1], ..., F[n-d] (whole d)
        p = self.rest + self.state[:n]
        # the port's previous position: where it was one period ago at the initial velocity
        self.engine.xp[:, self.engine.port] = p - self.state[n:] * scene.period
        self.engine.x[:, self.engine.port] = p
        self.joint = JointDeviceND(scene, p, self.state[n:]) if joint_space else None

    def step(self, samples: int = 1, record: bool = False, *, reading_error=None,
             force_error=None):
        """Advance the loop.

        Parameters
        ----------
        samples : int
            Samples to run.
        record : bool, optional
            Return the device positions.
        reading_error : ndarray, shape (samples, n), optional
            An error of the host's reading [m]: at sample ``i`` the engine is given the
            handle at ``x_dev[i] + reading_error[i]``, and the record holds that reading
            (a sensor's or a wire's rounding, observed and fed back through the links).
        force_error : ndarray, shape (samples, n), optional
            A force error [N] added to the force the device holds over sample ``i``
            (a wire's rounding of the force it is sent).

        Returns
        -------
        ndarray, shape (samples, n) or None
            The device's position deviation ``x_dev[n]`` [m] at each sample, before the
            step, plus ``reading_error`` (when ``record``).
        """
        n = self.n
        out = np.empty((samples, n)) if record else None
        eng = self.engine
        for i in range(int(samples)):
            x = self.state[:n]
            if reading_error is not None:
                x = x + reading_error[i]
            if record:
                out[i] = x
            eng.set_port_position(self.rest + x)
            eng.step()
            F = eng.port_force
            if self.delay.shape[0]:
                u = self.delay[-1].copy()
                self.delay[1:] = self.delay[:-1]
                self.delay[0] = F
            else:
                u = F
            if force_error is not None:
                u = u + force_error[i]
            if self.joint is not None:
                self.joint.step(u)
                self.state = np.concatenate([self.joint.position() - self.rest,
                                             np.zeros(n)])
            elif self.split > 0:
                self.state = self.Ad @ self.state + self._G0 @ u + self._G1 @ self._held
                self._held = u
            else:
                self.state = self.Ad @ self.state + self.Bd @ u
        return out


def _kinematics_of(scene):
    """The kinematics of a scene's pantograph or delta (ConfigError for a cartesian one)."""
    from hapsim.kinematics import device
    dev = scene.device
    if dev.joints is None:
        raise ConfigError("a joint-space device needs a pantograph or a delta",
                          file=scene.path, key="device.kind")
    return device(dev.kind, dev.geometry)


class JointDeviceND:
    """A kinematic device's joint-space dynamics, integrated over each sample period.

    ``(M_q + m_h J^T J) q'' = J^T u - B_q q' - b_h J^T J q' - m_h J^T (d^2 f / ds^2)`` with
    ``J = J(q)`` and the handle's acceleration bias ``d^2 f(q + s q') / ds^2`` (the
    velocity-product terms of the hand mass carried by the handle; Lagrange's equations for
    the rotor inertia ``M_q`` and the Cartesian point mass ``m_h``: Khatib 1987). The
    joint torques ``tau = J(q_n)^T u`` are held over the period (a torque zero-order hold,
    as a device applies them). Classical fourth-order Runge-Kutta with ``substeps`` steps
    per period; for small motion it is the Cartesian loop of
    :func:`hapsim.analysis.ths_nd.zoh_matrices` at rest (to the integrator's error,
    ``O((w T / substeps)^4)`` relative), and for larger motion it carries the kinematic
    nonlinearity :mod:`hapsim.analysis.linearisation_nd` bounds.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
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
        """Handle position ``f(q)`` [m], shape (n,)."""
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
    (:mod:`hapsim.analysis.linearisation_nd`); the next term is ``O(|s|^2)`` relative.
    Torques ``J(q_n)^T u`` held over the period; classical Runge-Kutta, ``substeps`` per
    period.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
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
        kin = _kinematics_of(scene)
        q0 = np.asarray(dev.joints, float)
        n = q0.size
        self.q0 = q0.copy()
        self.J0 = kin.jacobian(q0)
        self.f0 = kin.forward(q0)
        h = 1e-5
        H = np.empty((n, n, n))
        for k in range(n):
            e = np.zeros(n)
            e[k] = h
            H[:, :, k] = (kin.jacobian(q0 + e) - kin.jacobian(q0 - e)) / (2 * h)
        self.H = 0.5 * (H + H.transpose(0, 2, 1))      # d2f/dq_j dq_k is symmetric
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
        """Jacobian ``J0 + H s`` [m/rad] at joint displacement ``s`` [rad], shape (n, n)."""
        return self.J0 + self.H @ s

    def _disp(self, s):
        return self.J0 @ s + 0.5 * ((self.H @ s) @ s)

    def position(self) -> np.ndarray:
        """Handle position ``f(q0 + s)`` [m], shape (n,)."""
        return self.f0 + self._disp(self.s)

    def step(self, u) -> None:
        """Hold the torques ``J(q_n)^T u`` of the Cartesian force ``u`` [N] (shape (n,))
        over one period and advance."""
        self.step_torque(self.J(self.s).T @ np.asarray(u, float))

    def step_torque(self, tau) -> None:
        """Hold the joint torques ``tau`` [N m] (shape (n,)) over one period and advance
        (:func:`hapsim.kernels.joint_nd.joint_step`)."""
        self._u[:] = tau
        joint_step(self.s, self.sd, self._u, self.J0, self.H, self.Mq, self.Bq, self.mh,
                   self.bh, self.h, self.substeps, self._wv, self._wm)

    def advance_torque(self, tau, dt: float) -> None:
        """Hold the joint torques ``tau`` [N m] (shape (n,)) over ``dt`` [s], any length: a
        board on the wall clock (:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`).

        The same Runge-Kutta steps as :meth:`step_torque`, none longer than this device's
        ``h`` (``ceil(dt / h)`` equal steps): a period cut into intervals is the period's
        motion to the integrator's error, ``O((w h)^4)`` relative.
        """
        if not dt > 0.0:
            return
        n = max(1, math.ceil(dt / self.h - 1e-9))
        self._u[:] = tau
        joint_step(self.s, self.sd, self._u, self.J0, self.H, self.Mq, self.Bq, self.mh,
                   self.bh, dt / n, n, self._wv, self._wm)

    def joints(self) -> np.ndarray:
        """Joint angles ``q0 + s`` [rad], shape (n,)."""
        return self.q0 + self.s


def measure_felt_lockstep(scene, amplitude: float = 1e-8, samples: int | None = None,
                          progress=None, joint_space: bool = False) -> dict:
    """The felt matrices measured from lockstep free responses, against the prediction.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    amplitude : float, optional
        Excitation amplitude ``a`` [m]: record ``i`` starts the handle displaced by
        ``a e_i``, record ``n + i`` moving at ``a / (10 T) e_i`` (``e_i`` the axes).
    samples : int, optional
        Samples per record (default ``max(300, 20 x`` the prediction order ``x n)``).
    progress : callable, optional
        ``progress(done, total)`` after each record.
    joint_space : bool, optional
        The device as :class:`JointDeviceND` (its kinematic nonlinearity in the loop).

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.identify_nd.fit_felt_nd`'s dict of the
        records minus the record from rest, which removes the loop's response to a rest
        that is not exactly an equilibrium: exact for a linear loop), ``predicted``
        (:class:`hapsim.analysis.scene_nd_check.SceneCheckND`), ``deviation`` (the largest
        difference of the felt stiffness and damping matrices, each over the predicted
        matrix's largest entry [-]; None without felt matrices), ``bound``
        (:class:`hapsim.analysis.linearisation_nd.LinearisationBound` at the larger of
        ``a`` and ``excursion``), ``excursion`` (the largest distance [m] of the handle
        from rest over the records: a start moving at ``a / (10 T)`` carries it past
        ``a``), ``order``, ``records``, ``samples``.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`, :func:`hapsim.analysis.scene_nd_check.closed_loop_nd`;
        ``amplitude`` not positive; ``samples`` too short for the order.
    """
    from hapsim.analysis.identify_nd import fit_felt_nd
    from hapsim.analysis.linearisation_nd import linearisation_bound
    chk, order, N = identification_plan(scene, samples)
    a = linearisation_bound(scene, amplitude, chk.render.rendered_poles).amplitude
    n = scene.dimension
    T = scene.period
    starts = excitation_starts(n, a, T)[1:]
    rest = LockstepND(scene, joint_space=joint_space).step(N, record=True)
    excursion = float(np.max(np.linalg.norm(rest, axis=1)))
    recs = []
    for j, (x0, v0) in enumerate(starts):
        r = LockstepND(scene, x0=x0, v0=v0, joint_space=joint_space).step(N, record=True)
        excursion = max(excursion, float(np.max(np.linalg.norm(r, axis=1))))
        recs.append(r - rest)
        if progress is not None:
            progress(j + 1, len(starts))
    # the bound at the largest excursion the records reached (as over a port): a start
    # moving at a / (10 T) carries the handle past a, and the departure grows with it
    bound = linearisation_bound(scene, max(a, excursion), chk.render.rendered_poles)
    fit = fit_felt_nd(recs, scene.device.mass, T, order)
    dev = felt_deviation(fit, chk)
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "order": order, "records": len(recs), "samples": N, "excursion": excursion}


def default_samples(order: int, n: int) -> int:
    """Samples per identification record: ``max(300, 20 p n)`` for prediction order
    ``p`` and ``n`` axes (ten times the regression's ``2 p n`` minimum, so the fit is
    overdetermined tenfold)."""
    return max(300, 20 * int(order) * int(n))


def excitation_starts(n: int, amplitude: float, period: float) -> list:
    """The initial states of the identification records, the record from rest first.

    Parameters
    ----------
    n : int
        Axes.
    amplitude : float
        ``a`` [m].
    period : float
        Sample period ``T`` [s].

    Returns
    -------
    list of (x0, v0)
        ``2 n + 1`` pairs, each of shape (n,) [m], [m/s]: rest ``(0, 0)``; the handle
        displaced by ``a e_i``; the handle moving at ``a / (10 T) e_i`` (``e_i`` the axes).
        Every mode of the loop is excited by one of them unless it is unobservable from
        the handle (:mod:`hapsim.analysis.identify_nd`).
    """
    z = np.zeros(n)
    e = np.eye(n)
    return ([(z, z)] + [(amplitude * e[i], z) for i in range(n)]
            + [(z, amplitude / (10.0 * period) * e[i]) for i in range(n)])


def felt_deviation(fit: dict, chk) -> dict | None:
    """How far measured felt matrices are from the predicted ones.

    Parameters
    ----------
    fit : dict
        :func:`hapsim.analysis.identify_nd.fit_felt_nd`'s result.
    chk : hapsim.analysis.scene_nd_check.SceneCheckND
        The prediction.

    Returns
    -------
    dict or None
        ``felt_stiffness`` and ``felt_damping``: the largest entry of
        ``|measured - predicted|`` over the predicted matrix's largest entry [-]; None
        when either side has no felt matrices.
    """
    k, b = chk.render.felt_stiffness, chk.render.felt_damping
    if fit["felt_stiffness"] is None or k is None:
        return None
    return {"felt_stiffness": float(np.max(np.abs(fit["felt_stiffness"] - k))
                                    / np.max(np.abs(k))),
            "felt_damping": float(np.max(np.abs(fit["felt_damping"] - b))
                                  / np.max(np.abs(b)))}


def identification_plan(scene, samples: int | None = None) -> tuple:
    """The prediction, the prediction order and the record length of an identification.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    samples : int, optional
        Samples per record (default :func:`default_samples`).

    Returns
    -------
    (SceneCheckND, int, int)
        :func:`hapsim.analysis.scene_nd_check.check_scene_nd`'s result, the order ``p``
        (the loop's states over n) and the samples per record ``N``.

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.scene_nd_check.check_scene_nd`; ``samples`` fewer than
        the regression's ``2 p n`` unknowns.
    """
    from hapsim.analysis.scene_nd_check import check_scene_nd
    chk = check_scene_nd(scene)
    n = scene.dimension
    order = chk.states // n
    N = int(samples) if samples is not None else default_samples(order, n)
    if N < 2 * order * n:
        raise ConfigError(f"must be at least {2 * order * n} samples for this loop "
                          f"({chk.states} states), got {N}", key="samples")
    return chk, order, N


def error_responses(scene, samples: int, *, size: float = 1e-9) -> tuple:
    """The loop's impulse responses to a reading error and to a force error, per axis.

    The lockstep loop (:class:`LockstepND`) run from rest with a unit error at sample 0
    along each axis, minus the run without it, over the error's size: the record's
    change at each later sample. A reading error is logged (the direct term, the identity
    at sample 0) and fed back through the scene's links as a force; a force error moves
    the device from the next sample. Exact for a linear loop (superposition); for a scene
    with Euclidean links or contacts, the linearisation at rest to ``O(size)`` relative.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    samples : int
        Length ``L`` of the responses.
    size : float, optional
        The error's size [m] or [N] for the runs.

    Returns
    -------
    (ndarray, ndarray)
        Shapes (L, n, n): the response to a reading error [m/m] and to a force error
        [m/N]; ``[t, :, j]`` the record's change at sample ``t`` for a unit error along
        axis ``j`` at sample 0.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`.
    """
    n = scene.dimension
    L = int(samples)
    rest = LockstepND(scene).step(L, record=True)
    out = np.zeros((2, L, n, n))
    for kind in range(2):
        for j in range(n):
            e = np.zeros((L, n))
            e[0, j] = size
            kw = {"reading_error" if kind == 0 else "force_error": e}
            out[kind, :, :, j] = (LockstepND(scene).step(L, record=True, **kw) - rest) / size
    return out[0], out[1]


#: Largest first-order change (relative) that the readings' rounding may cause in a felt
#: quantity (the felt stiffness or damping matrix as a whole, or along one principal
#: direction) for that quantity to be stated: beyond it the excitation is too small for
#: the wire's or the encoders' resolution, the neglected higher orders of the fit's
#: perturbation (of the order of the first-order term's square) are no longer small
#: against the first, and that quantity is "not measurable".
MEASURABLE_WIRE = 0.25

_QUANTITIES = ("felt_stiffness", "felt_damping")


def felt_directions(fit: dict, chk) -> dict | None:
    """The measured and predicted felt stiffness and damping along the prediction's
    principal directions.

    Along a unit direction ``e`` the felt stiffness is the quadratic form ``e^T k e``
    [N/m] (the force per displacement the hand feels along ``e`` when it pushes along
    ``e``; only the symmetric part of ``k`` contributes) and the felt damping ``e^T b e``
    [N s/m]. The directions are the check's principal directions ``e_i``
    (:mod:`hapsim.analysis.ths_nd`: the major axis of rendered mode ``i``); for a loop
    that is symmetric in one basis (``M``, ``B0``, ``K``, ``B`` diagonal in it) they are
    the eigenvectors of ``k`` and ``b`` and ``e_i^T k e_i = m_i |s_i|^2`` (the check's
    ``direction_stiffness``); otherwise the two differ by the loop's asymmetric coupling
    (on the shipped scenes by at most 2e-5 relative) and the directions need not be
    orthogonal. The quadratic form is a statement about a fixed direction, so it stays
    well defined where two modes' poles coincide and their major axes are arbitrary;
    being linear in the matrix, its first-order wire term is exact
    (:func:`wire_terms_nd`).

    Parameters
    ----------
    fit : dict
        :func:`hapsim.analysis.identify_nd.fit_felt_nd`'s result.
    chk : hapsim.analysis.scene_nd_check.SceneCheckND
        The prediction.

    Returns
    -------
    dict or None
        ``directions`` (n unit vectors, the columns ``e_i``), ``damping_factor``
        (``|s_i| / (2 |Re s_i|)`` of mode ``i`` [-]: the linearisation bound's factor
        for the damping along ``e_i``, :mod:`hapsim.analysis.linearisation_nd`),
        ``largest`` (each predicted matrix's largest entry), and for
        ``felt_stiffness`` and ``felt_damping`` a list of n dicts ``predicted``,
        ``measured`` (``e_i^T X e_i``, [N/m] or [N s/m]) and ``deviation``
        (``|measured - predicted| / |predicted|`` [-], inf when ``predicted`` is 0). None
        when either side has no felt matrices.
    """
    r = chk.render
    if fit["felt_stiffness"] is None or r.felt_stiffness is None or r.directions is None:
        return None
    E = np.asarray(r.directions, float)
    s = np.log(np.asarray(r.rendered_poles, complex))   # s_i T: the factor is T-free
    out = {"directions": [E[:, i].tolist() for i in range(E.shape[1])],
           "damping_factor": [float(abs(v) / (2.0 * abs(v.real))) if v.real != 0
                              else math.inf for v in s]}
    out["largest"] = {}
    for q in _QUANTITIES:
        P, Mx = np.asarray(getattr(r, q), float), np.asarray(fit[q], float)
        out["largest"][q] = float(np.max(np.abs(P)))
        rows = []
        for i in range(E.shape[1]):
            e = E[:, i]
            p, m = float(e @ P @ e), float(e @ Mx @ e)
            rows.append({"predicted": p, "measured": m,
                         "deviation": abs(m - p) / abs(p) if p != 0 else math.inf})
        out[q] = rows
    return out



def wire_terms_nd(scene, diffs, chk, order: int, errors) -> dict:
    """The wire's term of the stated uncertainty: the first-order worst case of the felt
    matrices' change, as a whole and along each principal direction, under bounded
    errors of the readings and of the forces.

    Each error enters the records through the loop (:func:`error_responses`: a reading
    error is observed and fed back through the links, a force error moves the device),
    and the fit to first order (:func:`hapsim.analysis.identify_nd.felt_sensitivity_nd`);
    the rest record's errors enter every difference. For a felt entry ``o`` the worst
    case, whatever the errors' signs and correlation, is Hoelder's
    ``sum |(s * H)[o]| bound`` (:func:`hapsim.analysis.identify_nd.worst_case_nd`). The
    felt stiffness along a unit direction ``e`` is ``e^T k e`` (:func:`felt_directions`),
    a linear form in the entries: its first-order change is the same linear form of
    theirs, ``sum_ab e_a e_b dk_ab``, whose worst case is Hoelder's on the combined
    sensitivity ``sum_ab e_a e_b s[ab]`` (no larger than ``sum_ab |e_a e_b| wc_ab``, and
    smaller where the entries' changes cancel along ``e``); likewise for the damping.
    A rounding of a smooth signal a few counts wide is not white noise, so no
    statistical interval is taken for it.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        The scene the records were taken of.
    diffs : sequence of ndarray, each shape (N, n)
        The ``2n`` records minus the record from rest, as fitted [m].
    chk : hapsim.analysis.scene_nd_check.SceneCheckND
        The prediction.
    order : int
        The fit's order.
    errors : sequence of (str, array_like, bounds)
        Each ``(kind, G, bounds)``: ``kind`` ``"reading"`` (an error of the position
        read, [m] at the handle per unit) or ``"force"`` (of the force held, [N] at the
        handle per unit); ``G`` shape (n, m), the map from the error's ``m``
        coordinates to the handle's (e.g. ``J(q0)`` for joint angles, ``J(q0)^-T`` for
        joint torques, the identity for Cartesian ones); ``bounds`` the errors' bounds in
        those coordinates: shape (m,) for every sample of every record, or a list of
        ``2n + 1`` arrays of shape (N, m) or (m,), the record from rest first.

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping``: the worst case over the entries, over the
        predicted matrix's largest entry [-]; ``directions``: for each of the two, a list
        of n relative terms along the principal directions of :func:`felt_directions`
        (over ``|e_i^T X e_i|``; inf when it is 0). Every term inf when the records give
        no sensitivity (no felt matrices).

    Raises
    ------
    ConfigError
        As :func:`error_responses`; an error ``kind`` not ``"reading"`` or ``"force"``.
    """
    from hapsim.analysis.identify_nd import felt_sensitivity_nd, worst_case_nd
    n = scene.dimension
    r = chk.render
    inf = {"felt_stiffness": math.inf, "felt_damping": math.inf,
           "directions": {q: [math.inf] * n for q in _QUANTITIES}}
    if r.felt_stiffness is None or r.directions is None:
        return inf
    N = int(np.asarray(diffs[0]).shape[0])
    sens = felt_sensitivity_nd(diffs, scene.device.mass, scene.period, order)
    if sens is None:
        return inf
    sens = [s for s in sens] + [-sum(sens)]          # the rest record's, in each
    E = np.asarray(r.directions, float)
    # the entries, then the directional forms: one worst case over all of them
    comb = []
    for s in sens:
        S = s.reshape(2 * n * n, s.shape[-2], n)
        D = np.einsum("ai,bi,qabtc->qitc", E, E, s).reshape(2 * n, s.shape[-2], n)
        comb.append(np.concatenate([S, D])[:, None, None])
    Hr, Hf = error_responses(scene, N)
    wc = 0.0
    for kind, G, bounds in errors:
        if kind not in ("reading", "force"):
            raise ConfigError(f"an error's kind must be 'reading' or 'force', got {kind!r}",
                              key="errors")
        H = (Hr if kind == "reading" else Hf) @ np.asarray(G, float)
        if isinstance(bounds, (list, tuple)):
            b = list(bounds[1:]) + [bounds[0]]       # the order of ``sens``
        else:
            b = [bounds] * len(sens)
        wc = wc + worst_case_nd(comb, H, b)[:, 0, 0]
    wc = np.asarray(wc, float) * np.ones(2 * n * n + 2 * n)
    out = {}
    dirs = {}
    for qi, q in enumerate(_QUANTITIES):
        P = np.asarray(getattr(r, q), float)
        out[q] = float(np.max(wc[qi * n * n:(qi + 1) * n * n]) / np.max(np.abs(P)))
        wd = wc[2 * n * n + qi * n: 2 * n * n + (qi + 1) * n]
        row = []
        for i in range(n):
            p = abs(float(E[:, i] @ P @ E[:, i]))
            row.append(float(wd[i] / p) if p > 0 else math.inf)
        dirs[q] = row
    out["directions"] = dirs
    return out


_WORDS = {"felt_stiffness": "felt stiffness", "felt_damping": "felt damping"}


def statement_name(quantity: str, direction=None) -> str:
    """How a statement is named in a report: ``"felt stiffness"`` (the matrix as a whole)
    or ``"felt stiffness along (+0.000, +1.000)"``.

    Parameters
    ----------
    quantity : {"felt_stiffness", "felt_damping"}
    direction : array_like, shape (n,), optional
        The unit direction.

    Returns
    -------
    str
    """
    w = _WORDS[quantity]
    if direction is None:
        return w
    return w + " along (" + ", ".join(f"{v:+.3f}" for v in direction) + ")"


def _statement(quantity, direction, predicted, measured, deviation, lin, wire, limit,
               roundoff=0.0, why_not=None) -> dict:
    """One statement of :func:`felt_verdict` (its notes)."""
    out = {"quantity": quantity, "direction": direction,
           "name": statement_name(quantity, direction), "predicted": predicted,
           "measured": measured, "deviation": deviation,
           "linearisation": lin if lin is not None and math.isfinite(lin) else None,
           "roundoff": roundoff if math.isfinite(roundoff) else None,
           "wire": wire if wire is not None and math.isfinite(wire) else None,
           "uncertainty": None, "verdict": "not measurable", "within": None,
           "reason": why_not}
    if why_not is not None:
        return out
    if lin is None or not math.isfinite(lin):
        out["reason"] = "no finite linearisation bound for it (an undamped mode)"
        return out
    if wire is not None and not (math.isfinite(wire) and wire <= limit):
        out["reason"] = (f"the readings' rounding alone may move it by {wire:.2g} "
                         f"(relative, first order), above {limit:g}")
        return out
    if not (math.isfinite(deviation)):
        out["reason"] = "its predicted value is 0: no relative statement"
        return out
    u = lin + (wire or 0.0) + (roundoff if math.isfinite(roundoff) else 0.0)
    ok = deviation <= u
    out.update(uncertainty=u, verdict="within" if ok else "differs", within=bool(ok),
               reason=(f"measured - predicted {deviation:.2e} "
                       + ("<=" if ok else ">") + f" the stated uncertainty {u:.2e}"))
    return out


def felt_verdict(deviation, bound, wire=None, *, limit: float = MEASURABLE_WIRE,
                 estimated: int = 0, directions=None) -> dict:
    """The verdict of an n-D measurement against its stated uncertainty, per quantity
    and per principal direction.

    **What is stated.** The felt stiffness matrix and the felt damping matrix as a whole
    (the largest entry of ``|measured - predicted|`` over the predicted matrix's largest
    entry: :func:`felt_deviation`), and, given ``directions``, the felt stiffness and
    damping along each principal direction ``e_i`` of the prediction
    (``e_i^T X e_i`` over ``|e_i^T X_pred e_i|``: :func:`felt_directions`). Each
    statement says "within", "differs" or "not measurable" with its own uncertainty.

    **Each statement's uncertainty** (relative, first order) is the linearisation bound
    plus the wire's term plus the binary64 round-off allowance
    (:attr:`hapsim.analysis.linearisation_nd.LinearisationBound.roundoff`, relative to
    the matrix's largest entry, so ``roundoff max|X_pred| / |e_i^T X_pred e_i|`` along a
    direction):

    * linearisation (:mod:`hapsim.analysis.linearisation_nd`): a relative change
      ``eps`` of the loop's stiffness and inertia terms (``eps_k = (c_kin + c_link) a``)
      scales each rendered ``s_i^2`` by at most ``1 +- eps``, so the felt stiffness
      along ``e_i``, ``k_i = m_i |s_i|^2``, moves by at most ``eps_k k_i`` (relative
      ``eps_k``), and the felt damping ``b_i = -2 m_i Re s_i`` by at most
      ``m_i eps_k |s_i|``, relative ``eps_k |s_i| / (2 |Re s_i|)`` with mode ``i``'s own
      factor (a stiff, well-damped direction is not charged the lightly damped
      direction's factor). For a matrix as a whole the largest factor over the modes is
      taken (:attr:`LinearisationBound.damping`);
    * the wire (:func:`wire_terms_nd`): the first-order worst case of the same quantity's
      change under the readings' and the forces' rounding, whatever their signs and
      correlation: for a direction, Hoelder's inequality on the linear form
      ``e_i^T dX e_i`` of the fit's first-order change ``dX``, over ``|e_i^T X_pred e_i|``.

    **When a statement is made.** Not at all when no felt matrices were measured, or
    when the amplitude reaches a contact's or a plane's depth (the law is not smooth:
    nothing linear holds). A quantity whose wire term exceeds ``limit`` (or is not
    finite, or whose predicted value is 0) is "not measurable": the excitation is too
    small for the resolution *for that quantity*, and the first-order expansion no longer
    holds for it. Along a stiff direction the same rounding is small against the force
    rendered while along a soft one it is not, and the damping (a small real part of
    each pole) is always more sensitive than the stiffness, so one run may state the
    stiffness along one direction and nothing else.

    **The run's verdict** is the conjunction of what was stated: "differs" when any
    stated quantity differs; "within" when every quantity was stated and is within;
    "partly within" when every stated one is within but some could not be stated (the
    reason and ``not_stated`` name them: a reader of the verdict alone is not told that
    an unmeasured damping was verified); "not measurable" when nothing could be stated.

    Parameters
    ----------
    deviation : dict or None
        :func:`felt_deviation`'s result.
    bound : hapsim.analysis.linearisation_nd.LinearisationBound
    wire : dict or None, optional
        ``felt_stiffness`` and ``felt_damping``: the wire's relative terms for the
        matrices, and optionally ``directions`` (:func:`wire_terms_nd`); None: the
        record is exact, binary64 on the wire.
    limit : float, optional
        :data:`MEASURABLE_WIRE`.
    estimated : int, optional
        Estimated samples (missing replies) whose error bounds the wire's term carries
        (named in the reason).
    directions : dict, optional
        :func:`felt_directions`'s result (without it, or without the wire's
        ``directions`` when there is a wire, only the matrices are stated).

    Returns
    -------
    dict
        ``verdict`` (``"within"``, ``"partly within"``, ``"differs"`` or ``"not
        measurable"``), ``within`` (bool: every *stated* quantity within; None when
        nothing was stated), ``uncertainty`` (``felt_stiffness``,
        ``felt_damping``: each matrix's stated uncertainty [-], None for one not stated;
        None when nothing was stated), ``reason`` (str), ``statements`` (list of dicts:
        ``quantity``, ``direction`` (unit vector or None for the matrix), ``name``,
        ``predicted``, ``measured`` (along the direction; None for a matrix),
        ``deviation``, ``linearisation``, ``wire``, ``roundoff``, ``uncertainty`` [-],
        ``verdict``,
        ``within``, ``reason``) and ``not_stated`` (the names of the quantities that
        were not measurable).
    """
    lin = bound.to_dict()
    wq = {q: (None if wire is None else float(wire[q])) for q in _QUANTITIES}
    wdir = None if wire is None else (wire.get("directions") if isinstance(wire, dict)
                                      else None)
    dirs = directions if (directions is not None and (wire is None or wdir is not None)) \
        else None

    def no(reason):
        return {"verdict": "not measurable", "within": None, "uncertainty": None,
                "reason": reason, "statements": [], "not_stated": ["felt stiffness",
                                                                   "felt damping"]}
    if deviation is None:
        return no("the records give no felt matrices (fewer than n rendered pairs)")
    if lin["felt_stiffness"] is None:
        return no(f"the motion ({bound.amplitude:g} m from rest) reaches the depth of "
                  f"{bound.depth_name!r} ({bound.depth:.3g} m): the contact opens, no "
                  "linear estimate holds")
    rnd = float(getattr(bound, "roundoff", 0.0))
    st = []
    for q in _QUANTITIES:
        st.append(_statement(q, None, None, None, float(deviation[q]), lin[q], wq[q],
                             limit, rnd))
    if dirs is not None:
        eps = lin["felt_stiffness"]
        for q in _QUANTITIES:
            for i, row in enumerate(dirs[q]):
                lq = eps if q == "felt_stiffness" else eps * dirs["damping_factor"][i]
                p = abs(row["predicted"])
                rq = rnd * dirs["largest"][q] / p if p > 0 else math.inf
                st.append(_statement(q, [float(v) for v in dirs["directions"][i]],
                                     row["predicted"], row["measured"], row["deviation"],
                                     lq, None if wdir is None else float(wdir[q][i]),
                                     limit, rq))
    stated = [s for s in st if s["verdict"] != "not measurable"]
    not_stated = [s["name"] for s in st if s["verdict"] == "not measurable"]
    what = ("linearisation bound plus the wire's rounding" if wire is not None else
            "the linearisation bound; binary64 on the wire adds nothing")
    unc = {q: st[j]["uncertainty"] for j, q in enumerate(_QUANTITIES)}
    if not stated:
        wk, wd = wq["felt_stiffness"] or 0.0, wq["felt_damping"] or 0.0
        big = max(wk, wd)
        need = bound.amplitude * big / limit if math.isfinite(big) else None
        if estimated:
            reason = (f"the readings' errors (the wire's rounding and {estimated} "
                      f"estimated samples, missing replies) alone may move the felt "
                      f"stiffness by {wk:.2g} and the damping by {wd:.2g} (relative, first "
                      f"order), above {limit:g}, and no principal direction is measurable "
                      "either: fewer missing replies (or a larger excitation) are needed")
        else:
            reason = (f"the readings' rounding alone may move the felt stiffness by "
                      f"{wk:.2g} and the damping by {wd:.2g} (relative, first order), "
                      f"above {limit:g}, and no principal direction is measurable either: "
                      f"the excitation {bound.amplitude:g} m is too small for the wire's "
                      "resolution" + (f" (about {need:.2g} m or more is needed)"
                                      if need is not None else ""))
        out = no(reason)
        out.update(statements=st, not_stated=not_stated)
        return out
    bad = [s for s in stated if s["verdict"] == "differs"]
    ok = not bad
    if ok and not not_stated:
        reason = (f"measured = predicted within the stated uncertainty ({what})"
                  + (", as matrices and along each principal direction" if dirs is not None
                     else ""))
    elif ok:
        reason = (f"measured = predicted within the stated uncertainty ({what}): "
                  + ", ".join(s["name"] for s in stated))
    else:
        reason = ("measured differs from predicted by more than the stated uncertainty "
                  f"({what}): " + ", ".join(s["name"] for s in bad))
    if not_stated:
        reason += ("; not measurable (the wire's rounding too large against it"
                   + (f", {estimated} estimated samples" if estimated else "") + "): "
                   + ", ".join(not_stated))
    verdict = "differs" if not ok else ("partly within" if not_stated else "within")
    return {"verdict": verdict, "within": bool(ok),
            "uncertainty": unc, "reason": reason, "statements": st,
            "not_stated": not_stated}

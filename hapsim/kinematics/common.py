"""What the kinematic devices share: input checks, the joint torques of a Cartesian force
and the Cartesian mass of a joint inertia (:mod:`hapsim.kinematics`)."""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError, KinematicsError

__all__ = ["SINGULAR_SINE", "JOINT_TURN", "positive", "finite", "joint_angles",
           "geometry_of", "degrees_text", "joint_torques", "cartesian_mass"]

#: Refusal threshold near a singularity: the sine of the angle that vanishes there (the
#: angle between the two distal links of the pantograph, between a distal link and its
#: proximal one, the volume of the delta's constraint normals) must be at least this.
#: The Jacobian's condition number grows like its inverse: 1e-4 keeps it below ~1e4
#: times the link-length ratio, where a hand force still maps to finite torques and the
#: Cartesian mass is still meaningful.
SINGULAR_SINE = 1e-4


def positive(name: str, value) -> float:
    """``value`` as a finite length > 0 [m]; ConfigError (key ``name``) otherwise.

    Parameters
    ----------
    name : str
        The key named in the error.
    value : float or any
        The length [m].

    Returns
    -------
    float
        The length [m].

    Raises
    ------
    ConfigError
        Not a number, not finite, or <= 0.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a number [m], got {value!r}", key=name) from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(f"must be a finite length > 0 [m], got {value!r}", key=name)
    return v


def finite(name: str, value) -> float:
    """``value`` as a finite float; ConfigError (key ``name``) otherwise.

    Parameters
    ----------
    name : str
        The key named in the error.
    value : float or any
        The number.

    Returns
    -------
    float

    Raises
    ------
    ConfigError
        Not a number, or not finite.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a number, got {value!r}", key=name) from None
    if not math.isfinite(v):
        raise ConfigError(f"must be finite, got {value!r}", key=name)
    return v


#: The largest joint angle taken [rad]: one turn either way. A revolute joint's angle is
#: periodic, so nothing is lost; beyond it a value is a mistake (degrees given as radians
#: twice over, an overflow), and past ~1e16 rad its sine has no correct digit left.
JOINT_TURN = 2.0 * math.pi


def joint_angles(q, n: int, turn: bool = True) -> np.ndarray:
    """``q`` as a float array of shape (n,), finite and (with ``turn``) within one turn
    (:data:`JOINT_TURN`), else ConfigError (key ``joints``).

    Parameters
    ----------
    q : array_like, shape (n,)
        Joint angles [rad].
    n : int
        Joints of the device.
    turn : bool, optional
        Refuse an angle beyond one turn, ``|q| > 2 pi`` (default True).

    Returns
    -------
    ndarray, shape (n,)
        The angles [rad], float.

    Raises
    ------
    ConfigError
        Not numbers, another shape, not finite, or beyond one turn.
    """
    try:
        a = np.asarray(q, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"must be {n} joint angles [rad], got {q!r}", key="joints") from None
    if a.shape != (n,):
        raise ConfigError(f"must be {n} joint angles [rad], got shape {a.shape}",
                          key="joints")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"must be finite, got {a.tolist()}", key="joints")
    if turn and np.any(np.abs(a) > JOINT_TURN):
        raise ConfigError(f"must be within one turn, -360..360 deg (a revolute joint's "
                          f"angle is periodic: give it modulo 360), got "
                          f"{[round(math.degrees(v), 6) for v in a.tolist()]} deg",
                          key="joints")
    return a


def geometry_of(geometry, kind: str, presets: dict, cls: type):
    """``geometry`` itself when a ``cls``, else the preset of that name (ConfigError, key
    ``geometry``, naming the valid choices, otherwise).

    Parameters
    ----------
    geometry : str or cls
        A geometry, or a preset's name.
    kind : str
        The device's name for the message (``"pantograph"``, ``"delta"``).
    presets : dict
        The presets by name.
    cls : type
        The geometry class (:class:`~hapsim.kinematics.pantograph.PantographGeometry`,
        :class:`~hapsim.kinematics.delta.DeltaGeometry`).

    Returns
    -------
    cls
        The geometry.

    Raises
    ------
    ConfigError
        An unknown preset name, or neither a ``cls`` nor a string.
    """
    if isinstance(geometry, str):
        if geometry not in presets:
            raise ConfigError(f"unknown {kind} {geometry!r}; valid choices: "
                              f"{', '.join(presets)}", key="geometry")
        geometry = presets[geometry]
    if not isinstance(geometry, cls):
        raise ConfigError(f"must be a {cls.__name__} or a preset name, got {geometry!r}",
                          key="geometry")
    return geometry


def degrees_text(q) -> str:
    """Joint angles [rad] as ``"(a, b) deg"`` for a message.

    Parameters
    ----------
    q : iterable of float
        Joint angles [rad].

    Returns
    -------
    str
        Each in degrees to 6 significant digits.
    """
    return "(" + ", ".join(f"{math.degrees(v):.6g}" for v in q) + ") deg"


def joint_torques(J: np.ndarray, force, n: int) -> np.ndarray:
    """``tau = J^T F`` [N m] of a Cartesian force ``F`` (shape (n,), [N]) by virtual work;
    ConfigError (key ``force``) for a force of another shape or not finite.

    Parameters
    ----------
    J : ndarray, shape (n, n)
        Jacobian ``dx/dq`` [m/rad] at the joints.
    force : array_like, shape (n,)
        Cartesian force on the end effector [N].
    n : int
        The device's dimension.

    Returns
    -------
    ndarray, shape (n,)
        Joint torques [N m].

    Raises
    ------
    ConfigError
        ``force`` not numbers, of another shape, or not finite.
    """
    try:
        F = np.asarray(force, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"must be {n} force components [N], got {force!r}",
                          key="force") from None
    if F.shape != (n,) or not np.all(np.isfinite(F)):
        raise ConfigError(f"must be {n} finite force components [N], got {force!r}",
                          key="force")
    return J.T @ F


def cartesian_mass(J, joint_inertia) -> np.ndarray:
    """Cartesian (operational-space) mass ``M = J^-T M_q J^-1`` [kg].

    Parameters
    ----------
    J : array_like, shape (n, n)
        Jacobian ``dx/dq`` [m/rad], invertible.
    joint_inertia : array_like, shape (n,) or (n, n)
        Joint-space inertia ``M_q`` [kg m^2] (a vector: its diagonal), symmetric
        positive definite.

    Returns
    -------
    ndarray, shape (n, n)
        ``M`` [kg], symmetric (symmetrised against round-off). The same map takes a
        joint friction ``B_q`` [N m s/rad] to the Cartesian friction [N s/m].

    Notes
    -----
    Kinetic energy ``1/2 dq^T M_q dq = 1/2 dx^T M dx`` with ``dx = J dq`` (Khatib 1987).

    Raises
    ------
    ConfigError
        Shapes that do not match, or ``M_q`` not symmetric positive semi-definite
        (key ``joint_inertia``).
    KinematicsError
        ``J`` singular.
    """
    J = np.asarray(J, float)
    n = J.shape[0]
    Mq = np.asarray(joint_inertia, float)
    if Mq.ndim == 1:
        Mq = np.diag(Mq)
    if J.shape != (n, n) or Mq.shape != (n, n) or not np.all(np.isfinite(Mq)):
        raise ConfigError(f"needs a square Jacobian and a matching joint inertia; got "
                          f"{J.shape} and {np.shape(joint_inertia)}", key="joint_inertia")
    # eigenvalues of M_q scaled to entries <= 1: LAPACK's symmetric solver does not
    # converge on entries near the double range (a joint inertia of 1e308, issue 31)
    sq = max(float(np.max(np.abs(Mq))), np.finfo(float).tiny)
    if not np.allclose(Mq, Mq.T, rtol=1e-12, atol=0) or \
            np.min(np.linalg.eigvalsh(0.5 * (Mq / sq) + 0.5 * (Mq.T / sq))) < 0:
        raise ConfigError("must be symmetric positive semi-definite", key="joint_inertia")
    try:
        Jinv = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        raise KinematicsError("the Jacobian is singular: no Cartesian mass there",
                              joints=None, kind="serial") from None
    M = Jinv.T @ Mq @ Jinv
    return 0.5 * (M + M.T)

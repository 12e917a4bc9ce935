"""The loop of the THS with matrices: an n-DoF handle (n = 1, 2, 3; or n ports, each an
axis) at an operating point, and the virtual coupling's gains as matrices.

The 1-D THS of Florens, Voda & Urma (:class:`hapsim.analysis.loop.LoopModel`) generalised to
a handle moving in n Cartesian directions, linearised at an operating point
(docs/design.md, 'The THS'; issue 23):

- **Real side.** ``M x'' + B0 x' = F`` with the Cartesian mass ``M = J^-T M_q J^-1 + m_h I``
  [kg] and friction ``B0 = J^-T B_q J^-1 + b_h I`` [N s/m] (joint inertia ``M_q``, joint
  friction ``B_q`` mapped through the device Jacobian ``J`` at the operating point, plus
  the hand's mass and damping; :func:`hapsim.kinematics.cartesian_mass`). At rest the
  velocity-product (Coriolis) terms vanish and gravity is a constant offset, so this is
  the exact linearisation for small motion about the operating point.
- **Hold.** Zero-order hold of ``F`` over each period ``T`` (exact discretisation,
  :func:`hapsim.analysis.ths.holds.zoh_matrices`).
- **Delay.** ``d`` whole samples between the position a force is computed from and the
  sample it is applied at, as in 1-D (or ``m + f``, the split hold).
- **Virtual coupling.** ``F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1]) / T`` with the
  stiffness and damping *matrices* ``K`` [N/m], ``B`` [N s/m] (n x n).

**Stability** is read from the MIMO characteristic: the eigenvalues of the closed loop's
state matrix (:func:`hapsim.analysis.ths.holds.state_matrix`), never axis by axis: stable
axes do not make a stable coupled loop (Li, Tavakoli & Huang, "Stability of Cooperative
Teleoperation Using Haptic Devices With Complementary Degrees of Freedom", IEEE TCST 22(2),
2014 — coupling through a non-diagonal ``M`` or ``K`` moves the poles).

A rigid 1-D :class:`~hapsim.analysis.loop.LoopModel` with the zero-order hold is the case
n = 1 (:meth:`MatrixLoop.from_loop`); the functions of :mod:`hapsim.analysis.ths` take
either.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapsim.analysis.loop import MASS_RANGE, RATE_RANGE, LoopModel
from hapsim.analysis.subsample import split_delay
from hapsim.errors import ConfigError
from hapsim.option_values import check_values

__all__ = ["MatrixLoop", "MATRIX_HOLDS", "as_matrix_loop", "gain_matrices"]


#: The only hold the matrix loop models (the paper's idealised hold has no n-D form here).
MATRIX_HOLDS = ("zoh",)


def _matrix(name: str, value, n: int | None = None, *, symmetric: bool = False,
            definite: str | None = None) -> np.ndarray:
    """``value`` as a finite n x n float matrix (a scalar: times I; a vector: diagonal)."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a number or a square matrix, got {value!r}",
                          key=name) from None
    if a.ndim == 0 and n is not None:
        a = a * np.eye(n)
    elif a.ndim == 1:
        a = np.diag(a)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or (n is not None and a.shape[0] != n):
        raise ConfigError(f"must be a {n or 'square'} x {n or 'square'} matrix, got shape "
                          f"{a.shape}", key=name)
    if not np.all(np.isfinite(a)):
        raise ConfigError("must be finite", key=name)
    if symmetric:
        scale = max(float(np.max(np.abs(a))), 1e-300)
        if np.max(np.abs(a - a.T)) > 1e-12 * scale:
            raise ConfigError("must be symmetric", key=name)
        a = 0.5 * (a + a.T)
    if definite is not None:
        lam = np.linalg.eigvalsh(a)
        if definite == "positive" and not lam[0] > 0:
            raise ConfigError(f"must be positive definite (smallest eigenvalue "
                              f"{lam[0]:g})", key=name)
        if definite == "semi" and lam[0] < -1e-12 * max(abs(lam[-1]), 1e-300):
            raise ConfigError(f"must be positive semi-definite (smallest eigenvalue "
                              f"{lam[0]:g})", key=name)
    return a


@dataclass(frozen=True)
class MatrixLoop:
    """One n-DoF simulator configuration seen from the THS, at an operating point.

    Parameters
    ----------
    mass : array_like, shape (n, n) (or (n,) diagonal, or a scalar with ``dof``)
        Cartesian mass ``M`` of hand + handle [kg], symmetric positive definite.
    friction : array_like, shape (n, n) (or (n,), or a scalar)
        Cartesian viscous friction ``B0`` [N s/m], symmetric positive semi-definite.
    rate_hz : float > 0
        Sample rate [Hz]; ``T = 1 / rate_hz``.
    delay : float >= 0
        Delay ``d`` [periods] (as :class:`hapsim.analysis.loop.LoopModel`): a whole
        number (stored as an int) or ``m + f``, the split hold
        (:mod:`hapsim.analysis.subsample`).
    hold : {"zoh"}
        Zero-order hold (the only one modelled in n-D).
    dof : int, optional
        ``n`` when ``mass`` is a scalar.

    Raises
    ------
    ConfigError
        A mass not symmetric positive definite or outside
        :data:`hapsim.analysis.loop.MASS_RANGE` (its eigenvalues), friction not symmetric
        positive semi-definite, shapes that differ, a rate outside
        :data:`~hapsim.analysis.loop.RATE_RANGE`, a delay not a real number in
        ``[0, MAX_DELAY]``, an unknown hold; ``key`` names the field.
    """

    mass: object
    friction: object = 0.0
    rate_hz: float = 1000.0
    delay: int = 1
    hold: str = "zoh"
    dof: int | None = None

    def __post_init__(self) -> None:
        n = self.dof
        if n is None and np.ndim(self.mass) == 0:
            raise ConfigError("a scalar mass needs dof", key="dof")
        M = _matrix("mass", self.mass, n, symmetric=True, definite="positive")
        n = M.shape[0]
        if not 1 <= n <= 3:
            raise ConfigError(f"must be 1, 2 or 3 degrees of freedom, got {n}", key="dof")
        lam = np.linalg.eigvalsh(M)
        if lam[0] < MASS_RANGE[0] or lam[-1] > MASS_RANGE[1]:
            raise ConfigError(f"eigenvalues must be within {MASS_RANGE[0]:g} and "
                              f"{MASS_RANGE[1]:g} kg, got {lam[0]:g}..{lam[-1]:g}",
                              key="mass")
        B0 = _matrix("friction", self.friction, n, symmetric=True, definite="semi")
        try:
            r = float(self.rate_hz)
        except (TypeError, ValueError):
            raise ConfigError(f"must be a number [Hz], got {self.rate_hz!r}",
                              key="rate_hz") from None
        # the rate's sign and the delay by the declarations of --rate and --delay
        # (hapsim.option_values.API_OPTIONS["loop"], as LoopModel): one message
        check_values("loop", key_by="parameter", rate_hz=r)
        if not RATE_RANGE[0] <= r <= RATE_RANGE[1]:
            raise ConfigError(f"must be between {RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} "
                              f"Hz, got {self.rate_hz!r}", key="rate_hz")
        d = self.delay
        check_values("loop", key_by="parameter", delay=d)
        if not isinstance(self.hold, str) or self.hold not in MATRIX_HOLDS:
            raise ConfigError(f"unknown hold {self.hold!r} for an n-DoF loop; valid "
                              f"choices: {', '.join(MATRIX_HOLDS)}", key="hold")
        object.__setattr__(self, "mass", M)
        object.__setattr__(self, "friction", B0)
        object.__setattr__(self, "rate_hz", r)
        whole, frac = split_delay(d)
        object.__setattr__(self, "delay", whole if frac == 0.0 else float(d))
        object.__setattr__(self, "dof", n)

    @property
    def period(self) -> float:
        """Sample period ``T`` [s]."""
        return 1.0 / self.rate_hz

    @classmethod
    def from_device(cls, device, joints, joint_inertia, joint_friction=0.0, *,
                    hand_mass: float = 0.0, hand_damping: float = 0.0,
                    rate_hz: float = 1000.0, delay: int = 1) -> "MatrixLoop":
        """The loop of a kinematic device at the joint configuration ``joints``.

        Parameters
        ----------
        device : hapsim.kinematics.Pantograph or hapsim.kinematics.Delta
            The device (its ``jacobian(q)``).
        joints : array_like, shape (n,)
            Operating point [rad].
        joint_inertia : array_like, shape (n,) or (n, n)
            Joint-space inertia ``M_q`` [kg m^2].
        joint_friction : array_like, shape (n,) or (n, n), or float
            Joint viscous friction ``B_q`` [N m s/rad].
        hand_mass, hand_damping : float, optional
            Isotropic hand mass [kg] and damping [N s/m] added in Cartesian space.
        rate_hz, delay
            As the constructor.

        Returns
        -------
        MatrixLoop
            ``M = J^-T M_q J^-1 + m_h I``, ``B0 = J^-T B_q J^-1 + b_h I`` (module docstring).

        Raises
        ------
        hapsim.errors.KinematicsError
            A singular or unreachable operating point.
        ConfigError
            As :func:`hapsim.kinematics.cartesian_mass` and the constructor.
        """
        from hapsim.kinematics import cartesian_mass
        J = device.jacobian(joints)
        n = J.shape[0]
        Bq = _matrix("joint_friction", joint_friction, n)
        M = cartesian_mass(J, joint_inertia) + float(hand_mass) * np.eye(n)
        B0 = cartesian_mass(J, Bq) + float(hand_damping) * np.eye(n)
        return cls(mass=M, friction=B0, rate_hz=rate_hz, delay=delay)

    def to_dict(self) -> dict:
        """JSON-ready dict: ``dof``, ``mass`` [kg] and ``friction`` [N s/m] as nested
        lists, ``rate_hz``, ``delay``, ``hold``.

        Returns
        -------
        dict
            ``dof`` (int), ``mass`` and ``friction`` (n lists of n), ``rate_hz`` [Hz],
            ``delay`` [periods] (int when whole, else float) and ``hold`` (``"zoh"``).
        """
        return {"dof": self.dof, "mass": self.mass.tolist(),
                "friction": self.friction.tolist(), "rate_hz": self.rate_hz,
                "delay": self.delay, "hold": self.hold}

    @classmethod
    def from_loop(cls, loop: LoopModel) -> "MatrixLoop":
        """The 1-D loop as the case n = 1: ``M = [[m]]``, ``B0 = [[b0]]``, its rate and
        delay.

        Parameters
        ----------
        loop : hapsim.analysis.loop.LoopModel
            A rigid loop (one body, no real stiffness, no correction) with the zero-order
            hold.

        Returns
        -------
        MatrixLoop
            ``dof = 1``; its state matrix's characteristic polynomial is the loop's
            ``P K + Q B + R`` (:func:`hapsim.analysis.loop.characteristic`, zoh).

        Raises
        ------
        ConfigError
            The ideal hold (key ``hold``), a compliant grip, a real stiffness or a
            correction (key ``loop``): the matrix loop models none of them; the 1-D
            functions of :mod:`hapsim.analysis.ths` take such a loop as it is.
        """
        if loop.hold not in MATRIX_HOLDS:
            raise ConfigError(f"the matrix loop models the {', '.join(MATRIX_HOLDS)} hold "
                              f"only, this loop has {loop.hold!r}", key="hold")
        if loop.generic:
            raise ConfigError("the matrix loop is one rigid body with a plain virtual "
                              "coupling: this loop has a compliant grip, a real stiffness "
                              "or a correction", key="loop")
        return cls(mass=[[loop.mass]], friction=[[loop.friction]], rate_hz=loop.rate_hz,
                   delay=loop.delay)

    def to_loop_model(self) -> LoopModel:
        """The case n = 1 as a :class:`~hapsim.analysis.loop.LoopModel` (the inverse of
        :meth:`from_loop`).

        Returns
        -------
        hapsim.analysis.loop.LoopModel
            ``mass = M[0, 0]``, ``friction = B0[0, 0]``, the rate, delay and hold.

        Raises
        ------
        ConfigError
            ``dof > 1`` (key ``dof``), or a value the 1-D loop refuses (its ranges, e.g.
            ``b0 T / m``).
        """
        if self.dof != 1:
            raise ConfigError(f"a loop of {self.dof} degrees of freedom is not a 1-D loop",
                              key="dof")
        return LoopModel(mass=float(self.mass[0, 0]), friction=float(self.friction[0, 0]),
                         rate_hz=self.rate_hz, delay=self.delay, hold=self.hold)


def as_matrix_loop(loop) -> MatrixLoop:
    """``loop`` as a :class:`MatrixLoop`: itself, or a 1-D loop as the case n = 1.

    Parameters
    ----------
    loop : MatrixLoop or hapsim.analysis.loop.LoopModel

    Returns
    -------
    MatrixLoop

    Raises
    ------
    ConfigError
        As :meth:`MatrixLoop.from_loop`; another type (key ``loop``).
    """
    if isinstance(loop, MatrixLoop):
        return loop
    if isinstance(loop, LoopModel):
        return MatrixLoop.from_loop(loop)
    raise ConfigError(f"must be a LoopModel or a MatrixLoop, got {type(loop).__name__}",
                      key="loop")


def gain_matrices(loop: MatrixLoop, K, B) -> tuple[np.ndarray, np.ndarray]:
    """The virtual coupling's stiffness and damping as ``(n, n)`` matrices.

    Parameters
    ----------
    loop : MatrixLoop
        The loop (its ``dof`` is ``n``).
    K, B : float or array_like, shape (n,) or (n, n)
        Stiffness [N/m] and damping [N s/m]: a scalar (isotropic), a diagonal, or a
        symmetric matrix.

    Returns
    -------
    tuple of ndarray, shape (n, n)
        ``(K, B)``.

    Raises
    ------
    ConfigError
        A value that is not finite, of another shape, or not symmetric.
    """
    n = loop.dof
    return _matrix("K", K, n), _matrix("B", B, n)

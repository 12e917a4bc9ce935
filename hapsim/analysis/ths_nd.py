"""The THS as a matrix: the sampled loop of an n-DoF device (n = 1, 2, 3) and its felt
stiffness and damping matrices.

The 1-D THS of Florens, Voda & Urma (:mod:`hapsim.analysis.loop`, :mod:`hapsim.analysis.ths`)
generalised to a handle moving in n Cartesian directions, linearised at an operating point
(docs/design.md, 'The THS'; issue 23):

- **Real side.** ``M x'' + B0 x' = F`` with the Cartesian mass ``M = J^-T M_q J^-1 + m_h I``
  [kg] and friction ``B0 = J^-T B_q J^-1 + b_h I`` [N s/m] (joint inertia ``M_q``, joint
  friction ``B_q`` mapped through the device Jacobian ``J`` at the operating point, plus
  the hand's mass and damping; :func:`hapsim.kinematics.cartesian_mass`). At rest the
  velocity-product (Coriolis) terms vanish and gravity is a constant offset, so this is
  the exact linearisation for small motion about the operating point.
- **Hold.** Zero-order hold of ``F`` over each period ``T`` (exact discretisation,
  :func:`zoh_matrices`).
- **Delay.** ``d`` whole samples between the position a force is computed from and the
  sample it is applied at, as in 1-D.
- **Virtual coupling.** ``F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1]) / T`` with the
  stiffness and damping *matrices* ``K`` [N/m], ``B`` [N s/m] (n x n).

**Stability** is read from the MIMO characteristic: the eigenvalues of the closed loop's
state matrix (:func:`state_matrix`), never axis by axis: stable axes do not make a stable
coupled loop (Li, Tavakoli & Huang, "Stability of Cooperative Teleoperation Using Haptic
Devices With Complementary Degrees of Freedom", IEEE TCST 22(2), 2014 — coupling through a
non-diagonal ``M`` or ``K`` moves the poles).

**The felt matrices.** In 1-D the felt ``(k, b)`` is the continuous oscillator
``m s^2 + b s + k = 0`` whose poles ``s = ln(z)/T`` are the rendered (least damped)
closed-loop pair ``z`` (Florens et al. Sec. 5). In n-D the closed loop has n rendered pairs
``z_i`` (:func:`rendered_pairs`: the n least damped complex pairs whose handle mode shapes
are independent), each with its mode shape ``u_i`` (the position part of the eigenvector,
n complex components). The felt ``(k, b)`` matrices are the unique real n x n pair such that
the continuous second-order system ``M x'' + b x' + k x = 0`` has exactly these 2n
eigenpairs ``(s_i, u_i)``, ``(conj s_i, conj u_i)``:

    k U + b U S = -M U S^2,   U = [u_1..u_n, conj u_1..conj u_n] (n x 2n),
    S = diag(s_1..s_n, conj s_1..conj s_n),   i.e.   [k  b] [U; U S] = -M U S^2,

the inverse quadratic eigenvalue problem (Lancaster, "Inverse spectral problems for
semisimple damped vibrating systems", SIAM J. Matrix Anal. Appl. 29(1), 2007; Lancaster &
Prells, J. Sound Vib. 283, 2005): with ``[U; U S]`` invertible the pair is unique and real.
The felt system therefore has the rendered poles *and* the rendered mode shapes: a hand
pushing along ``u_i`` feels the oscillator ``(m_i, k_i, b_i)``. For ``n = 1`` this is the
1-D map exactly; for a decoupled (diagonal) loop it is the 1-D map per axis. In general
``k`` and ``b`` are *not* symmetric: the sampled, delayed loop is not a symmetric
mechanical system, and its exact second-order image carries that (the symmetric parts
are the conservative stiffness and the dissipative damping; the antisymmetric parts are
circulatory and gyroscopic terms, of the order of the coupling times the delay). They
are symmetric when the loop is (e.g. ``M``, ``B0``, ``K``, ``B`` diagonal in one basis).

**Principal directions.** Each rendered mode moves the handle along an ellipse
``Re(u_i e^{i w t})``; its principal direction ``e_i`` is the ellipse's major axis (unit,
real). Along it the felt pair is ``k_i = m_i |s_i|^2``, ``b_i = -2 m_i Re s_i`` with the
modal mass ``m_i = e_i^T M e_i`` (the 1-D formulas with the mass felt along ``e_i``).

**Stiffness limit per direction.** ``K_max(e)``: the largest ``kappa`` such that the loop
with ``K = K0 + kappa e e^T`` (``K0`` the rest of the virtual stiffness) is stable for every
``kappa' in (0, kappa)``. The added stiffness is a rank-one feedback, so a pole crosses the
unit circle at ``z = e^{i theta}`` iff ``kappa = -1 / (c^T (z I - A0)^-1 b)`` is real
(:func:`direction_limit`): exact crossings, classified by the spectral radius between
them, as :func:`hapsim.analysis.stability.stability_limit` does in 1-D.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import MASS_RANGE, MAX_DELAY, RATE_RANGE, STABILITY_TOL
from hapsim.analysis.subsample import split_delay
from hapsim.errors import ConfigError
from hapsim.option_values import check_values

__all__ = ["LoopModelND", "zoh_matrices", "split_hold_matrices", "state_matrix", "closed_loop_poles_nd", "rendered_pairs", "rendered_pairs_of", "felt_matrices", "continuous_poles", "render_state", "RenderND", "render_nd", "gain_matrices", "zoh_blocks"]

#: The only hold the n-D loop models (the paper's idealised hold has no n-D form here).
HOLDS_ND = ("zoh",)


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
class LoopModelND:
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
        if self.hold not in HOLDS_ND:
            raise ConfigError(f"unknown hold {self.hold!r} for an n-DoF loop; valid "
                              f"choices: {', '.join(HOLDS_ND)}", key="hold")
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
                    rate_hz: float = 1000.0, delay: int = 1) -> "LoopModelND":
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
        LoopModelND
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
        lists, ``rate_hz``, ``delay``, ``hold``."""
        return {"dof": self.dof, "mass": self.mass.tolist(),
                "friction": self.friction.tolist(), "rate_hz": self.rate_hz,
                "delay": self.delay, "hold": self.hold}


def split_hold_matrices(loop: LoopModelND):
    """The split hold of ``M x'' + B0 x' = F`` for the loop's delay ``m + f``.

    Parameters
    ----------
    loop : LoopModelND

    Returns
    -------
    Ad : ndarray, shape (2n, 2n)
        As :func:`zoh_matrices`.
    Gamma0 : ndarray, shape (2n, n)
        Response of ``[x, v]`` to the force held over the period's last ``(1 - f) T``
        [m/N, m/(N s)].
    Gamma1 : ndarray, shape (2n, n)
        Response to the force held over its first ``f T`` (zeros for a whole delay).

    Notes
    -----
    ``Gamma0 = int_0^((1-f)T) e^(As) ds b``, ``Gamma1 = e^(A(1-f)T) int_0^(fT) e^(As) ds b``
    (modified z-transform: Franklin, Powell & Workman ch. 4, sec. 4.3; Astrom & Wittenmark
    sec. 2.3; :mod:`hapsim.analysis.subsample`), each piece by :func:`zoh_matrices`' block
    exponential over its own length.
    """
    T = loop.period
    f = float(loop.delay) % 1.0
    Ad, Bd = _zoh_over(loop, T)
    if f == 0.0:
        return Ad, Bd, np.zeros_like(Bd)
    A0, G0 = _zoh_over(loop, (1.0 - f) * T)
    _, Gf = _zoh_over(loop, f * T)
    return Ad, G0, A0 @ Gf


def zoh_matrices(loop: LoopModelND) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of ``M x'' + B0 x' = F``.

    Parameters
    ----------
    loop : LoopModelND

    Returns
    -------
    Ad : ndarray, shape (2n, 2n)
        Transition of ``[x, v]`` ([m], [m/s]) over one period.
    Bd : ndarray, shape (2n, n)
        Response of ``[x, v]`` to a force held over the period [m/N, m/(N s)].

    Notes
    -----
    With ``C = M^-1 B0`` and ``Z = -C T``: ``Ad = [[I, T phi1(Z)], [0, e^Z]]``,
    ``Bd = [[T^2 phi2(Z)], [T phi1(Z)]] M^-1``, ``phi1(Z) = sum Z^k/(k+1)!``,
    ``phi2(Z) = sum Z^k/(k+2)!``; the three blocks come from one matrix exponential of
    ``[[Z, I, 0], [0, 0, I], [0, 0, 0]]`` (the phi-functions of exponential integrators:
    Higham, *Functions of Matrices*, 2008, Sec. 10.7.4), which keeps ``1 - e^-x`` and
    ``e^-x - 1 + x`` at full relative precision for small ``x = b0 T/m`` (the 1-D
    :func:`hapsim.analysis.loop.zoh_state_space` is the case n = 1).
    """
    return _zoh_over(loop, loop.period)


def _zoh_over(loop: LoopModelND, T: float):
    """:func:`zoh_matrices` over a hold of length ``T`` [s]."""
    return zoh_blocks(loop.mass, loop.friction, T)


def zoh_blocks(mass, friction, T: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`zoh_matrices` of raw matrices, over a hold of length ``T`` [s] (no range
    checks: a joint-space inertia of 2e-4 kg m^2 is outside :data:`MASS_RANGE`).

    Parameters
    ----------
    mass : ndarray, shape (n, n)
        ``M`` [kg] (or [kg m^2]), invertible.
    friction : ndarray, shape (n, n)
        ``B0`` [N s/m] (or [N m s/rad]).
    T : float
        The hold [s].

    Returns
    -------
    (Ad, Bd)
        As :func:`zoh_matrices`.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``mass`` singular.
    """
    from scipy.linalg import expm
    M = np.asarray(mass, float)
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    Z = -(Minv @ np.asarray(friction, float)) * T
    I = np.eye(n)
    big = np.zeros((3 * n, 3 * n))
    big[:n, :n] = Z
    big[:n, n:2 * n] = I
    big[n:2 * n, 2 * n:] = I
    E = expm(big)
    eZ, phi1, phi2 = E[:n, :n], E[:n, n:2 * n], E[:n, 2 * n:]
    Ad = np.zeros((2 * n, 2 * n))
    Ad[:n, :n] = I
    Ad[:n, n:] = T * phi1
    Ad[n:, n:] = eZ
    Bd = np.vstack([T * T * phi2 @ Minv, T * phi1 @ Minv])
    return Ad, Bd


def gain_matrices(loop: LoopModelND, K, B) -> tuple[np.ndarray, np.ndarray]:
    """The virtual coupling's stiffness and damping as ``(n, n)`` matrices.

    Parameters
    ----------
    loop : LoopModelND
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


def state_matrix(loop: LoopModelND, K, B=0.0, delays=None) -> np.ndarray:
    """The closed loop's state matrix (plant + delay line + virtual coupling).

    Parameters
    ----------
    loop : LoopModelND
    K : array_like, shape (n, n) (or (n,), or a scalar: times I)
        Virtual stiffness matrix [N/m].
    B : array_like, shape (n, n) (or (n,), or a scalar), optional
        Virtual damping matrix [N s/m].
    delays : sequence of int, shape (n,), optional
        A whole delay per axis [periods] (several ports, each its own device): row ``i``
        of ``F`` is computed from ``x[n-d_i]`` and applied by axis ``i``'s hold; ``d`` is
        then ``max d_i`` (``loop.delay`` is not used). Default: ``loop.delay`` on every axis.

    Returns
    -------
    ndarray, shape (n (d + 3), n (d + 3)); ``n (m + 4)`` for a delay ``m + f``
        ``s[n+1] = A s[n]`` for the state ``s[n] = (x[n], v[n], x[n-1], ..., x[n-d-1])``
        (a delay ``m + f``: ``..., x[n-m-1]``, then the force held over the period's
        first ``f T``, :func:`split_hold_matrices`)
        (positions [m], velocities [m/s]); ``F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1])/T``
        held over ``[nT, (n+1)T)``. For n = 1 its characteristic polynomial is the 1-D
        ``P K + Q B + R`` of :func:`hapsim.analysis.loop.characteristic` (zoh).

    Raises
    ------
    ConfigError
        ``K`` or ``B`` not finite or of the wrong shape (key ``K`` / ``B``); ``delays``
        not ``n`` whole numbers in ``[0, MAX_DELAY]`` (key ``delays``).
    """
    Kq, Bq = gain_matrices(loop, K, B)
    n, d, T = loop.dof, loop.delay, loop.period
    if delays is None and d % 1:
        return _split_state_matrix(loop, Kq, Bq)
    per = [d] * n if delays is None else list(delays)
    if len(per) != n or not all(isinstance(x, int) and 0 <= x <= MAX_DELAY for x in per):
        raise ConfigError(f"must be {n} whole delays in [0, {MAX_DELAY}], got {delays!r}",
                          key="delays")
    d = max(per)
    Ad, Bd = zoh_matrices(loop)
    N = n * (d + 3)
    A = np.zeros((N, N))
    A[:2 * n, :2 * n] = Ad

    def pos(k):   # block of x[n - k]
        return slice(0, n) if k == 0 else slice((k + 1) * n, (k + 2) * n)
    # F = -(K + B/T) x[n-d] + (B/T) x[n-d-1], the rows of the axes of each delay
    for dk in sorted(set(per)):
        rows = np.array([[float(x == dk)] for x in per])
        A[:2 * n, pos(dk)] += Bd @ (rows * -(Kq + Bq / T))
        A[:2 * n, pos(dk + 1)] += Bd @ (rows * (Bq / T))
    for k in range(1, d + 2):     # x[n+1-k] <- x[n-(k-1)]
        A[pos(k), pos(k - 1)] = np.eye(n)
    return A


def _split_state_matrix(loop: LoopModelND, Kq, Bq) -> np.ndarray:
    """:func:`state_matrix` for a delay ``m + f``: state ``(x[n], v[n], x[n-1], ...,
    x[n-m-1], h[n])`` with ``h[n] = F[n-m-1]`` the force held over the period's first
    ``f T``: ``[x; v][n+1] = Ad [x; v] + Gamma0 F[n-m] + Gamma1 h``, ``h[n+1] = F[n-m]``
    (:func:`hapsim.analysis.subsample.held_plant`); ``n (m + 4)`` states."""
    n, T = loop.dof, loop.period
    m = int(math.floor(loop.delay))
    Ad, G0, G1 = split_hold_matrices(loop)
    N = n * (m + 4)
    A = np.zeros((N, N))
    A[:2 * n, :2 * n] = Ad

    def pos(k):   # block of x[n - k]
        return slice(0, n) if k == 0 else slice((k + 1) * n, (k + 2) * n)
    h = slice((m + 3) * n, (m + 4) * n)
    Fx, Fxp = -(Kq + Bq / T), Bq / T          # F[n-m] = Fx x[n-m] + Fxp x[n-m-1]
    A[:2 * n, pos(m)] += G0 @ Fx
    A[:2 * n, pos(m + 1)] += G0 @ Fxp
    A[:2 * n, h] += G1
    A[h, pos(m)] = Fx
    A[h, pos(m + 1)] = Fxp
    for k in range(1, m + 2):     # x[n+1-k] <- x[n-(k-1)]
        A[pos(k), pos(k - 1)] = np.eye(n)
    return A


def closed_loop_poles_nd(loop: LoopModelND, K, B=0.0) -> np.ndarray:
    """Eigenvalues of :func:`state_matrix` [-], shape (n (d + 3),), largest ``|z|`` first.

    Parameters
    ----------
    loop : LoopModelND
    K, B : array_like
        Virtual stiffness [N/m] and damping [N s/m] matrices.

    Returns
    -------
    ndarray of complex
        The MIMO characteristic's roots (Li, Tavakoli & Huang 2014: stability from these,
        not per axis).
    """
    z = np.linalg.eigvals(state_matrix(loop, K, B))
    return z[np.argsort(-np.abs(z), kind="stable")]


def continuous_poles(z, T: float) -> np.ndarray:
    """``s = ln(z) / T`` [1/s], accurate near ``z = 1`` (``log1p`` of ``|z|^2 - 1``).

    Parameters
    ----------
    z : array_like of complex
        Sampled poles [-] (non-zero).
    T : float
        Sample period [s].

    Returns
    -------
    ndarray of complex, shape of ``z``
        ``(ln|z| + i arg z) / T`` with ``arg z`` in ``(-pi, pi]``; ``ln|z|`` as
        ``log1p(2 Re w + |w|^2) / 2``, ``w = z - 1``, so that a pole near the unit circle
        keeps the relative precision of its damping (as :func:`hapsim.analysis.modes.log_z`
        for one pole).
    """
    z = np.asarray(z)
    w = z - 1.0
    re = 0.5 * np.log1p(2.0 * w.real + w.real ** 2 + w.imag ** 2)
    return (re + 1j * np.angle(z)) / T


def rendered_pairs(loop: LoopModelND, K, B=0.0):
    """The n rendered pairs of the closed loop and their handle mode shapes.

    Parameters
    ----------
    loop : LoopModelND
    K, B : array_like
        Virtual stiffness [N/m] and damping [N s/m] matrices.

    Returns
    -------
    z : ndarray of complex, shape (m,)
        The rendered poles (``Im z > 0``), ``m <= n``: the least damped complex pairs
        (largest ``|z|``) taken in turn while their handle mode shapes stay independent
        (the 1-D rendered pair, Florens et al. Sec. 5, per mode); ``m < n`` when the loop
        has fewer such pairs (then no felt matrices exist).
    U : ndarray of complex, shape (n, m)
        Their mode shapes: the position part ``x[n]`` of each eigenvector, scaled to unit
        norm with its largest component real positive.
    poles : ndarray of complex
        Every closed-loop pole, largest ``|z|`` first.
    """
    return rendered_pairs_of(state_matrix(loop, K, B), loop.dof, loop.period)


def rendered_pairs_of(A, n: int, period: float):
    """:func:`rendered_pairs` of any closed-loop state matrix whose first ``n`` states
    are the handle position (a whole scene: :mod:`hapsim.analysis.scene_check`).

    Parameters
    ----------
    A : ndarray, shape (N, N)
        Closed-loop state matrix.
    n : int
        Degrees of freedom of the handle.
    period : float
        Sample period ``T`` [s].

    Returns
    -------
    z, U, poles
        As :func:`rendered_pairs`; a pair whose handle part is below 1e-8 of its
        eigenvector's norm is a mode of the object the hand does not feel, never rendered.
    """
    z, V = np.linalg.eig(A)
    order = np.argsort(-np.abs(z), kind="stable")
    z, V = z[order], V[:, order]
    chosen, shapes, cols_taken = [], [], []
    for i in np.flatnonzero(z.imag > 1e-12 * np.maximum(1.0, np.abs(z))):
        u = V[:n, i]
        nu = np.linalg.norm(u)
        if not nu > 1e-8 * np.linalg.norm(V[:, i]):
            continue                                   # not seen at the handle
        u = u / nu
        j = int(np.argmax(np.abs(u)))
        u = u * (abs(u[j]) / u[j])
        # the inverse problem needs [W; W S] invertible: test the columns [u; s u / |s|]
        # of this pair with the ones taken (conjugates included)
        si = complex(continuous_poles(np.array([z[i]]), period)[0])
        unit = si / abs(si) if si != 0 else 0.0
        cols = cols_taken + [np.concatenate([u, unit * u]),
                             np.concatenate([u.conj(), np.conj(unit) * u.conj()])]
        if np.linalg.matrix_rank(np.column_stack(cols), tol=1e-6) < len(cols):
            continue
        cols_taken = cols
        chosen.append(z[i])
        shapes.append(u)
        if len(chosen) == n:
            break
    U = np.column_stack(shapes) if shapes else np.zeros((n, 0), complex)
    return np.array(chosen, complex), U, z


def felt_matrices(mass, s, U) -> tuple[np.ndarray, np.ndarray]:
    """The felt stiffness and damping matrices of n rendered modes (module docstring).

    Parameters
    ----------
    mass : array_like, shape (n, n)
        Cartesian mass ``M`` [kg].
    s : array_like of complex, shape (n,)
        Continuous poles ``s_i = ln(z_i)/T`` [1/s] (one per pair).
    U : array_like of complex, shape (n, n)
        Their mode shapes (columns).

    Returns
    -------
    k : ndarray, shape (n, n)
        Felt stiffness [N/m].
    b : ndarray, shape (n, n)
        Felt damping [N s/m].

    Notes
    -----
    Solves ``[k b] [W; W S] = -M W S^2`` with ``W = [U, conj U]``,
    ``S = diag(s, conj s)`` (Lancaster 2007): the unique real pair whose continuous system
    ``M x'' + b x' + k x = 0`` has the eigenpairs ``(s_i, u_i)`` and their conjugates.
    ``n = 1``: ``k = m |s|^2``, ``b = -2 m Re s`` (the 1-D inverse map).

    Raises
    ------
    ConfigError
        Fewer than n modes, or mode shapes that do not determine the pair (``[W; W S]``
        singular).
    """
    M = np.asarray(mass, float)
    n = M.shape[0]
    s = np.asarray(s, complex)
    U = np.asarray(U, complex)
    if s.shape != (n,) or U.shape != (n, n):
        raise ConfigError(f"the felt matrices need {n} rendered pairs with independent "
                          f"mode shapes at the handle, the loop has {s.size}",
                          key="felt")
    W = np.hstack([U, U.conj()])
    S = np.concatenate([s, s.conj()])
    G = np.vstack([W, W * S])
    rhs = -(M @ (W * S * S))
    try:
        X = np.linalg.solve(G.T, rhs.T).T          # X G = rhs
    except np.linalg.LinAlgError:
        raise ConfigError("the rendered modes' shapes do not determine a felt (k, b) pair",
                          key="felt") from None
    return X[:, :n].real.copy(), X[:, n:].real.copy()


@dataclass(frozen=True)
class RenderND:
    """What the hand feels through an n-DoF loop for virtual matrices ``(K, B)``.

    Attributes
    ----------
    dof : int
        n.
    K, B : ndarray, shape (n, n)
        The virtual stiffness [N/m] and damping [N s/m] analysed.
    felt_stiffness, felt_damping : ndarray, shape (n, n) or None
        The felt ``k`` [N/m] and ``b`` [N s/m] matrices (module docstring); None when the
        loop has fewer than n rendered pairs.
    directions : ndarray, shape (n, n) or None
        Principal directions (columns, unit) of the rendered modes, least damped first.
    direction_stiffness, direction_damping, direction_mass : ndarray, shape (n,) or None
        The felt pair along each direction (``k_i = m_i |s_i|^2`` [N/m],
        ``b_i = -2 m_i Re s_i`` [N s/m]) and its modal mass ``m_i`` [kg].
    rendered_poles : ndarray of complex, shape (<= n,)
        The rendered poles (``Im z > 0``).
    poles : ndarray of complex
        Every closed-loop pole, largest ``|z|`` first.
    spectral_radius : float
        ``max |z|`` [-].
    stable : bool
        ``spectral_radius <= 1 + STABILITY_TOL`` (the 1-D verdict's tolerance).
    note : str
        Empty, or why the felt matrices are None.
    """

    dof: int
    K: np.ndarray
    B: np.ndarray
    felt_stiffness: np.ndarray | None
    felt_damping: np.ndarray | None
    directions: np.ndarray | None
    direction_stiffness: np.ndarray | None
    direction_damping: np.ndarray | None
    direction_mass: np.ndarray | None
    rendered_poles: np.ndarray
    poles: np.ndarray
    spectral_radius: float
    stable: bool
    note: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict (matrices as nested lists, non-finite numbers as None).

        Returns
        -------
        dict
            ``dof``, ``K``, ``B``, ``felt_stiffness``, ``felt_damping`` (n x n),
            ``principal_directions`` (list of n unit vectors), ``direction_stiffness``,
            ``direction_damping``, ``direction_mass``, ``spectral_radius``, ``stable``,
            ``rendered_poles`` (``[re, im]`` pairs), ``note``.
        """
        def clean(a):
            if a is None:
                return None
            a = np.asarray(a, float)
            return [clean(r) for r in a] if a.ndim > 1 else \
                [float(v) if math.isfinite(v) else None for v in a]
        return {"dof": self.dof, "K": clean(self.K), "B": clean(self.B),
                "felt_stiffness": clean(self.felt_stiffness),
                "felt_damping": clean(self.felt_damping),
                "principal_directions": None if self.directions is None
                else clean(self.directions.T),
                "direction_stiffness": clean(self.direction_stiffness),
                "direction_damping": clean(self.direction_damping),
                "direction_mass": clean(self.direction_mass),
                "spectral_radius": float(self.spectral_radius) if
                math.isfinite(self.spectral_radius) else None,
                "stable": bool(self.stable),
                "rendered_poles": [[float(z.real), float(z.imag)]
                                   for z in self.rendered_poles],
                "note": self.note}


def _major_axis(u: np.ndarray) -> np.ndarray:
    """Unit major axis of the ellipse ``Re(u e^{i t})`` (``u`` complex, shape (n,))."""
    R = np.column_stack([u.real, u.imag])
    w, V = np.linalg.eigh(R @ R.T)
    e = V[:, -1]
    j = int(np.argmax(np.abs(e)))
    return e if e[j] > 0 else -e


def render_nd(loop: LoopModelND, K, B=0.0) -> RenderND:
    """Inverse map ``(K, B) -> (k, b)`` as matrices: what the hand feels, and whether the
    coupled loop is stable.

    Parameters
    ----------
    loop : LoopModelND
    K, B : array_like, shape (n, n) (or (n,), or a scalar: times I)
        Virtual stiffness [N/m] and damping [N s/m] matrices.

    Returns
    -------
    RenderND
        Felt matrices, principal directions and per-direction pairs (module docstring),
        every pole and the spectral radius of the MIMO characteristic.

    Raises
    ------
    ConfigError
        ``K`` or ``B`` not finite or of the wrong shape.
    """
    Kq, Bq = gain_matrices(loop, K, B)
    return render_state(state_matrix(loop, Kq, Bq), loop.mass, loop.period, K=Kq, B=Bq)


def render_state(A, mass, period: float, *, K=None, B=None) -> RenderND:
    """:func:`render_nd` of any closed-loop state matrix whose first n states are the
    handle position (n = the mass matrix's size).

    Parameters
    ----------
    A : ndarray, shape (N, N)
        Closed-loop state matrix.
    mass : ndarray, shape (n, n)
        Cartesian mass of hand + handle [kg].
    period : float
        Sample period ``T`` [s].
    K, B : ndarray, optional
        The virtual matrices to report (nan when not given).

    Returns
    -------
    RenderND
    """
    M = np.asarray(mass, float)
    n = M.shape[0]
    Kq = np.full((n, n), np.nan) if K is None else K
    Bq = np.full((n, n), np.nan) if B is None else B
    zr, U, poles = rendered_pairs_of(A, n, period)
    rho = float(np.max(np.abs(poles))) if poles.size else 0.0
    stable = rho <= 1.0 + STABILITY_TOL
    common = dict(dof=n, K=Kq, B=Bq, rendered_poles=zr, poles=poles, spectral_radius=rho,
                  stable=stable)
    if zr.size < n:
        return RenderND(felt_stiffness=None, felt_damping=None, directions=None,
                        direction_stiffness=None, direction_damping=None,
                        direction_mass=None,
                        note=f"the closed loop has {zr.size} rendered pair(s) with "
                             f"independent mode shapes at the handle, fewer than {n}: "
                             "no felt matrices", **common)
    s = continuous_poles(zr, period)
    k, b = felt_matrices(M, s, U)
    E = np.column_stack([_major_axis(U[:, i]) for i in range(n)])
    m = np.einsum("in,ij,jn->n", E, M, E)
    return RenderND(felt_stiffness=k, felt_damping=b, directions=E,
                    direction_stiffness=m * np.abs(s) ** 2,
                    direction_damping=-2.0 * m * s.real, direction_mass=m, **common)


# --------------------------------------------------------------------------- limits



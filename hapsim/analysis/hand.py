"""The hand on the handle: a second mass behind a grip spring-damper, exactly sampled.

Florens, Voda & Urma Sec. 4 judge a THS over "the whole family of possible parameter sets
that the THS may get along its variations"; the largest variation is the hand. Here the
hand is a mass ``mh`` with damping ``bh`` to ground (the arm), tied to the handle (mass
``mc``, friction ``bc``) by a grip spring ``kg`` and damper ``bg``::

    mc xh'' = f - bc xh' - kg (xh - xm) - bg (xh' - xm')
    mh xm'' =   - bh xm' - kg (xm - xh) - bg (xm' - xh')

State ``[xh, vh, xm, vm]`` (handle position, velocity, hand position, velocity) [m, m/s];
input the force ``f`` on the handle [N], held over each period (zero-order hold). A rigid
grip (``kg = inf``) is one mass ``mc + mh`` with friction ``bc + bh``.

The exact ZOH uses ``Gamma = int_0^T e^(A s) ds = T phi1(A T)`` (the top-right block of the
exponential of ``[[A, I], [0, 0]] T``, Van Loan 1978): ``Ad = I + A Gamma``, ``Bd = Gamma b``; ``A Gamma``
is kept separately (``Ad - I``, the delta-operator matrix) so that poles near ``z = 1`` keep
their relative precision.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["HAND_FIELDS", "hand_matrices", "hand_zoh", "nominal_member", "members",
           "ranged_fields"]

#: Order of the columns of a member array: hand mass [kg], hand damping [N s/m], grip
#: stiffness [N/m] (``inf``: rigid), grip damping [N s/m].
HAND_FIELDS = ("mass", "damping", "grip_stiffness", "grip_damping")


def hand_matrices(mc: float, bc: float, member) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state-space model of handle + hand (module docstring).

    Parameters
    ----------
    mc : float > 0
        Handle mass [kg].
    bc : float >= 0
        Handle friction [N s/m].
    member : array_like, shape (..., 4)
        ``(mh, bh, kg, bg)`` per member (:data:`HAND_FIELDS`), finite ``kg``.

    Returns
    -------
    A : ndarray, shape (..., 4, 4)
        ``d/dt [xh, vh, xm, vm] = A [xh, vh, xm, vm] + b f``.
    b : ndarray, shape (4,)
        Force input column ``[0, 1/mc, 0, 0]`` [1/kg].

    Raises
    ------
    ConfigError
        A non-positive mass or a non-finite grip stiffness.
    """
    p = np.asarray(member, dtype=float)
    mh, bh, kg, bg = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    if not (mc > 0) or np.any(mh <= 0) or not np.all(np.isfinite(kg)):
        raise ConfigError("hand model needs handle mass > 0, hand mass > 0 and a finite grip "
                          "stiffness", key="device.hand")
    A = np.zeros(p.shape[:-1] + (4, 4))
    A[..., 0, 1] = 1.0
    A[..., 1, 0] = -kg / mc
    A[..., 1, 1] = -(bc + bg) / mc
    A[..., 1, 2] = kg / mc
    A[..., 1, 3] = bg / mc
    A[..., 2, 3] = 1.0
    A[..., 3, 0] = kg / mh
    A[..., 3, 1] = bg / mh
    A[..., 3, 2] = -kg / mh
    A[..., 3, 3] = -(bh + bg) / mh
    b = np.array([0.0, 1.0 / mc, 0.0, 0.0])
    return A, b


def hand_zoh(mc: float, bc: float, member, period: float):
    """Exact zero-order-hold discretisation of handle + hand, for one member or a stack.

    Parameters
    ----------
    mc, bc : float
        Handle mass [kg] and friction [N s/m].
    member : array_like, shape (..., 4)
        ``(mh, bh, kg, bg)`` (:data:`HAND_FIELDS`), finite grip stiffness.
    period : float > 0
        Hold period ``T`` [s].

    Returns
    -------
    Aw : ndarray, shape (..., 4, 4)
        ``Ad - I`` [-] (accurate: ``A Gamma``).
    Bd : ndarray, shape (..., 4)
        Response of the state to a unit force held over one period [m/N, m/(N s), ...].

    Notes
    -----
    Van Loan (1978): ``expm([[A, I], [0, 0]] T) = [[e^(AT), Gamma], [0, I]]`` with
    ``Gamma = int_0^T e^(As) ds = T phi1(AT)``; ``Ad = I + A Gamma``, ``Bd = Gamma b``.
    ``phi1`` by scaling and squaring on the whole stack at once (:func:`_phi1`).
    """
    A, b = hand_matrices(mc, bc, member)
    T = float(period)
    # Gamma = T phi1(A T), computed on the balanced [x, v T] coordinates (O(1) entries:
    # (w T)^2 and damping x T / m) and mapped back: phi1(S X S^-1) = S phi1(X) S^-1.
    S = np.array([1.0, T, 1.0, T])
    F = _phi1((A * T) * S[:, None] / S[None, :]) / S[:, None] * S[None, :]
    return (A * T) @ F, (F @ b) * T


def _phi1(X: np.ndarray) -> np.ndarray:
    """``phi1(X) = sum_k X^k / (k+1)!`` (so ``e^X = I + X phi1(X)``) for a stack of matrices.

    Scaling and squaring: Taylor series (20 terms) at ``X / 2^s`` with ``||X|| / 2^s <=
    1/2``, then ``phi1(2Y) = phi1(Y) (I + e^Y) / 2``, ``e^(2Y) = (e^Y)^2``. Checked against
    ``scipy.linalg.expm`` of ``[[X, I], [0, 0]]`` (Van Loan 1978) in the tests.
    """
    norm = float(np.max(np.abs(X).sum(axis=-1))) if X.size else 0.0
    s = max(0, int(math.ceil(math.log2(norm / 0.5)))) if norm > 0.5 else 0
    Y = X / (2.0 ** s)
    eye = np.broadcast_to(np.eye(X.shape[-1]), X.shape)
    term = eye.copy()
    F = eye / 1.0
    for k in range(2, 22):
        term = term @ Y / k
        F = F + term
    E = eye + Y @ F
    for _ in range(s):
        F = 0.5 * F @ (eye + E)
        E = E @ E
    return F


def _span(v) -> tuple[float, float]:
    return (float(v[0]), float(v[1])) if isinstance(v, tuple) else (float(v), float(v))


def ranged_fields(hand) -> list[str]:
    """Names of the fields of a hand given as a true range (``lo < hi``).

    Parameters
    ----------
    hand : hapsim.scene.Hand

    Returns
    -------
    list of str
        Among :data:`HAND_FIELDS`, in that order; ``2 ** len(...)`` is the number of
        corners of the family.
    """
    return [f for f in HAND_FIELDS if _span(getattr(hand, f))[0] < _span(getattr(hand, f))[1]]


def nominal_member(hand) -> np.ndarray:
    """The nominal member of a hand family: the middle of every range.

    Parameters
    ----------
    hand : hapsim.scene.Hand

    Returns
    -------
    ndarray, shape (4,)
        ``(mh, bh, kg, bg)``; for a stiffness range the geometric middle ``sqrt(lo hi)``
        (stiffness ranges span decades), arithmetic otherwise.
    """
    out = []
    for f in HAND_FIELDS:
        lo, hi = _span(getattr(hand, f))
        out.append(math.sqrt(lo * hi) if f == "grip_stiffness" else 0.5 * (lo + hi))
    return np.array(out)


def members(hand, samples: int | None = None, *, grid: int = 9, seed: int = 0) -> np.ndarray:
    """The members of a hand family: every corner of the ranges, then a grid or samples.

    Parameters
    ----------
    hand : hapsim.scene.Hand
    samples : int, optional
        Number of seeded uniform random members (log-uniform for the grip stiffness) added
        after the corners; None: a full grid of ``grid`` points per ranged field instead.
    grid : int, optional
        Points per ranged field for the grid (>= 2).
    seed : int, optional
        ``numpy.random.default_rng`` seed of the samples.

    Returns
    -------
    ndarray, shape (n, 4)
        ``(mh, bh, kg, bg)`` per member; the first ``2^r`` rows are the corners (``r``
        ranged fields), the nominal member (:func:`nominal_member`) follows them.

    Raises
    ------
    ConfigError
        ``samples < 1`` or ``grid < 2``.
    """
    spans = [_span(getattr(hand, f)) for f in HAND_FIELDS]
    ranged = [i for i, (lo, hi) in enumerate(spans) if lo < hi]
    base = np.array([lo for lo, _ in spans])
    corners = np.repeat(base[None, :], 2 ** len(ranged), axis=0)
    for j, i in enumerate(ranged):
        bit = (np.arange(corners.shape[0]) >> j) & 1
        corners[:, i] = np.where(bit == 1, spans[i][1], spans[i][0])
    rows = [corners, nominal_member(hand)[None, :]]
    if samples is not None:
        if int(samples) < 1:
            raise ConfigError(f"must be >= 1, got {samples!r}", key="--samples")
        rng = np.random.default_rng(seed)
        s = np.repeat(base[None, :], int(samples), axis=0)
        for i in ranged:
            lo, hi = spans[i]
            u = rng.random(int(samples))
            s[:, i] = (lo * (hi / lo) ** u if HAND_FIELDS[i] == "grip_stiffness" and lo > 0
                       else lo + (hi - lo) * u)
        rows.append(s)
    elif ranged:
        if int(grid) < 2:
            raise ConfigError(f"must be >= 2, got {grid!r}", key="grid")
        axes = []
        for i in ranged:
            lo, hi = spans[i]
            axes.append(np.geomspace(lo, hi, grid) if HAND_FIELDS[i] == "grip_stiffness"
                        and lo > 0 else np.linspace(lo, hi, grid))
        mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(ranged))
        g = np.repeat(base[None, :], mesh.shape[0], axis=0)
        g[:, ranged] = mesh
        rows.append(g)
    return np.concatenate(rows, axis=0)

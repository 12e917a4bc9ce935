"""The hand on the handle: a second mass behind a grip spring-damper, exactly sampled.

Florens, Voda & Urma Sec. 4 judge a THS over "the whole family of possible parameter sets
that the THS may get along its variations"; the largest variation is the hand. Here the
hand is a mass ``mh`` with damping ``bh`` and stiffness ``kh`` to ground (the arm's
impedance: mass, damping, stiffness, Hogan 1985), tied to the handle (mass ``mc``, friction
``bc``) by a grip spring ``kg`` and damper ``bg``::

    mc xh'' = f - bc xh' - kg (xh - xm) - bg (xh' - xm')
    mh xm'' =   - bh xm' - kh xm - kg (xm - xh) - bg (xm' - xh')

State ``[xh, vh, xm, vm]`` (handle position, velocity, hand position, velocity) [m, m/s];
input the force ``f`` on the handle [N], held over each period (zero-order hold). A rigid
grip (``kg = inf``) is one mass ``mc + mh`` with friction ``bc + bh`` and the real spring
``kh`` to ground: state ``[x, v]`` (:func:`body_zoh`). The arm's ``kh`` is the *real
spring* of the THS: with a virtual spring at the port it is the paper's Table 1 case V.

The ideal hold (Florens et al. eqs. (2)-(4)) is the impulse-invariant image: the force
sample acts as an impulse of area ``T f[n]`` at ``t = nT``, so ``Ad = e^(AT)`` and
``Bd = T e^(AT) b``; the position transfer is then ``T h(T) z / det(zI - Ad)`` with ``h``
the impulse response (:func:`ideal_rows`; for ``kh = 0`` exactly eq. (4)).

The exact ZOH uses ``Gamma = int_0^T e^(A s) ds = T phi1(A T)`` (the top-right block of the
exponential of ``[[A, I], [0, 0]] T``, Van Loan 1978): ``Ad = I + A Gamma``, ``Bd = Gamma b``; ``A Gamma``
is kept separately (``Ad - I``, the delta-operator matrix) so that poles near ``z = 1`` keep
their relative precision.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["HAND_FIELDS", "hand_matrices", "hand_zoh", "body_zoh", "ideal_rows", "zoh_matrices",
           "hand_stiffness", "nominal_member", "members", "ranged_fields"]

#: Order of the columns of a member array: hand mass [kg], hand damping [N s/m], grip
#: stiffness [N/m] (``inf``: rigid), grip damping [N s/m], hand (arm) stiffness to ground
#: [N/m]. Functions taking members also accept 4 columns (then ``kh = 0``).
HAND_FIELDS = ("mass", "damping", "grip_stiffness", "grip_damping", "stiffness")

#: Fields whose ranges span decades: geometric nominal and log-uniform samples (lo > 0).
_LOG_FIELDS = ("grip_stiffness", "stiffness")


def hand_stiffness(member) -> np.ndarray:
    """The hand's stiffness to ground ``kh`` [N/m] of a member (0 for a 4-column member).

    Parameters
    ----------
    member : array_like, shape (..., 4) or (..., 5)

    Returns
    -------
    ndarray, shape (...)
    """
    p = np.asarray(member, dtype=float)
    return p[..., 4] if p.shape[-1] > 4 else np.zeros(p.shape[:-1])


def hand_matrices(mc: float, bc: float, member) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state-space model of handle + hand (module docstring).

    Parameters
    ----------
    mc : float > 0
        Handle mass [kg].
    bc : float >= 0
        Handle friction [N s/m].
    member : array_like, shape (..., 4) or (..., 5)
        ``(mh, bh, kg, bg[, kh])`` per member (:data:`HAND_FIELDS`), finite ``kg``.

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
    A[..., 3, 2] = -(kg + hand_stiffness(p)) / mh
    A[..., 3, 3] = -(bh + bg) / mh
    b = np.array([0.0, 1.0 / mc, 0.0, 0.0])
    return A, b


def hand_zoh(mc: float, bc: float, member, period: float):
    """Exact zero-order-hold discretisation of handle + hand, for one member or a stack.

    Parameters
    ----------
    mc, bc : float
        Handle mass [kg] and friction [N s/m].
    member : array_like, shape (..., 4) or (..., 5)
        ``(mh, bh, kg, bg[, kh])`` (:data:`HAND_FIELDS`), finite grip stiffness.
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
    return _zoh(A, b, float(period))


#: Smallest balancing scale of :func:`_phi1_balanced` [s]: its square and its inverse's stay
#: far inside double precision's range.
_BALANCE_FLOOR = 1e-150


def _phi1_balanced(A: np.ndarray, T: float) -> np.ndarray:
    """``phi1(A T)`` of a stack of ``[x, v, ...]`` systems, computed on the balanced
    ``[x, v T]`` coordinates (O(1) entries: ``(w T)^2`` and damping ``x T / m``) and mapped
    back: ``phi1(S X S^-1) = S phi1(X) S^-1``, exact for any diagonal ``S``. The scale is
    ``T`` down to :data:`_BALANCE_FLOOR`: below it ``S^-1`` would overflow (a split hold's
    share ``f T`` of a delay ``1e-308`` periods: ``inf`` and ``nan`` in ``check``) while
    ``A T`` is far below round-off against ``I`` anyway, so no balancing is needed."""
    S = np.tile([1.0, max(T, _BALANCE_FLOOR)], A.shape[-1] // 2)
    return _phi1((A * T) * S[:, None] / S[None, :]) / S[:, None] * S[None, :]


def _zoh(A: np.ndarray, b: np.ndarray, T: float):
    """``(A Gamma, Gamma b)`` of a stack of ``[x, v, ...]`` systems (:func:`hand_zoh`);
    ``Gamma = T phi1(A T)``; ``b`` one column or a stack of them."""
    F = _phi1_balanced(A, T)
    return (A * T) @ F, np.matmul(F, b[..., None])[..., 0] * T


def zoh_matrices(A, b, period: float):
    """Exact zero-order hold of ``x' = A x + b u`` over ``period``, accurate near ``A = 0``.

    Parameters
    ----------
    A : ndarray, shape (..., p, p)
        Continuous state matrix (a stack allowed) [1/s]; states ``[x, v, ...]`` in pairs
        (balanced as ``[x, v T]`` for the series).
    b : ndarray, shape (..., p)
        Input column [state units / (N s)].
    period : float > 0
        Hold time ``T`` [s].

    Returns
    -------
    Aw : ndarray, shape (..., p, p)
        ``e^(AT) - I`` [-].
    Bd : ndarray, shape (..., p)
        ``int_0^T e^(As) ds b`` [state units / N].

    Notes
    -----
    Van Loan (1978) through ``Gamma = T phi1(AT)``, as :func:`hand_zoh`.
    """
    return _zoh(np.asarray(A, float), np.asarray(b, float), float(period))


def rigid_matrices(mass, friction, stiffness):
    """``A`` (stack, 2x2) and ``b`` of ``m x'' + b x' + k x = f``, state ``[x, v]``.

    Parameters
    ----------
    mass, friction, stiffness : array_like (broadcast together)
        ``m`` [kg], ``b`` [N s/m], ``k`` [N/m].

    Returns
    -------
    A : ndarray, shape (..., 2, 2)
    b : ndarray, shape (..., 2)
    """
    m, c, k = np.broadcast_arrays(*(np.asarray(v, float) for v in (mass, friction, stiffness)))
    A = np.zeros(m.shape + (2, 2))
    A[..., 0, 1] = 1.0
    A[..., 1, 0] = -k / m
    A[..., 1, 1] = -c / m
    return A, np.stack([np.zeros(m.shape), 1.0 / m], axis=-1)


def body_zoh(mc: float, bc: float, member, period: float):
    """Exact ZOH of handle + hand, rigid grip or not, with the arm's stiffness ``kh``.

    Parameters
    ----------
    mc, bc : float
        Handle mass [kg] and friction [N s/m].
    member : array_like, shape (..., 4) or (..., 5)
        ``(mh, bh, kg, bg[, kh])``; rigid (``kg = inf``) for all or none of a stack.
    period : float > 0
        ``T`` [s].

    Returns
    -------
    Aw : ndarray, shape (..., p, p)
        ``Ad - I``; ``p = 2`` (rigid: ``[x, v]`` of ``(mc + mh) x'' + (bc + bh) x' + kh x
        = f``) or 4 (:func:`hand_zoh`).
    Bd : ndarray, shape (..., p)

    Raises
    ------
    ConfigError
        As :func:`hand_matrices`.

    Notes
    -----
    Van Loan (1978), as :func:`hand_zoh`; for ``kh = 0`` the rigid case equals
    :func:`hapsim.analysis.loop.zoh_state_space` (tested).
    """
    p = np.asarray(member, dtype=float)
    if np.all(np.isfinite(p[..., 2])):
        return hand_zoh(mc, bc, p, period)
    A, b = rigid_matrices(mc + p[..., 0], bc + p[..., 1], hand_stiffness(p))
    return _zoh(A, b, float(period))


def ideal_rows(mass, friction, stiffness, period: float):
    """Ideal-hold (impulse-invariant) image of ``m x'' + b x' + k x = f``, vectorised.

    Parameters
    ----------
    mass, friction, stiffness : float or ndarray
        ``m`` [kg] > 0, ``b`` [N s/m] >= 0, ``k`` [N/m] >= 0 (broadcast together).
    period : float > 0
        ``T`` [s].

    Returns
    -------
    tr, det, g : ndarray
        ``x[n+1] = tr x[n] - det x[n-1] + g f[n]``: ``tr``, ``det`` the trace and
        determinant of ``Ad = e^(AT)`` [-], ``g = T h(T)`` [m/N] (``h`` the position's
        impulse response, ``e^(AT)[0, 1] / m``).

    Notes
    -----
    Florens et al. eq. (4) for ``k = 0`` (``tr = 1 + a``, ``det = a``, ``g = T (1 - a) /
    b``, ``a = e^(-bT/m)``); for ``b = 0`` their Table 1 case V (our
    :mod:`hapsim.analysis.table1`): ``tr = 2 cos(w0 T)``, ``det = 1``,
    ``g = T sin(w0 T) / (m w0)``. The response to impulses ``T f[n]`` at ``nT`` has a
    numerator ``z`` only since ``h(0) = 0``.
    """
    A, b = rigid_matrices(mass, friction, stiffness)
    T = float(period)
    W = (A * T) @ _phi1_balanced(A, T)          # e^(AT) - I
    tr = 2.0 + W[..., 0, 0] + W[..., 1, 1]
    det = np.exp(-np.asarray(friction, float) * T / np.asarray(mass, float))
    g = T * W[..., 0, 1] * b[..., 1]            # e^(AT)[0, 1] / m
    return tr, det, g


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


def _field(hand, f):
    """A hand field; a hand object without ``stiffness`` (older callers) has none: 0."""
    return getattr(hand, f, 0.0)


def field_span(v) -> tuple[float, float]:
    """``(lo, hi)`` of a hand field given as a number or as a range.

    Parameters
    ----------
    v : float or tuple of float
        The field's value, or its ``(lo, hi)`` range (in the field's unit).

    Returns
    -------
    (float, float)
        ``(v, v)`` for a number.
    """
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
    return [f for f in HAND_FIELDS
            if field_span(_field(hand, f))[0] < field_span(_field(hand, f))[1]]


def nominal_member(hand) -> np.ndarray:
    """The nominal member of a hand family: the middle of every range.

    Parameters
    ----------
    hand : hapsim.scene.Hand

    Returns
    -------
    ndarray, shape (5,)
        ``(mh, bh, kg, bg, kh)``; for a stiffness range the geometric middle ``sqrt(lo hi)``
        (stiffness ranges span decades; arithmetic from 0), arithmetic otherwise.
    """
    out = []
    for f in HAND_FIELDS:
        lo, hi = field_span(_field(hand, f))
        out.append(math.sqrt(lo * hi) if f in _LOG_FIELDS and lo > 0 else 0.5 * (lo + hi))
    return np.array(out)


#: The most members a family may have: each is a closed loop's analysis (~11 us on a
#: 2-core AMD EPYC, measured with ``hapsim.api.family`` on ``configs/hand_wall.yaml``:
#: 1e6 members in 11 s), and their rows and analyses are held in memory.
MAX_MEMBERS = 10 ** 7


def members(hand, samples: int | None = None, *, grid: int = 9, seed: int = 0) -> np.ndarray:
    """The members of a hand family: every corner of the ranges, then a grid or samples.

    Parameters
    ----------
    hand : hapsim.scene.Hand
    samples : int, optional
        Number of seeded uniform random members (log-uniform for a stiffness range from lo > 0) added
        after the corners; None: a full grid of ``grid`` points per ranged field instead.
    grid : int, optional
        Points per ranged field for the grid (>= 2).
    seed : int, optional
        ``numpy.random.default_rng`` seed of the samples.

    Returns
    -------
    ndarray, shape (n, 5)
        ``(mh, bh, kg, bg, kh)`` per member; the first ``2^r`` rows are the corners (``r``
        ranged fields), the nominal member (:func:`nominal_member`) follows them.

    Raises
    ------
    ConfigError
        ``samples < 1`` or ``grid < 2``; more than :data:`MAX_MEMBERS` members (before: an
        allocation of 75 GiB for ``--grid 100000``, a traceback).
    """
    spans = [field_span(_field(hand, f)) for f in HAND_FIELDS]
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
        _not_too_many(int(samples), "--samples", f"{_count(int(samples))} samples")
        rng = np.random.default_rng(seed)
        s = np.repeat(base[None, :], int(samples), axis=0)
        for i in ranged:
            lo, hi = spans[i]
            u = rng.random(int(samples))
            s[:, i] = (lo * (hi / lo) ** u if HAND_FIELDS[i] in _LOG_FIELDS and lo > 0
                       else lo + (hi - lo) * u)
        rows.append(s)
    elif ranged:
        if int(grid) < 2:
            raise ConfigError(f"must be >= 2, got {grid!r}", key="grid")
        _not_too_many(int(grid) ** len(ranged), "--grid",
                      f"{_count(int(grid))} points on each of {len(ranged)} ranged hand "
                      "values")
        axes = []
        for i in ranged:
            lo, hi = spans[i]
            axes.append(np.geomspace(lo, hi, grid) if HAND_FIELDS[i] in _LOG_FIELDS
                        and lo > 0 else np.linspace(lo, hi, grid))
        mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(ranged))
        g = np.repeat(base[None, :], mesh.shape[0], axis=0)
        g[:, ranged] = mesh
        rows.append(g)
    return np.concatenate(rows, axis=0)


def _not_too_many(n: int, key: str, what: str) -> None:
    """Refuse a family of more than :data:`MAX_MEMBERS` members, with the count."""
    if n > MAX_MEMBERS:
        raise ConfigError(f"{what} make {_count(n)} members; at most {MAX_MEMBERS:.0e} (each "
                          "is a closed loop's analysis, ~11 us and its rows in memory)",
                          key=key)


def _count(n: int) -> str:
    """A whole count as the messages say it (3 digits; beyond a float's range, so)."""
    return f"{n:.3g}" if n < 1e300 else "more than 1e300"

"""The hold and the delay of the matrix loop as matrices: the exact zero-order hold of
``M x'' + B0 x' = F`` (whole and split), and the closed loop's state matrix and poles.

The plant is :class:`hapsim.analysis.ths.matrix_loop.MatrixLoop`'s; a rigid 1-D
:class:`~hapsim.analysis.loop.LoopModel` with the zero-order hold is its case n = 1
(:func:`~hapsim.analysis.ths.matrix_loop.as_matrix_loop`).
docs/design.md, 'A whole scene'; docs/dimensions.md, 'The THS as a matrix'.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis import loop_poles
from hapsim.analysis.loop import MAX_DELAY, LoopModel
from hapsim.analysis.ths.matrix_loop import MatrixLoop, as_matrix_loop, gain_matrices
from hapsim.errors import ConfigError

__all__ = ["zoh_matrices", "zoh_blocks", "phi_functions", "split_hold_matrices",
           "state_matrix", "closed_loop_poles"]


def split_hold_matrices(loop: MatrixLoop):
    """The split hold of ``M x'' + B0 x' = F`` for the loop's delay ``m + f``.

    Parameters
    ----------
    loop : MatrixLoop

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
    Ad, Bd = _zoh_over(loop, loop.period)
    f = float(loop.delay) % 1.0
    if f == 0.0:
        return Ad, Bd, np.zeros_like(Bd)
    return (Ad,) + _split_pieces(loop, f)


def _split_pieces(loop: MatrixLoop, f: float):
    """``(Gamma0, Gamma1)`` of :func:`split_hold_matrices` for the fraction ``f`` in
    ``(0, 1)``: the force held over the period's last ``(1 - f) T``, and over its first
    ``f T`` carried to the period's end."""
    T = loop.period
    A0, G0 = _zoh_over(loop, (1.0 - f) * T)
    _, Gf = _zoh_over(loop, f * T)
    return G0, A0 @ Gf


def zoh_matrices(loop: MatrixLoop) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of ``M x'' + B0 x' = F``.

    Parameters
    ----------
    loop : MatrixLoop

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


def _zoh_over(loop: MatrixLoop, T: float):
    """:func:`zoh_matrices` over a hold of length ``T`` [s]."""
    return zoh_blocks(loop.mass, loop.friction, T)


def phi_functions(Z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``e^Z``, ``phi1(Z) = sum Z^k/(k+1)!`` and ``phi2(Z) = sum Z^k/(k+2)!`` from one
    matrix exponential of ``[[Z, I, 0], [0, 0, I], [0, 0, 0]]`` (Higham, *Functions of
    Matrices*, 2008, Sec. 10.7.4: full relative precision for small ``Z``).

    Parameters
    ----------
    Z : ndarray, shape (n, n)

    Returns
    -------
    eZ, phi1, phi2 : ndarray, shape (n, n)
    """
    from scipy.linalg import expm
    n = Z.shape[0]
    I = np.eye(n)
    big = np.zeros((3 * n, 3 * n))
    big[:n, :n] = Z
    big[:n, n:2 * n] = I
    big[n:2 * n, 2 * n:] = I
    E = expm(big)
    return E[:n, :n], E[:n, n:2 * n], E[:n, 2 * n:]


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
    M = np.asarray(mass, float)
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    Z = -(Minv @ np.asarray(friction, float)) * T
    I = np.eye(n)
    eZ, phi1, phi2 = phi_functions(Z)
    Ad = np.zeros((2 * n, 2 * n))
    Ad[:n, :n] = I
    Ad[:n, n:] = T * phi1
    Ad[n:, n:] = eZ
    Bd = np.vstack([T * T * phi2 @ Minv, T * phi1 @ Minv])
    return Ad, Bd


def state_matrix(loop: MatrixLoop, K, B=0.0, delays=None) -> np.ndarray:
    """The closed loop's state matrix (plant + delay line + virtual coupling).

    Parameters
    ----------
    loop : MatrixLoop or hapsim.analysis.loop.LoopModel
        A 1-D loop is the case n = 1 (:meth:`MatrixLoop.from_loop`: rigid, zoh).
    K : array_like, shape (n, n) (or (n,), or a scalar: times I)
        Virtual stiffness matrix [N/m].
    B : array_like, shape (n, n) (or (n,), or a scalar), optional
        Virtual damping matrix [N s/m].
    delays : sequence of float, shape (n,), optional
        A delay per axis [periods] (several ports, each its own device): row ``i`` of
        ``F`` is computed from ``x[n-d_i]`` and applied by axis ``i``'s hold; ``d`` is
        then ``max d_i`` (``loop.delay`` is not used). Whole delays give the state
        below; a sub-sample one on any axis, each axis its own split hold
        (:func:`_per_axis_split_state_matrix`). Default: ``loop.delay`` on every axis.

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
        not ``n`` whole numbers in ``[0, MAX_DELAY]`` (key ``delays``); a 1-D loop the
        matrix loop does not model (:meth:`MatrixLoop.from_loop`).
    """
    loop = as_matrix_loop(loop)
    Kq, Bq = gain_matrices(loop, K, B)
    n, d, T = loop.dof, loop.delay, loop.period
    if delays is None and d % 1:
        # every axis the loop's delay m + f: state (x[n], v[n], x[n-1], ..., x[n-m-1],
        # h[n]), h[n] = F[n-m-1] held over the period's first f T
        # (hapsim.analysis.subsample.held_plant)
        return _per_axis_split_state_matrix(loop, Kq, Bq, [float(d)] * n)
    per = [d] * n if delays is None else list(delays)
    if delays is not None and len(per) == n and all(
            isinstance(x, (int, float)) and math.isfinite(x) and 0 <= x <= MAX_DELAY
            for x in per) and any(float(x) % 1 for x in per):
        return _per_axis_split_state_matrix(loop, Kq, Bq, [float(x) for x in per])
    if len(per) != n or not all(isinstance(x, int) and 0 <= x <= MAX_DELAY for x in per):
        raise ConfigError(f"must be {n} delays in [0, {MAX_DELAY}] [periods], got "
                          f"{delays!r}", key="delays")
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


def _per_axis_split_state_matrix(loop: MatrixLoop, Kq, Bq, per) -> np.ndarray:
    """:func:`state_matrix` with a delay ``m_i + f_i`` per axis (several ports, each its
    own device and hold). Over ``[nT, (n+1)T)`` axis ``i``'s force is ``F_i[n-m_i-1]``
    for the first ``f_i T``, then ``F_i[n-m_i]``: each is a column of the split hold
    (:func:`split_hold_matrices` with axis ``i``'s ``f_i``: ``Gamma0`` over the last
    ``(1 - f_i) T``, ``Gamma1`` over the first ``f_i T`` carried to the period's end;
    modified z-transform, Franklin, Powell & Workman sec. 4.3), so
    ``[x; v][n+1] = Ad [x; v] + sum_i Gamma0_i F_i[n-m_i] + Gamma1 h[n]`` with
    ``h_i[n] = F_i[n-m_i-1]`` (zero columns for a whole ``f_i``), and
    ``h_i[n+1] = F_i[n-m_i]``. State ``(x[n], v[n], x[n-1], ..., x[n-M-1], h[n])``,
    ``M = max m_i``: ``n (M + 4)`` states. Whole delays on every axis give the same
    poles as :func:`state_matrix`'s whole form (with ``n`` more zeros)."""
    n, T = loop.dof, loop.period
    ms = [int(math.floor(x)) for x in per]
    fs = [x - m for x, m in zip(per, ms)]
    M = max(ms)
    Ad, Bd = _zoh_over(loop, T)
    G0, G1 = np.zeros_like(Bd), np.zeros_like(Bd)
    for f in sorted(set(fs)):
        cols = [i for i in range(n) if fs[i] == f]
        if f == 0.0:
            G0[:, cols] = Bd[:, cols]
            continue
        g0, g1 = _split_pieces(loop, f)
        G0[:, cols] = g0[:, cols]
        G1[:, cols] = g1[:, cols]
    N = n * (M + 4)
    A = np.zeros((N, N))
    A[:2 * n, :2 * n] = Ad

    def pos(k):   # block of x[n - k]
        return slice(0, n) if k == 0 else slice((k + 1) * n, (k + 2) * n)
    h = slice((M + 3) * n, (M + 4) * n)
    Fx, Fxp = -(Kq + Bq / T), Bq / T          # F[n-k] = Fx x[n-k] + Fxp x[n-k-1]
    for m in sorted(set(ms)):
        rows = np.array([[float(x == m)] for x in ms])
        A[:2 * n, pos(m)] += G0 @ (rows * Fx)
        A[:2 * n, pos(m + 1)] += G0 @ (rows * Fxp)
        A[h, pos(m)] += rows * Fx
        A[h, pos(m + 1)] += rows * Fxp
    A[:2 * n, h] += G1
    for k in range(1, M + 2):     # x[n+1-k] <- x[n-(k-1)]
        A[pos(k), pos(k - 1)] = np.eye(n)
    return A


def closed_loop_poles(loop, K, B=0.0) -> np.ndarray:
    """The closed loop's poles [-], for a loop of any dimension.

    Parameters
    ----------
    loop : MatrixLoop or hapsim.analysis.loop.LoopModel
    K, B : float or array_like
        Virtual stiffness [N/m] and damping [N s/m]: scalars for a 1-D loop; matrices
        (or a diagonal, or a scalar times I) for a :class:`MatrixLoop`.

    Returns
    -------
    ndarray of complex
        A :class:`MatrixLoop`: the eigenvalues of :func:`state_matrix`, shape
        ``(n (d + 3),)``, largest ``|z|`` first (the MIMO characteristic's roots: Li,
        Tavakoli & Huang 2014, stability from these, not per axis). A 1-D
        :class:`~hapsim.analysis.loop.LoopModel`: the roots of ``P K + Q B + R``
        (:func:`hapsim.analysis.loop_poles.closed_loop_poles`, the companion matrix in
        ``z`` Newton-polished in ``w = z - 1``, in its order), which is the case n = 1
        to round-off and also covers the ideal hold, a compliant grip and a correction.

    Raises
    ------
    ConfigError
        ``K`` or ``B`` not finite or of the wrong shape; for a 1-D loop, ``|K| T^2/m`` or
        ``|B| T/m`` above :data:`hapsim.analysis.loop.MAX_PRODUCT`.
    """
    if isinstance(loop, LoopModel):
        return loop_poles.closed_loop_poles(loop, K, B)
    z = np.linalg.eigvals(state_matrix(loop, K, B))
    return z[np.argsort(-np.abs(z), kind="stable")]
